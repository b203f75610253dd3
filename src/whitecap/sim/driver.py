"""The `simulate` loop: frames, output files, checkpoints, resume, progress.

Per output frame the solver advances ``substeps`` steps, then the frame is
written to ``fluid/fluid_NNNNN.ply`` (temporary file, then rename) and
``run.json`` is updated. Every ``output.checkpoint_interval`` frames (and at
the last one) the full state goes to ``checkpoint.npz``; ``resume`` restarts
from it and produces the same remaining frames as an uninterrupted run.

The files, ``run.json`` and the checkpoints are written by a background thread
(:class:`whitecap.io.writer.FrameWriter`) while the solver steps on, in the
order they were handed over: ``run.json`` lists a frame's file only once it is
complete, and the checkpoint of frame k is written only after every frame up
to k is on disk and recorded. Its queue is bounded (``WRITER_QUEUE`` jobs), and
an error of the writer (a full disk) is raised in the loop at the next frame.

Frame hooks (:class:`FrameHook`: the foam stage) see each frame after the
solver; they may add files and carry state in the checkpoint. This keeps the
solver free of imports from later stages.
"""

from __future__ import annotations

import abc
import contextlib
import functools
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..config import DEFAULT_ARCH, Scene, scene_from_dict, with_options
from ..errors import InputError, WhitecapError
from ..io import ParticleFrame, write, write_text
from ..io.atomic import sweep_temps, write_arrays
from ..io.lock import LOCK_FILE, run_lock
from ..io.run import (
    CHECKPOINT,
    IDENTITY_IGNORES,
    RUN_JSON,
    SCENE_FILE,
    WALLS,
    RunInfo,
    check_scene_file,
    claim_run_dir,
    frame_name,
    remove_run,
    scene_sha256,
    simulation_identity,
)
from ..io.writer import DEFAULT_QUEUE, FrameWriter
from ..progress import progress
from ..timing import timer
from . import runtime

if TYPE_CHECKING:  # a type only: build_solver imports the solver's modules when it runs
    from .obstacles import Obstacles

#: Write frames, run.json and checkpoints in a background thread: True, False (in the loop), or None:
#: on a GPU only. On the CPU, Taichi's kernels hold Python's global lock, so the thread could only write
#: between kernels and competed with the solver: 125k particles ran 11-13 % slower with it on 2 cores
#: (benchmarks/bench_output.py), where a checkpoint every frame costs 1-3 % of the run anyway.
BACKGROUND_WRITER: bool | None = None
#: Jobs the background writer may hold waiting (each a copy of a frame, run.json or the state).
WRITER_QUEUE = DEFAULT_QUEUE
#: The writer of the simulation now running (None: write at once), used by _save_checkpoint.
_WRITER: FrameWriter | None = None


