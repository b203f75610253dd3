"""One writer for every foreign case: a :class:`~whitecap.cases.Case` -> a whitecap run directory
(``import``, and ``foam`` over a foreign sequence, which imports it as a bare sequence, its frames
written by the foam pass as it reads them: :func:`write_case`'s ``then``).

    RUN/run.json                 obstacles (one per shape, with its role) and per-frame body poses
    RUN/fluid/fluid_NNNNN.ply    the fluid frames, converted (z up)
    RUN/geometry/NAME.ply        one mesh per shape, in its rest placement (first frame)

Obstacle entries have the contract of whitecap's own (``config.Obstacle``
dumped into ``run.json``): ``mesh`` and ``render_mesh`` are paths relative to
the run directory (the renderer, the viewer and the Blender add-on look there
when the run names no ``extra.scene_dir``), so a run directory stays valid when
moved. Each entry adds ``name``, ``role`` (``container``, ``obstacle`` or
``body``) and ``source`` (where it came from in the solver's output). Moving
shapes come first, so that ``frames[i].bodies[k]`` is the pose of obstacle
``k`` and fixed shapes need no pose.

The run's identity (``simulation``) is :func:`whitecap.io.run.source_identity`
of the fluid files plus the case's other inputs, so a rerun on the same output
resumes (frames already converted are skipped) and a run of another case is
never mixed in.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InputError, WhitecapError
from ..io import read, write, write_mesh, write_text
from ..io.lock import LOCK_FILE, run_lock
from ..io.mesh import SurfaceMesh
from ..io.record import Obstacle
from ..io.run import (
    DOMAIN_RULE,
    RUN_JSON,
    RunInfo,
    claim_run_dir,
    domain_text,
    flow_domain,
    frame_name,
    remove_run,
    sequence_bounds,
    source_identity,
)
from ..io.writer import FrameWriter
from ..progress import console, progress
from . import ROLES, Case, CaseShape

GEOMETRY_DIR = "geometry"
#: Render looks of imported shapes: the tank in light grey stone, fixed obstacles in terracotta clay (so a
#: building stands out against the tank's floor), bodies in orange plastic.
ROLE_LOOKS = {
    "container": {"material": "stone", "color": [0.6, 0.62, 0.65]},
    "obstacle": {"material": "clay", "color": [0.7, 0.36, 0.22]},
    "body": {"material": "plastic", "color": [0.9, 0.5, 0.08]},
}


def _safe_name(name: str, taken: set[str]) -> str:
    base = "".join(c if c.isalnum() or c in "-_" else "_" for c in name) or "shape"
    out, k = base, 1
    while out in taken:
        k += 1
        out = f"{base}_{k}"
    taken.add(out)
    return out


def check_case(case: Case) -> None:
    """What write_case relies on; an InputError names the case and the field."""
    where = str(case.source)
    if not case.fluid:
        raise InputError(f"{where}: no fluid frames found")
    if not (case.frame_dt > 0):
        raise InputError(f"{where}: the time between frames is unknown or not positive ({case.frame_dt!r})")
    if not (case.particle_radius > 0):
        raise InputError(f"{where}: the particle radius is unknown or not positive ({case.particle_radius!r})")
    if case.times is not None and len(case.times) != len(case.fluid):
        raise InputError(f"{where}: {len(case.times)} frame times for {len(case.fluid)} fluid frames")
    for s in case.shapes:
        if s.role not in ROLES:
            raise InputError(f"{where}: shape {s.name!r}: role {s.role!r} is not one of {', '.join(ROLES)}")
        if len(s.faces) == 0:
            raise InputError(f"{where}: shape {s.name!r} ({s.source}): empty mesh")
        if s.poses is not None and len(s.poses) != len(case.fluid):
            raise InputError(f"{where}: shape {s.name!r} ({s.source}): {len(s.poses)} poses for "
                             f"{len(case.fluid)} fluid frames")


def ordered_shapes(case: Case) -> list[CaseShape]:
    """Moving shapes first (their index is their index in ``frames[i].bodies``), then the rest."""
    return [s for s in case.shapes if s.poses is not None] + [s for s in case.shapes if s.poses is None]


def case_identity(case: Case) -> str:
    """The identity of the simulation a case holds: its fluid files, its up axis, and its
    shapes (names, roles, vertex sums), so a changed boundary reading makes a new run."""
    shapes = [[s.name, s.role, s.source, float(np.asarray(s.vertices, np.float64).sum()), len(s.faces),
               None if s.poses is None else len(s.poses)] for s in case.shapes]
    return source_identity([p for _, p in case.fluid], case.up,
                           {"solver": case.solver, "shapes": shapes, "options": case.fluid_reader_options})


def _domain(case: Case, opts: dict) -> tuple[dict[str, list[float]], str]:
    """The case's own domain when it states one; else :func:`whitecap.io.run.flow_domain` of the
    fluid over all frames and the shapes. With the rule it follows, printed."""
    if case.domain is not None:
        lo, hi = case.domain
        domain, rule = {"lower": [float(x) for x in lo], "upper": [float(x) for x in hi]}, case.domain_rule
    else:
        boxes = [(np.asarray(s.vertices, np.float64).min(0), np.asarray(s.vertices, np.float64).max(0))
                 for s in case.shapes]
        flow = sequence_bounds([p for _, p in case.fluid], **opts)
        boxes += [flow] if flow is not None else []
        if not boxes:  # (a bare sequence: foam's input)
            raise InputError(f"{case.source}: all {len(case.fluid)} frames are empty (no particles), so there is "
                             "nothing to make diffuse particles from")
        lo, hi = np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)
        domain, rule = flow_domain((lo, hi), case.particle_radius), DOMAIN_RULE
    console.print(f"domain: {domain_text(domain)} ({rule})", soft_wrap=True)
    return domain, rule


def _new_info(case: Case, identity: str, opts: dict) -> RunInfo:
    r = case.particle_radius
    mass = case.particle_mass if case.particle_mass else case.rest_density * (2 * r) ** 3
    domain, rule = _domain(case, opts)
    info = RunInfo(
        particle_radius=float(r), rest_density=float(case.rest_density), particle_mass=float(mass),
        gravity=[float(g) for g in case.gravity], domain=domain, frame_rate=1.0 / case.frame_dt,
        extra={"source": str(case.source), "solver": case.solver, "seed": 0, "domain_rule": rule, **case.notes},
    )
    info.simulation = identity
    return info


def _obstacle_entry(shape: CaseShape, rel: str) -> Obstacle:
    return Obstacle.model_validate({
        "name": shape.name, "role": shape.role, "source": shape.source, "mesh": rel, "render_mesh": rel,
        "translate": [0.0, 0.0, 0.0], "rotate": [0.0, 0.0, 0.0], "scale": 1.0,
        **ROLE_LOOKS[shape.role], **(shape.look or {})})  # a shape's own look (e.g. glass) wins


def write_case(case: Case, out: str | Path, show_progress: bool = True, force: bool = False,
               then: Callable[[RunInfo], RunInfo] | None = None) -> RunInfo:
    """Write ``case`` as a run directory at ``out`` (made if missing); resumable.

    ``out`` follows :func:`whitecap.io.run.claim_run_dir`: a run of another simulation is refused
    (its frames would be mixed with this case's) unless ``force``, which replaces it whole; a folder
    of files whitecap did not write is refused. An import that fails on bad input leaves nothing
    behind but what was there before.

    With ``then``, the fluid frames' files are not written here: their entries (times, body poses) are,
    and frames listed before stay listed; ``then(info)`` runs in their place, under the same lock and
    with the same clean-up on bad input, and its result is returned. That is ``foam`` over a foreign
    sequence, which writes each frame into the run as its pass reads it (:func:`reader_options`): each
    frame is read once, and its file written by the pass's writer thread while the next is computed.
    """
    out = Path(out)
    check_case(case)
    identity = case_identity(case)
    state = claim_run_dir(out, identity, force=force)
    created = not out.exists()
    with run_lock(out, "import"):
        if state == "replace":
            remove_run(out)
        old = RunInfo.load(out) if state == "same" else None
        try:
            info = _write(case, out, identity, old, show_progress, frames=then is None)
            return info if then is None else then(info)
        except WhitecapError:
            if old is None:  # bad input met half-way: take back what this import wrote
                remove_run(out)
            raise
        finally:
            if not (out / RUN_JSON).exists():
                (out / LOCK_FILE).unlink(missing_ok=True)
                if created:
                    with contextlib.suppress(OSError):
                        out.rmdir()


def reader_options(case: Case) -> dict:
    """How the case's fluid files are read: :func:`whitecap.io.read`'s options (up axis, solver's own)."""
    return {"up": case.up, **case.fluid_reader_options}


def _write(case: Case, out: Path, identity: str, old: RunInfo | None, show_progress: bool,
           frames: bool = True) -> RunInfo:
    opts = reader_options(case)
    info = old if old is not None else _new_info(case, identity, opts)
    # Shapes: built once by the reader, written once here (rewritten, identical, on a resume).
    shapes = ordered_shapes(case)
    taken: set[str] = set()
    rels = [f"{GEOMETRY_DIR}/{_safe_name(s.name, taken)}.ply" for s in shapes]
    info.obstacles = [_obstacle_entry(s, rel) for s, rel in zip(shapes, rels)]
    info.save(out)  # the run records its files before any is written (only those are ever removed)
    for s, rel in zip(shapes, rels):
        write_mesh(out / rel, SurfaceMesh(np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int32),
                                          source=s.source or s.name))
    moving = [s.poses for s in shapes if s.poses is not None]  # each moving shape's poses by frame
    times = case.times if case.times is not None else [i * case.frame_dt for i, _ in case.fluid]
    done = {i for i, rel in info.files("fluid") if (out / rel).is_file()}
    todo = [(k, i, p) for k, (i, p) in enumerate(case.fluid) if i not in done] if frames else []
    if frames and len(todo) < len(case.fluid):
        console.print(f"import: {len(case.fluid) - len(todo)} of {len(case.fluid)} frames already in {out}")
    bar = progress(disable=not (show_progress and frames))
    # Frames are written by a thread while the next is read (each file, then the run.json that lists it, in
    # that order); leaving the block waits for them, so nothing is still being written after an error.
    with bar, FrameWriter(name="whitecap-import-writer") as writer:
        task = bar.add_task("import", total=len(case.fluid), completed=len(case.fluid) - len(todo), info="")
        for k, index, path in todo:
            fr = read(path, **opts)
            fr.check_finite()
            fr.time = float(times[k])
            rel = frame_name("fluid", index)
            writer.submit(functools.partial(write, out / rel, fr), "fluid")
            info.set_file(index, "fluid", rel, fr.time)
            if moving:
                info.set_bodies(index, [poses[k] for poses in moving])
            # after every frame, a snapshot (the loop goes on changing info): an interrupted import resumes here
            writer.submit(functools.partial(write_text, out / RUN_JSON, info.dumps()), "run.json")
            bar.update(task, advance=1, info=f"{len(fr):,} fluid")
    for k, (index, _) in enumerate(case.fluid):  # poses of frames converted earlier, too
        info.frame(index).time = float(times[k])
        if moving:
            info.set_bodies(index, [poses[k] for poses in moving])
    info.save(out)
    info.extra["out"] = str(out)  # for the caller's message; not saved
    return info
