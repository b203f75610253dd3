"""``whitecap export``: ParaView series of a run's particles and meshes.

For each series (fluid particles, diffuse particles, optionally split by
type, and surface meshes) one file per frame goes to ``RUN/export/<series>/``
plus a collection beside it that carries each frame's simulated time from
``run.json``: ``<series>.pvd`` for VTK XML (``--to vtk``, PolyData ``.vtp``)
or ``<series>.series`` for PLY (``--to ply``). Opening the collection in
ParaView plays the run.

``export.json`` in the output directory records the identity of the
simulation the series were made from and the files written; a new export
removes the files of the previous one that it does not write again, so no
series of an earlier simulation is left behind. Nothing else in the output
directory is ever removed: files whitecap did not list there are the user's.
The files an export is about to write are added to the list before the first
is written, so an interrupted export's files are removed by the next one.

Only the output is written: with ``--out`` outside the run, the run is read
under a shared lock (:func:`whitecap.io.lock.read_lock`) and may be read-only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import io as wio
from ..config import with_options
from ..errors import InputError
from ..executor import cluster_settings
from ..io.diffuse_types import TYPE_NAMES
from ..io.frame import ParticleFrame
from ..io.lock import export_locks
from ..io.manifest import Manifest
from ..io.mesh import SurfaceMesh, read_mesh, write_mesh
from ..io.pvd import write_pvd, write_series
from ..io.run import RunInfo
from ..io.vtk_xml import write_vtp
from ..stage_frames import check_jobs, map_over_frames
from . import SERIES_TARGETS, ExportJob

TARGETS = SERIES_TARGETS
MANIFEST = "export.json"


def _point_arrays(frame: ParticleFrame) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {}
    if frame.velocities is not None:
        arrays["velocity"] = frame.velocities
    if frame.density is not None:
        arrays["density"] = frame.density
    arrays.update(frame.arrays)
    arrays["id"] = frame.ids
    return arrays


def _subset(frame: ParticleFrame, keep: np.ndarray) -> ParticleFrame:
    return ParticleFrame(
        positions=frame.positions[keep],
        velocities=None if frame.velocities is None else frame.velocities[keep],
        ids=frame.ids[keep],
        density=None if frame.density is None else frame.density[keep],
        time=frame.time,
        arrays={k: a[keep] for k, a in frame.arrays.items()},
        source=frame.source,
    )


def _write_points(path: Path, frame: ParticleFrame, to: str) -> None:
    if to == "vtk":
        write_vtp(path, frame.positions, _point_arrays(frame))
    else:
        wio.write(path, frame, fmt="ply")


def _write_surface(path: Path, mesh: SurfaceMesh, to: str) -> None:
    if to == "vtk":
        arrays = {k: a for k, a in mesh.arrays.items()}
        if mesh.normals is not None:
            arrays["Normals"] = mesh.normals
        write_vtp(path, mesh.vertices, arrays, triangles=mesh.faces)
    else:
        write_mesh(path, mesh)


def export_run(run: str | Path, job: ExportJob | None = None, out: str | Path | None = None,
               kinds: tuple[str, ...] = ("fluid", "diffuse", "mesh"), **options) -> dict[str, Path]:
    """Write the series of ``run`` to ``out`` (default ``RUN/export``) as ``job`` says
    (``options``, its field names, build one or replace its fields).

    Returns {series name: collection path}. Kinds the run does not have are
    skipped; a run with none of them is an error. The frames are written on
    an executor (:mod:`whitecap.executor`): here (``jobs`` = 1), in ``jobs``
    local processes, or on Dask with ``cluster``; the collections are written
    here, from the frame list, so they do not depend on which frame finished first.
    """
    job = with_options(ExportJob, job, options)
    run, out = export_target(run, job.to, SERIES_TARGETS, out, job.jobs)
    with export_locks(run, out, "export"):
        return _export(run, job.to, out, job.split_types, kinds, job.show_progress, job.jobs or 1, job.cluster)


def export_target(run: str | Path, to: str, targets: tuple[str, ...], out: str | Path | None, jobs: int | None,
                  sub: str = "") -> tuple[Path, Path]:
    """Check an export's target, ``--jobs`` and run; returns the run and the output folder
    (``out``, else ``RUN/export``, or ``RUN/export/<sub>``)."""
    if to not in targets:
        raise InputError(f"export: unknown target '{to}' (choose from {', '.join(targets)})")
    check_jobs("export", jobs)
    run = Path(run)
    if not run.is_dir():
        raise InputError(f"{run}: no such run directory")
    return run, Path(out) if out is not None else run / "export" / sub


def export_frame(src: Path, kind: str, paths: dict[str, Path], to: str) -> None:
    """Write one frame of one kind: ``paths`` maps each series name (kind, diffuse_<type>) to its file."""
    if kind == "mesh":
        mesh = read_mesh(src)
        mesh.check_finite()
        _write_surface(paths["mesh"], mesh, to)
        return
    frame = wio.read(src)
    frame.check_finite()
    _write_points(paths[kind], frame, to)
    if len(paths) > 1:  # diffuse split by type
        if "type" not in frame.arrays:
            raise InputError(f"{src}: missing array 'type' (needed by --split-types)")
        t = frame.arrays["type"]
        for code, label in enumerate(TYPE_NAMES):
            _write_points(paths[f"diffuse_{label}"], _subset(frame, t == code), to)


def _export(run: Path, to: str, out: Path, split_types: bool, kinds: tuple[str, ...],
            show_progress: bool, jobs: int = 1, cluster: str | None = None) -> dict[str, Path]:
    info = RunInfo.load(run)
    ext = "vtp" if to == "vtk" else "ply"
    times = {f.index: float(info.time(f.index)) for f in info.frames}
    work = [(kind, i, rel) for kind in kinds for i, rel in info.files(kind)]
    if not work:
        raise InputError(f"{run / 'run.json'}: no {', '.join(kinds)} frames to export")
    series: dict[str, list[tuple[float, str]]] = {}
    tasks = []
    for k, (kind, i, rel) in enumerate(work):
        names = [kind] + ([f"diffuse_{label}" for label in TYPE_NAMES] if kind == "diffuse" and split_types else [])
        paths = {}
        for name in names:
            frel = f"{name}/{name}_{i:05d}.{ext}"
            series.setdefault(name, []).append((times[i], frel))
            paths[name] = out / frel
        tasks.append((k, (run / rel, kind, paths, to)))

    out.mkdir(parents=True, exist_ok=True)
    collections = {f"{name}.{'pvd' if to == 'vtk' else 'series'}" for name in series}
    files = collections | {rel for entries in series.values() for _, rel in entries}
    record_planned(out, info.simulation, files)
    map_over_frames("export", export_frame, tasks, lambda r: work[r.index][2], shared=run, jobs=jobs, cluster=cluster,
                    cfg=cluster_settings(run) if cluster else None, show_progress=show_progress,
                    sweep=[out / name for name in series])

    written: dict[str, Path] = {}
    for name, entries in series.items():
        if to == "vtk":
            path = out / f"{name}.pvd"
            write_pvd(path, entries)
        else:
            path = out / f"{name}.series"
            write_series(path, entries)
        written[name] = path
    replace_previous(out, info.simulation, files)
    return written


def record_planned(out: Path, simulation: str, files: set[str]) -> None:
    """Before writing: refuse a file in the way that export.json does not list (the user's), then
    add the files this export will write to the list, so that an export interrupted half-way leaves
    only files that the next one knows to be its own (io/manifest.py)."""
    m = Manifest(out, MANIFEST)
    m.refuse_foreign(sorted(files), "export")
    m.simulation = simulation
    m.plan(sorted(files))


def replace_previous(out: Path, simulation: str, files: set[str]) -> None:
    """Remove what export.json lists (earlier exports, an interrupted one) and this export did
    not write; record this one in export.json. Files it does not list are never touched."""
    m = Manifest(out, MANIFEST)
    m.keep_only(files)
    m.simulation = simulation
    m.files.update({rel: simulation for rel in files})
    m.save()