class FrameHook(abc.ABC):
    """A stage that runs inside `simulate`, after the solver, on every frame it writes.

    The loop calls, in this order: :meth:`restore` (on a resume, with what :meth:`checkpoint`
    gave at the frame resumed from), :meth:`on_start` once, then per frame :meth:`on_frame`
    and :meth:`write`, :meth:`checkpoint` at each checkpoint, and :meth:`finish` once the last
    frame is on disk. A subclass that lacks one of the abstract methods cannot be made
    (TypeError at construction), and one without a ``name`` cannot be defined.
    """

    #: The hook's files go to ``<name>/``, its entry in run.json's frames and its checkpoint
    #: arrays are named by it, as is its timer in ``--profile``.
    name: str

    def __init_subclass__(cls, **kw) -> None:
        super().__init_subclass__(**kw)
        if not isinstance(getattr(cls, "name", None), str):
            raise TypeError(f"{cls.__qualname__}: a frame hook needs a class attribute 'name' (a str)")

    @abc.abstractmethod
    def on_start(self, solver, out: Path, info: RunInfo, last_frame: int) -> None:
        """Before the first frame: the solver built for this run (its obstacles, ``solver.obstacles``),
        the run directory, its record and the index of the run's last frame."""

    @abc.abstractmethod
    def on_frame(self, frame: ParticleFrame, index: int, dt: float, out: Path, info: RunInfo) -> str | None:
        """Compute frame ``index`` from the fluid ``frame`` (``dt``: the time since the last frame);
        return the path, relative to ``out``, of the file it makes (written by :meth:`write`), or None."""

    def write(self, writer=None) -> None:
        """Write the files the last :meth:`on_frame` made (timed as output, apart from on_frame): handed to
        ``writer`` (io.writer.FrameWriter's ``submit``: the run's writer thread, or at once on the CPU) when
        given, so that they are written before the frame's run.json (on a lane of their own: beside its other
        files)."""

    @abc.abstractmethod
    def checkpoint(self) -> dict[str, np.ndarray]:
        """The hook's state to resume from, as arrays (empty when it has none)."""

    @abc.abstractmethod
    def restore(self, data: dict[str, np.ndarray]) -> None:
        """Take back the state :meth:`checkpoint` gave (called before :meth:`on_start`)."""

    def status(self) -> str:
        """A short text for the progress bar ('' for none)."""
        return ""

    def finish(self) -> None:
        """After the last frame is on disk: say what the run made (not called on an error)."""


def run_info_for(scene: Scene, solver) -> RunInfo:
    return RunInfo(
        particle_radius=scene.solver.particle_radius,
        rest_density=scene.solver.rest_density,
        particle_mass=float(solver.mass),
        gravity=list(scene.domain.gravity),
        domain={"lower": list(scene.domain.lower), "upper": list(scene.domain.upper)},
        frame_rate=scene.solver.frame_rate,
        simulation=simulation_identity(scene.to_toml()),
        obstacles=[o.model_dump() for o in scene.obstacle],
        extra={"kernel_support": solver.h, "name": scene.name, "seed": scene.seed, "scene_dir": str(scene.base_dir),
               "solid_walls": list(WALLS)},
    )


def build_solver(scene: Scene, arch: str = DEFAULT_ARCH, frames: int | None = None):
    """Initialise Taichi and build the solver with obstacles, emitters and sinks from the scene
    (its arrays sized for ``frames``, when more than the scene's, see sim.emitters.capacity)."""
    from .emitters import Sources, capacity
    from .pbf import PBFSolver, estimate_particle_count, fits_in_memory, lattice_points

    n_est = capacity(scene, estimate_particle_count(scene), frames)
    fits, need = fits_in_memory(n_est, scene.solver.max_neighbors)
    if not fits:
        raise WhitecapError(
            f"the fluid blocks hold about {n_est:,} particles, needing about {need / 2**30:.1f} GiB, "
            "more than this machine has free; increase solver.particle_radius or shrink the fluid"
        )
    runtime.init(arch)
    pos, vel = lattice_points(scene)
    obstacles: Obstacles | None = None
    if scene.obstacle:
        from .obstacles import load_obstacles

        obstacles = load_obstacles(scene)
    check_fluid_blocks(scene, obstacles)
    if obstacles:
        keep = obstacles.outside_mask(pos)
        pos, vel = pos[keep], vel[keep]
    cap = capacity(scene, len(pos), frames)
    if len(pos) > cap:
        raise InputError(f"{scene.source}: solver.max_particles: {cap:,} is fewer than the {len(pos):,} particles "
                         "of the initial fluid; raise it")
    solver = PBFSolver(scene, pos, vel, capacity=cap)
    if scene.emitter or scene.sink:
        solver.sources = Sources(scene, solver, obstacles, where=f"{scene.source}: ")
    if obstacles:
        solver.colliders.append(obstacles.collider(solver))
        solver.obstacles = obstacles  # the frame hooks' (the diffuse particles'): the same SDFs and motion laws
    return solver


