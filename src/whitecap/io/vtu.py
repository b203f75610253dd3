"""VTK XML unstructured grids (``.vtu``) through meshio: points plus point data
(``velocity``/``Vel``/``v``, ``density``, ``id``), as ParaView and many
solvers write them. A file cut short is refused in one line naming the file and
the array (:func:`whitecap.io.vtk_xml.check_complete`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .axes import to_z_up
from .frame import ParticleFrame
from .registry import DENSITY_NAMES, ID_NAMES, VELOCITY_NAMES, find_array, register
from .vtk_xml import check_complete


def read_mesh(path: str | Path):
    """The one VTU parse: meshio's ``Mesh`` of the file (every point array, every cell block), its
    completeness and array lengths checked. The registry's :func:`read_vtu` and the Blender add-on
    (which carries meshio as a wheel and this module as a copy) both read ``.vtu`` through it."""
    from meshio import vtu

    check_complete(path)
    try:
        # meshio's own reader: meshio.read prints its errors and exits the process on a bad file
        m = vtu.read(str(path))
    except Exception as exc:
        raise InputError(f"{path}: not a readable VTU file ({str(exc) or type(exc).__name__})") from None
    for k, v in m.point_data.items():
        if len(v) != len(m.points):
            what = "truncated: " if len(v) < len(m.points) else ""
            raise InputError(f"{path}: {what}array '{k}' holds {len(v)} values for the {len(m.points)} points "
                             "the file declares (NumberOfPoints)")
    return m


def read_vtu(path: Path, up: str = "z", require_velocity: bool = True) -> ParticleFrame:
    m = read_mesh(path)
    arrays = dict(m.point_data)
    vk, rk, ik = find_array(arrays, VELOCITY_NAMES), find_array(arrays, DENSITY_NAMES), find_array(arrays, ID_NAMES)
    if vk is None and require_velocity:
        raise InputError(f"{path}: missing array 'velocity'; found {sorted(arrays) or 'no arrays'}")
    pos, vel = to_z_up(np.asarray(m.points, np.float32), np.asarray(arrays[vk], np.float32) if vk else None, up)
    return ParticleFrame(
        positions=pos,
        velocities=vel,
        ids=np.asarray(arrays[ik]).astype(np.uint32).ravel() if ik else None,
        density=np.asarray(arrays[rk]).ravel() if rk else None,
        arrays={k: np.asarray(v) for k, v in arrays.items() if k not in (vk, rk, ik) and np.asarray(v).ndim == 1},
        source=str(path),
    )


def write_vtu(path: Path, frame: ParticleFrame) -> None:
    import meshio

    from .atomic import atomic_path

    n = len(frame)
    data = {"id": frame.ids.astype(np.int64)}
    if frame.velocities is not None:
        data["velocity"] = frame.velocities
    if frame.density is not None:
        data["density"] = frame.density
    data.update(frame.arrays)
    with atomic_path(path) as tmp:
        meshio.write(str(tmp), meshio.Mesh(frame.positions, [("vertex", np.arange(n).reshape(-1, 1))], point_data=data))


register("vtu", (".vtu",), read_vtu, write_vtu, check=check_complete)
