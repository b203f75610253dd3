"""VTK XML PolyData (.vtp) for point clouds and triangle meshes (vtk package).

ParaView opens these directly; a :mod:`whitecap.io.pvd` collection strings
them into a time series. :func:`check_complete` refuses a VTK XML file (``.vtp``,
``.vtu``) that was cut short, in one line naming the file and the array.
"""

from __future__ import annotations

import errno
import os
import re
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


_ARRAY_TAG = re.compile(rb"<DataArray\b[^>]*>")
_ATTR = {k: re.compile(rb'\b' + k + rb'="([^"]*)"') for k in (b"Name", b"format", b"offset")}


def check_complete(path: str | Path) -> None:
    """Raise InputError (one line: the file, ``truncated``, the array it stops in) when a VTK XML
    file (``.vtu``, ``.vtp``) does not end with its closing ``</VTKFile>``. Reads its first and last
    few hundred bytes (the whole file only to name the array of a file that is cut)."""
    p = Path(path)
    try:
        with open(p, "rb") as f:
            head = f.read(512)
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - 256))
            tail = f.read()
            if not (head.lstrip().startswith(b"<?xml") or b"<VTKFile" in head) or \
                    tail.rstrip().endswith(b"</VTKFile>"):
                return
            f.seek(0)
            raw = f.read()
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    raise InputError(f"{p}: truncated: {_where_cut(raw)} (no closing </VTKFile>)")


def _where_cut(raw: bytes) -> str:
    """Which array a VTK XML file that lost its end stops in (inline, or in the appended data)."""
    def attr(tag: bytes, key: bytes) -> str | None:
        m = _ATTR[key].search(tag)
        return m.group(1).decode("utf-8", "replace") if m else None

    app = raw.find(b"<AppendedData")
    if app >= 0:
        start = raw.find(b"_", app) + 1  # the raw or base64 data begins after an underscore
        at = len(raw) - start
        inside = None
        for m in _ARRAY_TAG.finditer(raw, 0, app):
            if attr(m.group(), b"format") == "appended" and int(attr(m.group(), b"offset") or 0) <= at:
                inside = attr(m.group(), b"Name") or inside
        return (f"the file ends inside the appended data of array '{inside}'" if start > 0 and inside
                else "the file ends inside its appended data")
    tags = list(_ARRAY_TAG.finditer(raw))
    if not tags:
        return "the file ends before its first array"
    last = tags[-1]
    name = attr(last.group(), b"Name") or "?"
    if last.group().endswith(b"/>") or raw.find(b"</DataArray>", last.end()) >= 0:
        return f"the file ends after array '{name}'"
    return f"the file ends inside array '{name}'"


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
            code = w.GetErrorCode()  # VTK keeps the system's errno when a write fails (28: disk full)
            if 0 < code < 20000:
                raise OSError(code, os.strerror(code), str(path))
            raise OSError(errno.EIO, f"VTK could not write the file (VTK error code {code})", str(path))


def read_vtp(path: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """(points, point arrays, triangles (M, 3)) of a .vtp file (used by tests and tools)."""
    numpy_support, *_, Reader = _vtk()
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found")
    check_complete(p)
    r = Reader()
    if not r.CanReadFile(str(p)):
        raise InputError(f"{p}: not a readable VTK XML PolyData (.vtp) file")
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