def check_fluid_blocks(scene: Scene, obstacles=None) -> None:
    """InputError naming a [[fluid]] block that would give no particle at all."""
    from .pbf import block_lattice

    r = scene.solver.particle_radius
    for k, b in enumerate(scene.fluid):
        lo, hi = b.bounds()
        where = f"fluid[{k}] (from {[round(v, 6) for v in lo]} to {[round(v, 6) for v in hi]})"
        g = block_lattice(scene, b)
        if len(g) == 0:
            raise InputError(f"{where}: holds no particle: it is too small for the particle spacing "
                             f"2r = {2 * r:g} m; enlarge it or lower solver.particle_radius")
        if obstacles and not obstacles.outside_mask(g.astype(np.float32)).any():
            raise InputError(f"{where}: lies entirely inside the obstacles, so it holds no particle; move it out")


def _save_checkpoint(out: Path, index: int, solver, hooks, host: dict | None = None) -> None:
    """The state at frame ``index`` to ``checkpoint.npz``: gathered here, written by the running
    simulation's background writer (after every file handed to it before), else at once. ``host``: the
    solver's particles as that frame's output read them back (PBFSolver.arrays)."""
    data = {f"solver/{k}": v for k, v in solver.checkpoint(host).items()}
    for h in hooks:
        data.update({f"{h.name}/{k}": v for k, v in h.checkpoint().items()})
    data["frame"] = np.int64(index)
    writer = _WRITER
    if writer is None:
        write_arrays(out / CHECKPOINT, data)
        return
    # The solver and the hooks go on (a hook's state may be its live arrays): the writer gets copies.
    owned = {k: np.array(v, copy=True) for k, v in data.items()}
    writer.submit(functools.partial(write_arrays, out / CHECKPOINT, owned), "checkpoint")


def _load_checkpoint(out: Path) -> tuple[int, dict]:
    p = out / CHECKPOINT
    try:
        z = np.load(p)
        data = {k: z[k] for k in z.files}
    except Exception as exc:
        raise InputError(f"{p}: unreadable checkpoint ({exc}); start over with `whitecap simulate --force`") from None
    return int(data.pop("frame")), data


def _sub(data: dict, prefix: str) -> dict:
    return {k[len(prefix) + 1 :]: v for k, v in data.items() if k.startswith(prefix + "/")}


def scene_changes(scene: Scene, out: Path) -> list[str]:
    """Dotted keys whose resolved values differ between ``scene`` and the run's ``scene.toml``
    (a hint for the message: whether a run may continue is decided by its identity in run.json).

    ``output.frames`` does not count (a run may be extended), nor does ``[cluster]`` (where frames run).
    """
    old_file = Path(out) / SCENE_FILE
    if not old_file.is_file():
        return []
    try:
        old = scene_from_dict(tomllib.loads(old_file.read_bytes().decode("utf-8")), str(old_file)).to_toml()
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, InputError):
        return ["scene.toml (unreadable)"]
    a, b = _flatten(tomllib.loads(old)), _flatten(tomllib.loads(scene.to_toml()))
    missing = object()
    return [k for k in sorted(a.keys() | b.keys())
            if not any(k == ig or k.startswith(ig + ".") for ig in IDENTITY_IGNORES)
            and a.get(k, missing) != b.get(k, missing)]


def _flatten(d: dict, prefix: str = "") -> dict:
    flat = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else k
        if isinstance(v, dict):
            flat.update(_flatten(v, key))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for i, x in enumerate(v):
                flat.update(_flatten(x, f"{key}[{i}]"))
        else:
            flat[key] = v
    return flat


