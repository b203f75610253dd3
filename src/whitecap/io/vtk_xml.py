"""VTK XML PolyData (.vtp) for point clouds and triangle meshes (vtk package).

ParaView opens these directly; a :mod:`whitecap.io.pvd` collection strings
them into a time series.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError, MissingDependency
from .atomic import atomic_path


def _vtk():
    try:
        from vtkmodules.util import numpy_support
        from vtkmodules.vtkCommonCore import vtkPoints
        from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
        from vtkmodules.vtkIOXML import vtkXMLPolyDataReader, vtkXMLPolyDataWriter
    except ImportError as exc:  # pragma: no cover - vtk is a dependency
        raise MissingDependency(f"the 'vtk' package is needed for VTK export ({exc})") from None
    return numpy_support, vtkPoints, vtkCellArray, vtkPolyData, vtkXMLPolyDataWriter, vtkXMLPolyDataReader


def _cells(numpy_support, vtkCellArray, conn: np.ndarray, per_cell: int):
    """A vtkCellArray from a flat connectivity list of fixed-size cells."""
    n = len(conn) // per_cell if per_cell else 0
    offsets = numpy_support.numpy_to_vtkIdTypeArray(np.arange(0, n + 1, dtype=np.int64) * per_cell, deep=True)
    connectivity = numpy_support.numpy_to_vtkIdTypeArray(np.ascontiguousarray(conn, dtype=np.int64), deep=True)
    cells = vtkCellArray()
    cells.SetData(offsets, connectivity)
    return cells


def write_vtp(path: str | Path, points: np.ndarray, arrays: dict[str, np.ndarray] | None = None,
              triangles: np.ndarray | None = None) -> None:
    """Write points (N, 3) with per-point ``arrays`` atomically.

    Without ``triangles`` every point becomes a vertex cell (a point cloud);
    with them (M, 3) the file is a triangle mesh.
    """
    numpy_support, vtkPoints, vtkCellArray, vtkPolyData, Writer, _ = _vtk()
    pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
    poly = vtkPolyData()
    vp = vtkPoints()
    vp.SetData(numpy_support.numpy_to_vtk(pts, deep=True))
    poly.SetPoints(vp)
    if triangles is None:
        poly.SetVerts(_cells(numpy_support, vtkCellArray, np.arange(len(pts)), 1))
    else:
        poly.SetPolys(_cells(numpy_support, vtkCellArray, np.asarray(triangles).reshape(-1), 3))
    for name, a in (arrays or {}).items():
        a = np.ascontiguousarray(a)
        if len(a) != len(pts):
            raise InputError(f"{path}: array '{name}' has {len(a)} entries for {len(pts)} points")
        va = numpy_support.numpy_to_vtk(a, deep=True)
        va.SetName(name)
        poly.GetPointData().AddArray(va)
    w = Writer()
    w.SetInputData(poly)
    w.SetDataModeToAppended()
    w.SetCompressorTypeToZLib()
    with atomic_path(path) as tmp:
        w.SetFileName(str(tmp))
        if w.Write() != 1:
            raise InputError(f"{path}: VTK writer failed")


def read_vtp(path: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """(points, point arrays, triangles (M, 3)) of a .vtp file (used by tests and tools)."""
    numpy_support, *_, Reader = _vtk()
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found")
    r = Reader()
    r.SetFileName(str(p))
    r.Update()
    poly = r.GetOutput()
    if poly.GetPoints() is None:
        return np.zeros((0, 3), np.float32), {}, np.zeros((0, 3), np.int64)
    pts = numpy_support.vtk_to_numpy(poly.GetPoints().GetData())
    pd = poly.GetPointData()
    arrays = {pd.GetArrayName(i): numpy_support.vtk_to_numpy(pd.GetArray(i)) for i in range(pd.GetNumberOfArrays())}
    conn = numpy_support.vtk_to_numpy(poly.GetPolys().GetConnectivityArray())
    return pts, arrays, conn.reshape(-1, 3)
