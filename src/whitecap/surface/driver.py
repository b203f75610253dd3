"""``whitecap mesh``: reconstruct every frame of a run or a particle sequence.

The main process lists the frames, skips those already meshed (unless
``force``; in a run, a mesh counts as done only when ``run.json`` records it
as made from the run's current simulation, so meshes left by an earlier
simulation are made again), maps :func:`~whitecap.surface.reconstruct.mesh_frame` over an
executor (a local process pool, or Dask with ``--cluster``) and records
each finished mesh in ``run.json`` (an atomic
write per frame, from the main process).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from ..config import DEFAULT_UP, SPLASHSURF_WEIGHTS_NORMALIZATION, Cluster, Mesh, load_scene
from ..errors import InputError
from ..io.atomic import sweep_temps
from ..io.lock import read_lock, run_lock
from ..io.manifest import Manifest
from ..io.run import RUN_JSON, RunInfo, refuse_inside_other_run, source_identity
from ..io.sequence import find_sequence
from ..stage_frames import check_jobs, map_over_frames, todo as stage_todo
from ..timing import timer
from .reconstruct import MeshParams, mesh_frame, params_from_config, walls_from_run


@dataclass
class MeshJob:
    """Frames to mesh: (index, input path, output path, output path relative to the run)."""

    frames: list[tuple[int, Path, Path, str]]
    params: MeshParams
    run_dir: Path | None = None
    recorded: set[int] = field(default_factory=set)  # frames whose mesh run.json (or the manifest) records as current
    stats: list[dict[str, Any]] = field(default_factory=list)
    on_done: Any = None  # outside a run: records a finished frame in the folder's manifest
    source_run: Path | None = None  # the run the frames come from, when they do


@dataclass(frozen=True)
class MeshRun:
    """How one ``mesh`` runs (not what it makes: that is ``[mesh]``, :class:`~whitecap.config.Mesh`):
    the options of ``whitecap mesh`` and of :func:`whitecap.pipeline.mesh`, with their defaults,
    defined here once (the CLI and the pipeline build one; :func:`run_mesh` takes it). Checked on
    construction.

    ``jobs`` frames at once (None: the core count, or with a remote ``cluster`` its
    ``[cluster].jobs``); ``force`` meshes finished frames again; ``cluster`` (a scheduler address,
    or local, slurm, pbs) runs the frames on Dask, configured by ``cluster_config``.
    """

    jobs: int | None = None
    force: bool = False
    show_progress: bool = True
    cluster: str | None = None
    cluster_config: Cluster | None = None

    def __post_init__(self) -> None:
        check_jobs("mesh", self.jobs)

    def workers(self) -> int:
        """Frames at once: ``jobs``, else a remote cluster's ``[cluster].jobs``, else the core count
        (splashsurf itself runs on one thread per frame)."""
        if self.jobs:
            return self.jobs
        if self.cluster and self.cluster != "local" and self.cluster_config is not None:
            return self.cluster_config.jobs
        return len(os.sched_getaffinity(0))


def mesh_config(base: Mesh | None = None, **overrides) -> Mesh:
    """A ``[mesh]`` section with command-line overrides applied (None = keep)."""
    data = (base or Mesh()).model_dump()
    data.update({k: v for k, v in overrides.items() if v is not None})
    try:
        return Mesh(**data)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = ".".join(str(p) for p in err["loc"])
        raise InputError(f"mesh.{key}: {err['msg']} (got {err.get('input')!r})") from None


def plan(source: str | Path, out: str | Path | None = None, radius: float | None = None,
         config: Mesh | None = None, up: str = DEFAULT_UP, **overrides) -> MeshJob:
    """Resolve the input (run directory or sequence), the parameters and the output names."""
    src = Path(source)
    is_run = src.is_dir() and (src / RUN_JSON).is_file()
    if not is_run and not any(c in str(source) for c in "*?[") and not src.exists():
        raise InputError(f"{src}: no such run directory or particle sequence")
    rest_density = 1000.0
    walls: tuple = ()
    if is_run:
        info = RunInfo.load(src)
        if config is None and (src / "scene.toml").is_file():
            config = load_scene(src / "scene.toml").mesh
        r = info.particle_radius if radius is None else radius
        rest_density = info.rest_density
        walls = walls_from_run(info)
        inputs = [(i, src / rel) for i, rel in info.files("fluid")]
        if not inputs:
            with read_lock(src, "mesh"):  # a simulate still at its first frame: name it rather than say "none"
                raise InputError(f"{src / RUN_JSON}: the run has no fluid frames")
        out_dir = Path(out) if out is not None else src / "mesh"
    else:
        inputs = find_sequence(source)
        if radius is None:
            raise InputError(f"{source}: not a whitecap run, so the particle radius is unknown; pass --radius R [m]")
        r = radius
        out_dir = Path(out) if out is not None else inputs[0][1].parent / "mesh"
    cfg = mesh_config(config, **overrides)
    params = params_from_config(r, cfg, rest_density=rest_density, up=up, walls=walls)
    check_memory(inputs[0][1], params, up=None if is_run else up)
    # Meshes are recorded in run.json only when they land inside the run.
    inside = is_run and out_dir.resolve().is_relative_to(src.resolve())
    frames = []
    for i, p in inputs:
        o = out_dir / f"fluid_{i:05d}.{cfg.format}"
        rel = os.path.relpath(o, src) if inside else str(o)
        frames.append((i, p, o, rel))
    return MeshJob(frames, params, src if inside else None, source_run=src if is_run else None)


#: Bytes splashsurf keeps per marching-cubes point near the surface (its density value, index and
#: hash-map entry, the vertex and its share of triangles and normals), from its memory on a dam break.
BYTES_PER_SURFACE_POINT = 64
#: Surface points per face area of the fluid's bounding box, over the box's own faces: splashes and
#: folds give a water surface a larger area than its box.
SURFACE_AREA_FACTOR = 2.0


def check_memory(first: Path, params: MeshParams, up: str | None) -> None:
    """Refuse, before any frame starts, a reconstruction whose marching-cubes grid would not fit in
    memory (``--cube-size 0.001`` makes cells a thousand times finer than the particles): the points
    near the surface are estimated from the first frame's bounding box."""
    from ..io import read
    from ..resources import MEMORY_HEADROOM, available_memory

    pos = read(first, require_velocity=False, **({"up": up} if up else {})).positions
    if not len(pos):
        return
    e = np.ptp(pos, 0).astype(np.float64) + 2 * params.surface_radius
    cell = params.cube_size * params.particle_radius
    points = SURFACE_AREA_FACTOR * 2 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2]) / cell**2
    need = points * BYTES_PER_SURFACE_POINT
    if need > MEMORY_HEADROOM * available_memory():
        raise InputError(
            f"mesh.cube_size: {params.cube_size:g} r = {cell:.3g} m cells would need about {need / 2**30:,.0f} GiB "
            f"for the surface of {first.name} ({points:.2g} grid points), more than this machine has free; "
            "raise --cube-size (0.5 to 1 is usual)")