def refuse_changed_scene(scene: Scene, out: Path) -> None:
    """A one-line error unless ``out`` is a run of this very scene: the identity run.json records
    (the simulation its frames come from) must be the scene's. Continuing a run of another scene,
    an imported case or a converted sequence would mix two simulations in one run."""
    out = Path(out)
    identity = simulation_identity(scene.to_toml())
    try:
        claim_run_dir(out, identity)
    except InputError:
        changed = [] if RunInfo.load(out).extra.get("source") else scene_changes(scene, out)
        if changed:
            shown = ", ".join(changed[:8]) + (f" and {len(changed) - 8} more" if len(changed) > 8 else "")
            what = f"was made from another scene (changed: {shown})"
        else:
            what = f"holds another simulation ({_made_from(out)})"
        raise InputError(
            f"{out / RUN_JSON}: the run {what}; a run continues only with its own scene: "
            "simulate with --force to replace it, or use another --out"
        ) from None


def _refuse_restart_without_checkpoint(out: Path) -> None:
    """A resume finds no checkpoint: starting over is harmless only when the run holds no more than a
    first frame (a simulate stopped before its first checkpoint). A run with later frames and none
    (one written by `foam --out` from a run, or whose checkpoint was removed) is not replaced without
    --force."""
    later = [f.index for f in RunInfo.load(out).frames if f.files and f.index > 0]
    if later:
        raise InputError(f"{out}: holds {len(later)} frames after the first but no {CHECKPOINT} to resume from "
                         "(a run converted by `foam --out`, or its checkpoint was removed); simulate with --force to "
                         "start it over")


def _made_from(out: Path) -> str:
    info = RunInfo.load(out)
    if info.extra.get("source"):
        return f"converted from {info.extra['source']}"
    return f"identity {info.simulation or 'unknown'}; its scene.toml may have been edited since"


@dataclass(frozen=True)
class SimulateJob:
    """What one ``simulate`` does: the options of ``whitecap simulate`` and of
    :func:`whitecap.pipeline.simulate`, with their defaults, defined here once (the CLI and the
    pipeline build one; :func:`run_simulation` takes it).

    ``frames`` replaces the scene's ``output.frames``; ``resume`` continues from the last
    checkpoint, and only with the run's own scene (else an error lists the changed keys);
    ``force`` starts over in a directory that holds a run; ``arch`` is the Taichi backend
    (cpu, cuda, auto); ``foam`` generates diffuse particles when the scene's ``[foam]`` is on;
    ``profile`` prints the time per phase (both read by the pipeline, which adds the hooks and
    the report).
    """

    frames: int | None = None
    resume: bool = False
    force: bool = False
    arch: str = DEFAULT_ARCH
    foam: bool = True
    profile: bool = False
    show_progress: bool = True


def run_simulation(
    scene: Scene,
    out: str | Path,
    job: SimulateJob | None = None,
    hooks: list[FrameHook] | tuple[FrameHook, ...] = (),
    solver=None,
    **options,
) -> RunInfo:
    """Simulate ``scene`` into the run directory ``out`` as ``job`` says (``options``, its
    field names, build one or replace its fields); return its RunInfo.

    The old run is replaced only once everything is set up and the first new
    frame is about to be written, so a failing set-up leaves it intact.
    ``hooks`` (:class:`FrameHook`) run after the solver on every frame.
    """
    job = with_options(SimulateJob, job, options)
    for h in hooks:
        if not isinstance(h, FrameHook):
            raise TypeError(f"hooks: {type(h).__qualname__} is not a whitecap.sim.driver.FrameHook")
    out = Path(out)
    nframes = scene.output.frames if job.frames is None else int(job.frames)
    if nframes < 1:
        raise InputError(f"--frames: must be at least 1 (got {nframes})")
    created = not out.exists()
    try:
        with run_lock(out, "simulate"):
            return _simulate(scene, out, nframes, job.resume, job.force, job.arch, hooks, job.show_progress, solver)
    finally:
        if out.is_dir() and not (out / RUN_JSON).exists():  # refused, or failed, where no run was: leave nothing
            (out / LOCK_FILE).unlink(missing_ok=True)
            if created:
                with contextlib.suppress(OSError):
                    out.rmdir()


