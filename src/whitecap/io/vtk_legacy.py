"""Legacy VTK particle files (``.vtk``): DualSPHysics PartVTK, SPlisHSPlasH and others.

Read with the ``vtk`` package (meshio cannot read POLYDATA, which is what
DualSPHysics writes). Points become positions; point arrays are matched by
name, case-insensitively (:func:`whitecap.io.registry.find_array`):

- velocity: ``Vel`` (DualSPHysics), ``velocity`` (SPlisHSPlasH), ``v``
- density:  ``Rhop`` or ``Rho`` (DualSPHysics), ``density``
- ids:      ``Idp`` (DualSPHysics), ``id``
- ``Type``/``Mk`` (DualSPHysics) are kept in ``arrays``; when ``Type`` is
  present only fluid particles (Type 3) are returned.

Options: ``up='y'`` for y-up solvers (SPlisHSPlasH's default),
``require_velocity`` (default True) to fail with the file and array name, and
``by_id`` to return the rows in increasing id order (SPlisHSPlasH z-sorts its
particles, so its row order changes from frame to frame; the file must then
hold an id array).

Triangle meshes in legacy VTK (SPlisHSPlasH's rigid-body VTK export: an
``UNSTRUCTURED_GRID`` of triangles; also ``POLYDATA`` polygons) are read as a
mesh format: :func:`whitecap.io.registry.read_mesh` on a ``.vtk`` file.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from .axes import to_z_up
from .frame import ParticleFrame
from .registry import DENSITY_NAMES, ID_NAMES, MESH, VELOCITY_NAMES, find_array, register

if TYPE_CHECKING:
    from .mesh import SurfaceMesh

DUALSPHYSICS_FLUID_TYPE = 3


def _read_dataset(path: Path):
    import vtk

    r = vtk.vtkGenericDataObjectReader()
    r.SetFileName(str(path))
    r.ReadAllScalarsOn()
    r.ReadAllVectorsOn()
    r.ReadAllFieldsOn()
    r.Update()
    out = r.GetOutput()
    if out is None or not hasattr(out, "GetPoints") or out.GetPoints() is None:
        raise InputError(f"{path}: not a readable legacy VTK point data set")
    return out


def point_arrays(ds) -> dict[str, np.ndarray]:
    from vtk.util.numpy_support import vtk_to_numpy

    pd = ds.GetPointData()
    arrays = {}
    for k in range(pd.GetNumberOfArrays()):
        a = pd.GetAbstractArray(k)
        if a is not None and a.GetName() and hasattr(a, "GetNumberOfComponents"):
            try:
                arrays[a.GetName()] = vtk_to_numpy(a)
            except Exception:
                continue
    return arrays


def read_vtk(path: Path, up: str = "z", require_velocity: bool = True, by_id: bool = False) -> ParticleFrame:
    from vtk.util.numpy_support import vtk_to_numpy

    ds = _read_dataset(path)
    pos = vtk_to_numpy(ds.GetPoints().GetData()).astype(np.float32)
    arrays = point_arrays(ds)
    vk, rk, ik = find_array(arrays, VELOCITY_NAMES), find_array(arrays, DENSITY_NAMES), find_array(arrays, ID_NAMES)
    if vk is None and require_velocity:
        raise InputError(f"{path}: missing array 'Vel' (particle velocities); found {sorted(arrays) or 'no arrays'}")
    vel = arrays[vk].astype(np.float32).reshape(-1, 3) if vk else None
    keep = np.ones(len(pos), bool)
    tk = find_array(arrays, ("type",))
    if tk is not None and len(np.unique(arrays[tk])) > 1:
        keep = arrays[tk] == DUALSPHYSICS_FLUID_TYPE
    pos, vel = to_z_up(pos, vel, up)
    if by_id and ik is None:
        raise InputError(f"{path}: missing array 'id' (persistent particle ids) to order the particles by; "
                         f"found {sorted(arrays) or 'no arrays'}")
    extra = {k: v[keep] for k, v in arrays.items() if k not in (vk, rk, ik) and v.ndim == 1}
    frame = ParticleFrame(
        positions=pos[keep],
        velocities=None if vel is None else vel[keep],
        ids=arrays[ik][keep].astype(np.uint32) if ik else None,
        density=arrays[rk][keep] if rk else None,
        arrays=extra,
        source=str(path),
    )
    return frame.sorted_by_id() if by_id else frame


def read_mesh_vtk(path: Path) -> "SurfaceMesh":
    """A triangle mesh from a legacy VTK file (cells of 3 points; others are refused)."""
    from vtk.util.numpy_support import vtk_to_numpy

    from .mesh import SurfaceMesh

    ds = _read_dataset(path)
    verts = vtk_to_numpy(ds.GetPoints().GetData()).astype(np.float64)
    cells = ds.GetPolys() if hasattr(ds, "GetPolys") else ds.GetCells()
    if cells is None or cells.GetNumberOfCells() == 0:
        raise InputError(f"{path}: no triangles (cells) in this VTK file")
    offsets = vtk_to_numpy(cells.GetOffsetsArray())
    sizes = np.diff(offsets)
    if (sizes != 3).any():
        c = int(np.flatnonzero(sizes != 3)[0])
        raise InputError(f"{path}: cell {c} has {int(sizes[c])} points; only triangle meshes are read")
    faces = vtk_to_numpy(cells.GetConnectivityArray()).reshape(-1, 3)
    return SurfaceMesh(verts, np.asarray(faces, np.int64).reshape(-1, 3), source=str(path))


register("vtk", (".vtk",), read_vtk, None)
register("vtk", (".vtk",), read_mesh_vtk, None, kind=MESH)