def settings_key(params: MeshParams) -> str:
    """What makes two meshes of a frame the same: every reconstruction setting but splashsurf's own
    threading (how the work is split, not what it makes). Recorded per mesh in run.json, so meshes of
    other settings are made again rather than skipped."""
    d = params.as_dict()
    d.pop("multi_threading", None)  # recorded by earlier versions, which threaded splashsurf on one job
    if d.get("mesh_smoothing_weights_normalization") == SPLASHSURF_WEIGHTS_NORMALIZATION:
        # earlier versions passed none, so splashsurf used its own: their meshes are still current
        del d["mesh_smoothing_weights_normalization"]
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


def run_mesh(job: MeshJob, run: MeshRun | None = None, **options) -> list[dict]:
    """Mesh every frame of ``job`` as ``run`` says (``options``, :class:`MeshRun` fields, build one or
    replace its fields); returns per-frame stats (``skipped`` True for frames already done).

    With ``run.cluster`` the frames run on Dask (:mod:`whitecap.executor`); this process keeps the
    lock and records run.json.
    """
    run = MeshRun(**options) if run is None else replace(run, **options)
    if job.run_dir is None:
        return _run_mesh(job, run)
    with run_lock(job.run_dir, "mesh"):
        return _run_mesh(job, run)


#: The manifest of meshes written outside a run (io/manifest.py): a sequence's mesh/ folder, or --out.
MESH_MANIFEST = "mesh.json"


def _done(job: MeshJob, frame: tuple) -> bool:
    """A frame's mesh exists and was made from this input and these settings (in a run: from the
    run's current simulation, as run.json records; elsewhere: as the folder's manifest does)."""
    return frame[2].is_file() and frame[0] in job.recorded


