"""Binary little-endian PLY particle files (plyfile).

Fluid frames carry ``x y z vx vy vz density id``; diffuse frames add
``type lifetime radius``. Any extra float/int vertex property is read into
``ParticleFrame.arrays``. A file cut short is refused with one line: the file,
``truncated``, the element and its declared and held rows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyElementParseError, PlyHeaderParseError

from ..errors import InputError
from .atomic import atomic_path
from .frame import ParticleFrame
from .registry import register

_CORE = ("x", "y", "z", "vx", "vy", "vz", "density", "id")
_DTYPES = {np.dtype(np.float32): "f4", np.dtype(np.uint32): "u4", np.dtype(np.uint8): "u1", np.dtype(np.int32): "i4"}


def read_vertices(path: Path, known_list_len: dict | None = None):
    """(PlyData, vertex records, property names) of a PLY with x y z, or InputError naming the file.

    ``known_list_len`` ({element: {list property: length}}) lets plyfile map
    fixed-length lists (triangles) straight from the file instead of parsing
    them row by row; a row of another length raises a PlyElementParseError
    naming the element and row.
    """
    try:
        ply = PlyData.read(str(path), known_list_len=known_list_len or {})
    except PlyElementParseError as exc:
        raise _element_error(path, exc) from None
    except PlyHeaderParseError as exc:
        if "early end-of-file" in str(exc):
            raise InputError(f"{path}: truncated: the file ends inside its header") from None
        raise InputError(f"{path}: not a readable PLY file ({exc})") from None
    except Exception as exc:  # plyfile raises a variety of types on garbage
        raise InputError(f"{path}: not a readable PLY file ({exc})") from None
    if ply.text and not _ends_with_newline(path):
        # an ASCII file whose last row stops inside a value: writers end every row with an end of line
        last = ply.elements[-1] if ply.elements else None
        raise InputError(f"{path}: truncated: the file ends inside the last row"
                         + (f" of element '{last.name}'" if last is not None else "") + " (no end of line after it)")
    if "vertex" not in ply:
        raise InputError(f"{path}: PLY has no 'vertex' element")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    for k in ("x", "y", "z"):
        if k not in names:
            raise InputError(f"{path}: PLY vertex element has no '{k}' property")
    return ply, v, names


def _element_error(path: Path, exc: PlyElementParseError) -> InputError:
    """One line for plyfile's element errors; rows missing at the end of the file say ``truncated``
    with the rows the element declares and the complete rows the file holds."""
    el = exc.element
    if el is not None and exc.row is not None and (exc.message == "early end-of-file" or (
            exc.message in ("early end-of-line", "malformed input") and not _ends_with_newline(path))):
        return InputError(f"{path}: truncated: element '{el.name}' declares {el.count} rows, "
                          f"the file holds {exc.row}")
    return InputError(f"{path}: {exc}")


def _ends_with_newline(path: Path) -> bool:
    with open(path, "rb") as f:
        f.seek(0, 2)
        if f.tell() == 0:
            return False
        f.seek(-1, 2)
        return f.read(1) == b"\n"


def read_ply(path: Path, up: str = "z", require_velocity: bool = False) -> ParticleFrame:
    ply, v, names = read_vertices(path)
    pos = np.stack([v["x"], v["y"], v["z"]], axis=1)
    vel = np.stack([v["vx"], v["vy"], v["vz"]], axis=1) if all(k in names for k in ("vx", "vy", "vz")) else None
    if vel is None and require_velocity:
        raise InputError(f"{path}: missing properties 'vx', 'vy', 'vz' (velocity)")
    from .axes import to_z_up

    pos, vel = to_z_up(pos, vel, up)
    arrays = {k: np.asarray(v[k]) for k in names if k not in _CORE and k not in ("nx", "ny", "nz")}
    return ParticleFrame(
        positions=pos,
        velocities=vel,
        ids=np.asarray(v["id"]) if "id" in names else None,
        density=np.asarray(v["density"]) if "density" in names else None,
        arrays=arrays,
        source=str(path),
    )


def write_ply(path: Path, frame: ParticleFrame) -> None:
    n = len(frame)
    cols: list[tuple[str, np.ndarray]] = [
        ("x", frame.positions[:, 0]),
        ("y", frame.positions[:, 1]),
        ("z", frame.positions[:, 2]),
    ]
    vel = frame.velocities if frame.velocities is not None else np.zeros((n, 3), np.float32)
    cols += [("vx", vel[:, 0]), ("vy", vel[:, 1]), ("vz", vel[:, 2])]
    if frame.density is not None:
        cols.append(("density", frame.density))
    for k, a in frame.arrays.items():
        cols.append((k, a))
    cols.append(("id", frame.ids))
    dtype = []
    for k, a in cols:
        dt = np.dtype(a.dtype)
        if dt not in _DTYPES:
            dt = np.dtype(np.float32)
        dtype.append((k, _DTYPES[dt]))
    data = np.empty(n, dtype=dtype)
    for k, a in cols:
        data[k] = a
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(data, "vertex")], byte_order="<").write(str(tmp))


register("ply", (".ply",), read_ply, write_ply)