def _simulate(scene: Scene, out: Path, nframes: int, resume: bool, force: bool, arch: str, hooks, show_progress,
              solver) -> RunInfo:
    global _WRITER
    identity = simulation_identity(scene.to_toml())
    has_run = (out / RUN_JSON).exists()
    if has_run and not resume and not force:
        raise WhitecapError(f"{out}: already holds a run; pass --resume to continue it or --force to start over")
    if resume and has_run and not force:
        refuse_changed_scene(scene, out)
    # Files whitecap did not write are refused even with --force; --force replaces another simulation.
    same = claim_run_dir(out, identity, force=True) == "same"
    check_scene_file(out)
    for d in (out, out / "fluid", out / "diffuse"):  # temporary files of a writer killed mid-file (kill -9)
        sweep_temps(d)
    from_checkpoint = resume and same and (out / CHECKPOINT).exists()
    if resume and same and not from_checkpoint and not force:
        _refuse_restart_without_checkpoint(out)
    start_frame, data = _load_checkpoint(out) if from_checkpoint else (0, {})

    # Set up everything (particle count and memory, fluid, obstacles) before touching the old run.
    if solver is None:
        with timer("setup"):
            solver = build_solver(scene, arch, nframes)
    info = run_info_for(scene, solver)
    if from_checkpoint:
        solver.restore(_sub(data, "solver"))
        for h in hooks:
            h.restore(_sub(data, h.name))
        info = RunInfo.load(out)
        info.truncate(start_frame)
    for h in hooks:
        h.on_start(solver, out, info, nframes)

    bodies = next((c for c in solver.colliders if getattr(c, "moving", False)), None)

    def emit(index: int, dt: float) -> dict:
        """Frame ``index``: its files and its run.json, handed to ``writer`` in that order; returns the solver's
        particles as read back for it (PBFSolver.arrays), which the frame's checkpoint takes too."""
        if bodies is not None:  # moving bodies: their pose at this frame, as run.json records it
            info.set_bodies(index, bodies.body_records())
        with timer("output"):
            # host copies no earlier frame still held shares (the writer may keep them meanwhile): the fluid file's
            # records, made on the device, which the writer writes as they are (ParticleFrame.from_records)
            a = solver.arrays(records=True)
            rec = a.get("records")
            frame = (ParticleFrame.from_records(rec, time=solver.time) if rec is not None else
                     ParticleFrame(a["positions"], a["velocities"], a["ids"], a["density"], time=solver.time))
            info.frame(index).particles = len(frame)  # the count varies with emitters and sinks
            for fmt in scene.output.formats:
                rel = frame_name("fluid", index, fmt)
                writer.submit(functools.partial(write, out / rel, frame), "fluid", lane=f"fluid_{fmt}")
                info.set_file(index, "fluid" if fmt == "ply" else f"fluid_{fmt}", rel, solver.time)
        for h in hooks:  # on this thread: a hook computes on the device, then hands its files to the writer
            with timer(h.name):
                rel = h.on_frame(frame, index, dt, out, info)
            with timer("output"):
                h.write(writer)
            if rel:
                info.set_file(index, h.name, rel, solver.time)
        with timer("output"):
            # Its text now (the loop goes on changing info), saved by the writer after the frame's files.
            writer.submit(functools.partial(write_text, out / RUN_JSON, info.dumps()), "run.json")
        return a

    scene_text = scene.to_toml()
    if not from_checkpoint:  # else frame start_frame and those before it are done: never recompute them
        if has_run:
            remove_run(out)  # what the old run recorded as its own; derived files become stale by identity
        info.extra["scene_sha256"] = scene_sha256(scene_text)
        info.save(out)  # the directory is a run (of this simulation) before anything else lands in it
    write_text(out / SCENE_FILE, scene_text)
    if info.extra.get("scene_sha256") != scene_sha256(scene_text):
        info.extra["scene_sha256"] = scene_sha256(scene_text)
        info.save(out)
    background = BACKGROUND_WRITER if BACKGROUND_WRITER is not None else runtime.on_gpu()
    writer: FrameWriter | _InlineWriter = FrameWriter(WRITER_QUEUE) if background else _InlineWriter()
    _WRITER = writer if isinstance(writer, FrameWriter) else None
    try:
        _frames(scene, out, nframes, start_frame, from_checkpoint, solver, hooks, emit, show_progress)
        with timer("output"):  # (its wait is output.wait, as a full queue's is)
            writer.flush()  # every file on disk, or the writer's error (a full disk) raised here
    finally:
        _WRITER = None
        writer.close()  # on an error or Ctrl-C, what was handed over is still written (each file whole)
    if solver.stats.neighbor_overflow:
        from ..progress import console

        kept = solver.grid.max_neighbors
        console.print(
            f"[yellow]warning:[/] {solver.stats.neighbor_overflow} neighbour pairs exceeded "
            + (f"solver.max_neighbors={kept}; raise it for accuracy" if not solver.grid.cut else
               f"the {kept} entries a list holds at {solver.grid.capacity:,} particles (32-bit indices); "
               "fewer particles keep them all")
        )
    for h in hooks:
        h.finish()
    return info


