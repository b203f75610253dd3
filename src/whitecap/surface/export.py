"""``whitecap export``: ParaView series of a run's particles and meshes.

For each series (fluid particles, diffuse particles, optionally split by
type, and surface meshes) one file per frame goes to ``RUN/export/<series>/``
plus a collection beside it that carries each frame's simulated time from
``run.json``: ``<series>.pvd`` for VTK XML (``--to vtk``, PolyData ``.vtp``)
or ``<series>.series`` for PLY (``--to ply``). Opening the collection in
ParaView plays the run.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import io as wio
from ..errors import InputError
from ..io.diffuse_types import TYPE_NAMES
from ..io.frame import ParticleFrame
from ..io.mesh import SurfaceMesh, read_mesh, write_mesh
from ..io.pvd import write_pvd, write_series
from ..io.run import RunInfo
from ..io.vtk_xml import write_vtp
from ..progress import progress

#: diffuse particle ``type`` codes of the run-directory contract
TARGETS = ("vtk", "ply")  # vtk: .vtp/.vtu + .pvd; ply: PLY + .series


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


def export_run(run: str | Path, to: str = "vtk", out: str | Path | None = None, split_types: bool = False,
               kinds: tuple[str, ...] = ("fluid", "diffuse", "mesh"), show_progress: bool = True) -> dict[str, Path]:
    """Write the series of ``run`` to ``out`` (default ``RUN/export``).

    Returns {series name: collection path}. Kinds the run does not have are
    skipped; a run with none of them is an error.
    """
    if to not in TARGETS:
        raise InputError(f"export: unknown target '{to}' (choose from {', '.join(TARGETS)})")
    run = Path(run)
    if not run.is_dir():
        raise InputError(f"{run}: no such run directory")
    info = RunInfo.load(run)
    out = Path(out) if out is not None else run / "export"
    ext = "vtp" if to == "vtk" else "ply"
    times = {f["index"]: float(f["time"]) for f in info.frames}
    work = [(kind, i, rel) for kind in kinds for i, rel in info.files(kind)]
    if not work:
        raise InputError(f"{run / 'run.json'}: no {', '.join(kinds)} frames to export")
    series: dict[str, list[tuple[float, str]]] = {}

    def emit(name: str, index: int) -> Path:
        rel = f"{name}/{name}_{index:05d}.{ext}"
        series.setdefault(name, []).append((times[index], rel))
        return out / rel

    with progress(disable=None if show_progress else True) as bar:
        task = bar.add_task("export", total=len(work), info="")
        for kind, i, rel in work:
            src = run / rel
            if kind == "mesh":
                _write_surface(emit("mesh", i), read_mesh(src), to)
            else:
                frame = wio.read(src)
                _write_points(emit(kind, i), frame, to)
                if kind == "diffuse" and split_types:
                    if "type" not in frame.arrays:
                        raise InputError(f"{src}: missing array 'type' (needed by --split-types)")
                    t = frame.arrays["type"]
                    for code, label in enumerate(TYPE_NAMES):
                        _write_points(emit(f"diffuse_{label}", i), _subset(frame, t == code), to)
            bar.update(task, advance=1, info=rel)

    written: dict[str, Path] = {}
    for name, entries in series.items():
        if to == "vtk":
            path = out / f"{name}.pvd"
            write_pvd(path, entries)
        else:
            path = out / f"{name}.series"
            write_series(path, entries)
        written[name] = path
    return written