def _frame_key(path: Path, params: MeshParams) -> str:
    """What a mesh outside a run was made from: its input file (name, size, time) and the settings."""
    return f"{source_identity([path], params.up)}-{settings_key(params)}"


def _run_mesh(job: MeshJob, run: MeshRun) -> list[dict]:
    manifest = None
    if job.run_dir is not None:  # read under the lock, so no simulate can change what is current meanwhile
        info = RunInfo.load(job.run_dir)
        current, key = dict(info.files("mesh")), settings_key(job.params)
        job.recorded = {i for i, _, _, rel in job.frames
                        if current.get(i) == rel and info.frame(i).mesh_settings == key}
    elif job.frames:  # outside a run: only files the folder's manifest lists are ours
        refuse_inside_other_run(job.frames[0][2].parent, job.source_run, "mesh")
        manifest = Manifest(job.frames[0][2].parent, MESH_MANIFEST)
        keys = {i: _frame_key(p, job.params) for i, p, _, _ in job.frames}
        job.recorded = {i for i, _, o, _ in job.frames if manifest.current(o.name, keys[i])}
    todo = stage_todo(job.frames, lambda f: _done(job, f), run.force)
    if job.run_dir is not None:  # inside the run: never over a file the run holds as something else
        others = {rel: kind for f in info.frames for kind, rel in f.files.items() if kind != "mesh"}
        for _, _, o, rel in todo:
            if rel in others:
                raise InputError(f"{o}: is the run's {others[rel]} file; mesh would overwrite it: choose another --out")
    if manifest is not None:
        manifest.refuse_foreign([o.name for _, _, o, _ in todo], "mesh")
        manifest.plan([o.name for _, _, o, _ in todo])
        outputs = {i: o for i, _, o, _ in todo}
        job.on_done = lambda i: manifest.record(outputs[i].name, keys[i])
    stats = {f[0]: {"index": f[0], "out": str(f[2]), "skipped": True} for f in job.frames if f not in todo}
    out_dirs = sorted({f[2].parent for f in job.frames})
    try:
        _map_frames(job, todo, stats, run)
    finally:
        # Frames finished before an error or Ctrl-C are kept and recorded.
        job.stats = [stats[i] for i, *_ in job.frames if i in stats]
        if job.run_dir is not None:
            record(job)
        for d in out_dirs:  # a worker killed while writing leaves its temporary file
            sweep_temps(d)
    return job.stats


def _map_frames(job: MeshJob, todo: list, stats: dict, run: MeshRun) -> None:
    if not todo:
        return

    def done(r) -> str:
        s = r.value
        stats[r.index] = {"index": r.index, "skipped": False, **s}
        if job.run_dir is not None:  # recorded at once, so a killed mesh resumes after its last frame
            job.stats = [stats[r.index]]
            record(job)
        elif job.on_done is not None:
            job.on_done(r.index)
        return f"{s['particles']} particles -> {s['faces']} triangles"

    map_over_frames("mesh", mesh_frame, [(i, (p, o, job.params)) for i, p, o, _ in todo], done,
                    shared=job.run_dir if job.run_dir is not None else todo[0][2].parent,
                    jobs=run.workers(), cluster=run.cluster,
                    cfg=run.cluster_config, total=len(job.frames), completed=len(stats),
                    show_progress=run.show_progress,
                    around=lambda: timer("mesh"))


def record(job: MeshJob) -> RunInfo:
    """Add the meshes of ``job.stats`` to run.json (main process only)."""
    assert job.run_dir is not None  # only a run's meshes are recorded
    info = RunInfo.load(job.run_dir)
    made = {s["index"] for s in job.stats}  # meshed now, or skipped as current: never a stale file
    key = settings_key(job.params)
    for i, _, o, rel in job.frames:
        if i in made and o.is_file():
            info.set_file(i, "mesh", rel)
            info.frame(i).mesh_settings = key
    # The settings of the meshes run.json lists: only once every one of them was made with these.
    meshed = [f for f in info.frames if "mesh" in f.files]
    if meshed and all(f.mesh_settings == key for f in meshed):
        info.extra["mesh"] = job.params.as_dict()
    else:
        info.extra.pop("mesh", None)
    info.save(job.run_dir)
    return info