#: Automatic checkpoint interval (``output.checkpoint_interval = 0``) per arch. Measured (benchmarks/bench_output.py,
#: issue 31): on 2 CPU cores a checkpoint costs 1-3% of a frame's wall time at 10k-125k particles, so every frame;
#: on an H100 (581k particles, foam off) 40 ms against about 38 ms of solver a frame, so every 20th frame keeps it
#: under 5% even where its writing is not overlapped.
AUTO_CHECKPOINT_INTERVAL = {"cpu": 1, "cuda": 20}


def checkpoint_interval(scene: Scene) -> int:
    """Frames between checkpoints: ``output.checkpoint_interval``, or by the arch when it is 0 (automatic)."""
    return scene.output.checkpoint_interval or AUTO_CHECKPOINT_INTERVAL.get(runtime.current() or "cpu", 1)


class _InlineWriter:
    """FrameWriter's interface, writing at once in the caller's thread (``BACKGROUND_WRITER = False``)."""

    def submit(self, job, label: str = "output", lane: str | None = None) -> None:
        job()

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass


def _frames(scene: Scene, out: Path, nframes: int, start_frame: int, from_checkpoint: bool, solver, hooks, emit,
            show_progress: bool) -> None:
    """Frame 0 (a new run), then step, emit and checkpoint each frame after ``start_frame``."""
    frame_dt = 1.0 / scene.solver.frame_rate
    interval = checkpoint_interval(scene)
    if not from_checkpoint:
        host = emit(0, frame_dt)
        with timer("checkpoint"):
            _save_checkpoint(out, 0, solver, hooks, host)
    bar = progress(disable=not show_progress)
    with bar:
        task = bar.add_task("simulate", total=nframes, completed=start_frame, info="")
        t0, steps0 = time.perf_counter(), solver.step_count
        for index in range(start_frame + 1, nframes + 1):
            with timer("step"):
                solver.advance_frame(index)
            host = emit(index, frame_dt)
            if index % interval == 0 or index == nframes:
                with timer("checkpoint"):
                    _save_checkpoint(out, index, solver, hooks, host)
            el = time.perf_counter() - t0
            sps = (solver.step_count - steps0) / el if el > 0 else 0.0
            extra = "".join(f"  {text}" for h in hooks if (text := h.status()))
            bar.update(
                task,
                completed=index,
                info=f"t={solver.time:.3f}s  {sps:.1f} steps/s  {solver.n:,} particles  "
                f"vmax={solver.stats.max_speed:.2f} m/s{extra}",
            )
