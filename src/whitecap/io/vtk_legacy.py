"""Legacy VTK particle files (``.vtk``): DualSPHysics PartVTK, SPlisHSPlasH and others.

Read with the ``vtk`` package (meshio cannot read POLYDATA, which is what
DualSPHysics writes). Points become positions; point arrays are matched by
name, case-insensitively (:func:`whitecap.io.registry.find_array`):

- velocity: ``Vel`` (DualSPHysics), ``velocity`` (SPlisHSPlasH), ``v``
- density:  ``Rhop`` or ``Rho`` (DualSPHysics), ``density``
- ids:      ``Idp`` (DualSPHysics), ``id``
- ``Type``/``Mk`` (DualSPHysics) are kept in ``arrays``; when ``Type`` is
  present only fluid particles (Type 3) are returned.

Options: ``up='y'`` for y-up solvers (SPlisHSPlasH's default), and
``require_velocity`` (default True) to fail with the file and array name.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .axes import to_z_up
from .frame import ParticleFrame
from .registry import DENSITY_NAMES, ID_NAMES, VELOCITY_NAMES, find_array, register

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


def read_vtk(path: Path, up: str = "z", require_velocity: bool = True) -> ParticleFrame:
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
    extra = {k: v[keep] for k, v in arrays.items() if k not in (vk, rk, ik) and v.ndim == 1}
    return ParticleFrame(
        positions=pos[keep],
        velocities=None if vel is None else vel[keep],
        ids=arrays[ik][keep].astype(np.uint32) if ik else None,
        density=arrays[rk][keep] if rk else None,
        arrays=extra,
        source=str(path),
    )


register("vtk", (".vtk",), read_vtk, None)
