"""Legacy VTK particle files (``.vtk``): DualSPHysics PartVTK, SPlisHSPlasH and others.

Read with the ``vtk`` package (meshio cannot read POLYDATA, which is what
DualSPHysics writes). Points become positions; point arrays are matched by
name, case-insensitively (:func:`whitecap.io.registry.find_array`):

- velocity: ``Vel`` (DualSPHysics), ``velocity`` (SPlisHSPlasH), ``v``
- density:  ``Rhop`` or ``Rho`` (DualSPHysics), ``density``
- ids:      ``Idp`` (DualSPHysics), ``id``
- ``Type``/``Mk`` (DualSPHysics) are kept in ``arrays``; when ``Type`` is
  present only fluid particles (Type 3) are returned.

A file cut short (a copy or a solver stopped mid-write) is refused with one line
naming the file and the array (:func:`check_legacy_vtk`): VTK itself reads an array
cut off inside its data as one of the declared length with a made-up tail.

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

import mmap
import os
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

    check_legacy_vtk(path)
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


def read_points(path: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The points of a legacy VTK point data set, (N, 3) as stored, and its point arrays by name
    (every particle, whatever its Type: DualSPHysics boundary particles too)."""
    from vtk.util.numpy_support import vtk_to_numpy

    ds = _read_dataset(Path(path))
    return vtk_to_numpy(ds.GetPoints().GetData()).reshape(-1, 3), point_arrays(ds)


def read_vtk(path: Path, up: str = "z", require_velocity: bool = True, by_id: bool = False) -> ParticleFrame:
    pos, arrays = read_points(path)
    pos = pos.astype(np.float32)
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


# ----------------------------------------------------------------------------- truncation check
# VTK reads a legacy file cut inside an array as an array of the declared length whose tail is
# whatever was in memory (silently for ASCII, with a warning on stderr for binary), so what the
# headers declare is checked against what the file holds before VTK parses it. Binary: the
# header lines are walked and each data block skipped by its declared size (a few reads and
# seeks per file). ASCII: a file is only ever cut at its end, so the values after the last
# header line are counted against what that header declares (the last block, not the file;
# about 2 % of VTK's own time on an ASCII file). A file cut exactly between two whole arrays
# reads as a file without the later arrays: for binary files the walk still says truncated
# (a FIELD holding fewer arrays than it declares); for ASCII ones only the FIELD's count, when
# nothing follows it, is checked.

#: bytes per value of each legacy VTK type (vtkIdType is written as int; bit arrays are packed)
_TYPE_BYTES = {"bit": 0, "unsigned_char": 1, "char": 1, "signed_char": 1, "short": 2, "unsigned_short": 2,
               "int": 4, "unsigned_int": 4, "long": 8, "unsigned_long": 8, "float": 4, "double": 8,
               "vtktypeint64": 8, "vtktypeuint64": 8, "vtkidtype": 4}
_CELLS = {b"VERTICES", b"LINES", b"POLYGONS", b"TRIANGLE_STRIPS", b"CELLS"}
_COORDINATES = {b"X_COORDINATES", b"Y_COORDINATES", b"Z_COORDINATES"}
_NO_DATA = {b"DATASET", b"DIMENSIONS", b"ORIGIN", b"SPACING", b"ASPECT_RATIO"}
#: point/cell attributes -> values per point (0: given on the header line)
_ATTRIBUTES: dict[bytes, int] = {
    b"SCALARS": 0, b"VECTORS": 3, b"NORMALS": 3, b"TENSORS": 9, b"TENSORS6": 6,
    b"GLOBAL_IDS": 1, b"PEDIGREE_IDS": 1, b"TEXTURE_COORDINATES": 0, b"COLOR_SCALARS": 0}
#: lines of a METADATA block (after an array's data; nothing is counted in them)
_METADATA = {b"METADATA", b"INFORMATION", b"NAME", b"DATA", b"COMPONENT_NAMES"}
_KEYWORDS = ({b"POINTS", b"CELL_TYPES", b"POINT_DATA", b"CELL_DATA", b"FIELD", b"LOOKUP_TABLE", b"OFFSETS",
              b"CONNECTIVITY", b"NULL_ARRAY"} | _CELLS | _COORDINATES | _NO_DATA | set(_ATTRIBUTES) | _METADATA)
#: the tail searched first for an ASCII file's last header line [bytes]; doubled until one is found
_TAIL = 1 << 20


class _Unknown(Exception):
    """A layout this check does not follow (string arrays, another writer's keyword): VTK decides."""


def _truncated(path: Path, what: str, declared: int, held: int) -> InputError:
    return InputError(f"{path}: truncated: {what} declares {declared} values, the file holds {held}")


def _ends_inside(path: Path, line: bytes) -> InputError:
    text = line.decode("latin-1").strip()
    return InputError(f"{path}: truncated: the file ends inside the line '{text[:60]}'")


def _field_array(parts: list[bytes]) -> bool:
    """Whether a line is a FIELD array's header: NAME COMPONENTS TUPLES TYPE."""
    return (len(parts) == 4 and parts[1].isdigit() and parts[2].isdigit()
            and parts[3].decode("latin-1").lower() in (*_TYPE_BYTES, "string", "utf8_string", "variant"))


def check_legacy_vtk(path: str | Path) -> None:
    """Raise InputError (one line: the file, ``truncated``, the array, declared and held values)
    when a legacy VTK file ends before the data its headers declare. Layouts this check does not
    follow are left to VTK."""
    p = Path(path)
    try:
        with open(p, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            head = [f.readline() for _ in range(3)]
            if not head[0].startswith(b"# vtk DataFile"):
                if size and b"# vtk DataFile".startswith(head[0]) and not head[0].endswith(b"\n"):
                    raise InputError(f"{p}: truncated: the file ends inside its header")
                return
            if not head[2].endswith(b"\n"):
                raise InputError(f"{p}: truncated: the file ends inside its header")
            fmt = head[2].strip().upper()
            if fmt == b"BINARY":
                _BinaryWalk(p, f, size).walk()
            elif fmt == b"ASCII":
                version = head[0].split()[-1] if head[0].split() else b"3.0"
                _check_ascii_tail(p, f, size, new_cells=not version.startswith((b"1.", b"2.", b"3.", b"4.")))
    except _Unknown:
        return
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None


class _BinaryWalk:
    def __init__(self, path: Path, f, size: int):
        self.path, self.f, self.size = path, f, size
        self.count = 0  # values per array of the current POINT_DATA / CELL_DATA

    def line(self, header_expected: bool = False) -> bytes | None:
        """The next non-blank header line (stripped), None at the end of the file. A last line
        with no end of line is a header cut short when it starts with a keyword (or wherever
        ``header_expected``); otherwise it is a layout not followed here."""
        while True:
            raw = self.f.readline()
            if not raw:
                return None
            s = raw.strip()
            if not raw.endswith(b"\n") and s:
                if header_expected or s[:1].isalpha() and s.isascii() and all(32 <= c < 127 or c == 9 for c in s):
                    raise _ends_inside(self.path, s)
                raise _Unknown
            if s:
                return s

    def peek(self, keyword: bytes) -> list[bytes] | None:
        """The next line's words when it starts with ``keyword`` (consumed), else None (not consumed)."""
        at = self.f.tell()
        raw = self.f.readline()
        if raw.lstrip().upper().startswith(keyword):
            if not raw.endswith(b"\n"):
                raise _ends_inside(self.path, raw)
            return raw.split()
        self.f.seek(at)
        return None

    def block(self, what: str, count: int, typ: bytes) -> None:
        t = typ.decode("latin-1").lower()
        if t not in _TYPE_BYTES:
            raise _Unknown  # strings and variants have no fixed size
        nb = _TYPE_BYTES[t]
        need = (count + 7) // 8 if nb == 0 else count * nb
        start = self.f.tell()
        left = self.size - start
        if need > left:
            raise _truncated(self.path, what, count, left * 8 if nb == 0 else left // nb)
        self.f.seek(start + need)

    def walk(self) -> None:
        pending: str | None = "the header"  # a header that promises more to follow
        while (s := self.line()) is not None:
            pending = None
            parts = s.split()
            key = parts[0].upper()
            try:
                pending = self.section(key, parts)
            except (IndexError, ValueError):
                raise _Unknown from None
            if key == b"DATASET" and parts[1:2] != [b"STRUCTURED_POINTS"]:
                pending = b" ".join(parts).decode("latin-1")  # the points must follow
        if pending == "the header":
            raise InputError(f"{self.path}: truncated: the file ends after its header")
        if pending:
            raise InputError(f"{self.path}: truncated: the file ends after the line '{pending}'")

    def section(self, key: bytes, parts: list[bytes]) -> str | None:
        if key in _NO_DATA:
            return None
        if key == b"POINTS":
            self.block("block 'POINTS'", 3 * int(parts[1]), parts[2])
        elif key in _COORDINATES:
            self.block(f"block '{key.decode()}'", int(parts[1]), parts[2])
        elif key in _CELLS:
            self.cells(key.decode(), int(parts[1]), int(parts[2]))
        elif key == b"CELL_TYPES":
            self.block("block 'CELL_TYPES'", int(parts[1]), b"int")
        elif key in (b"POINT_DATA", b"CELL_DATA"):
            self.count = int(parts[1])
            return b" ".join(parts).decode("latin-1") if self.count > 0 else None
        elif key == b"FIELD":
            self.field(parts[1].decode("latin-1"), int(parts[2]))
        elif key in _ATTRIBUTES:
            name = parts[1].decode("latin-1")
            width, typ = _ATTRIBUTES[key], parts[2] if len(parts) > 2 else b""
            if key == b"SCALARS":
                width = int(parts[3]) if len(parts) > 3 else 1
                self.peek(b"LOOKUP_TABLE")
            elif key == b"TEXTURE_COORDINATES":
                width, typ = int(parts[2]), parts[3]
            elif key == b"COLOR_SCALARS":
                width, typ = int(parts[2]), b"unsigned_char"
            self.block(f"array '{name}'", width * self.count, typ)
        elif key == b"LOOKUP_TABLE":
            self.block(f"lookup table '{parts[1].decode('latin-1')}'", 4 * int(parts[2]), b"unsigned_char")
        elif key == b"METADATA":
            self.metadata()
        else:
            raise _Unknown
        return None

    def cells(self, key: str, n: int, size: int) -> None:
        offsets = self.peek(b"OFFSETS")
        if offsets is None:  # VTK < 5: one list of counts and point indices
            self.block(f"block '{key}'", size, b"int")
            return
        self.block(f"block '{key}' (offsets)", n, offsets[1])
        conn = self.line()
        if conn is None:
            raise _truncated(self.path, f"block '{key}' (connectivity)", size, 0)
        if not conn.upper().startswith(b"CONNECTIVITY"):
            raise _Unknown
        self.block(f"block '{key}' (connectivity)", size, conn.split()[1])

    def field(self, name: str, k: int) -> None:
        for i in range(k):
            s = self.line(header_expected=True)
            while s is not None and s.upper() == b"METADATA":
                self.metadata()
                s = self.line(header_expected=True)
            if s is None:
                raise InputError(f"{self.path}: truncated: field '{name}' declares {k} arrays, the file holds {i}")
            parts = s.split()
            if parts[0].upper() == b"NULL_ARRAY":
                continue
            if not _field_array(parts):
                raise _Unknown
            self.block(f"array '{parts[0].decode('latin-1')}'", int(parts[1]) * int(parts[2]), parts[3])

    def metadata(self) -> None:
        """Skip a METADATA block: text lines up to a blank one."""
        while (raw := self.f.readline()) and raw.strip():
            pass


def _check_ascii_tail(path: Path, f, size: int, new_cells: bool) -> None:
    """The values after an ASCII file's last header line against what that header declares."""
    if size == 0:
        return
    with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        last = mm[size - 1:size]
        if last != b"\n":  # the file ends inside a line: a header's, or a value's
            nl = mm.rfind(b"\n")
            words = mm[nl + 1:size].split()
            if words and words[0][:1].isalpha() and not _all_numbers(words):  # not nan/inf values
                raise _ends_inside(path, mm[nl + 1:size])
        hdr = _last_header(mm, size)
        if hdr is None:
            raise InputError(f"{path}: truncated: the file ends after its header")
        start, end, classes = hdr
        parts = mm[start:end].split()
        key = parts[0].upper()
        try:
            if (key in (b"POINT_DATA", b"CELL_DATA", b"FIELD") and int(parts[-1]) > 0 or key == b"DATASET"
                    and parts[1:2] != [b"STRUCTURED_POINTS"]) and not mm[end:size].strip():
                raise InputError(f"{path}: truncated: the file ends after the line "
                                 f"'{mm[start:end].decode('latin-1').strip()}'")
            what, declared = _ascii_declared(mm, start, end, parts, key, new_cells)
        except (IndexError, ValueError):
            raise _Unknown from None
        if what is None:
            return
        held = _count_values(classes)  # the values begin after the header line's end
        if held < declared:
            raise _truncated(path, what, declared, held)
        if held == declared and last not in b" \t\r\n":
            # every value is there but the file stops right after the last one: it may be cut short
            # (writers end the file with an end of line)
            raise InputError(f"{path}: truncated: the file ends inside the last value of {what} "
                             "(no end of line after it)")


def _all_numbers(words: list[bytes]) -> bool:
    try:
        [float(w) for w in words]
    except ValueError:
        return False
    return True


#: bytes.translate table for the tail of an ASCII file: letters -> "A", end of line kept, other
#: blanks -> " ", anything else -> "x"
_CLASSES = bytes(10 if c == 10 else 32 if c <= 32 else 65 if chr(c).isascii() and chr(c).isalpha() else 120
                 for c in range(256))


def _last_header(mm, size: int) -> tuple[int, int, bytes] | None:
    """(start, end) of the last header line of the file and the file from ``end`` on as
    :data:`_CLASSES`; None when there is no header. Only lines that start with a letter are
    looked at (values never do), found with ``rfind`` on the translated tail."""
    n, start, classes = _TAIL, size, b""
    below = size + 2  # candidates "\nA" at or after this offset were looked at
    while start > 0:
        seen, start = start, max(0, size - n)
        classes = mm[start:seen].translate(_CLASSES) + classes
        while (k := classes.rfind(b"\nA", 0, below - start)) >= 0:
            at = start + k + 1
            end = mm.find(b"\n", at)
            end = size if end < 0 else end
            parts = mm[at:end].split()
            if parts and (parts[0].upper() in _KEYWORDS or _field_array(parts)):
                return at, end, classes[end - start:]
            below = start + k + 1
        n *= 2
    return None


def _line_before(mm, at: int) -> tuple[int, int]:
    """(start, end) of the non-blank line before the one starting at ``at``."""
    end = at - 1
    while end > 0:
        begin = mm.rfind(b"\n", 0, end) + 1
        if mm[begin:end].strip():
            return begin, end
        end = begin - 1
    raise _Unknown


def _attribute_count(mm, at: int) -> int:
    """Values per array of the POINT_DATA / CELL_DATA section the line at ``at`` is in."""
    k = max(mm.rfind(b"POINT_DATA", 0, at), mm.rfind(b"CELL_DATA", 0, at))
    if k < 0:
        raise _Unknown
    return int(mm[k:mm.find(b"\n", k)].split()[1])


def _ascii_declared(mm, start: int, end: int, parts: list[bytes], key: bytes,
                    new_cells: bool) -> tuple[str | None, int]:
    """(what, values declared) of the block the header at ``start`` opens; what is None when it
    opens nothing to count."""
    if _field_array(parts):
        return f"array '{parts[0].decode('latin-1')}'", int(parts[1]) * int(parts[2])
    if key == b"LOOKUP_TABLE" and len(parts) == 2:  # a SCALARS' table line: the values follow it
        start, end = _line_before(mm, start)
        parts = mm[start:end].split()
        key = parts[0].upper()
        if key != b"SCALARS":
            raise _Unknown
    if key == b"POINTS":
        return "block 'POINTS'", 3 * int(parts[1])
    if key in _COORDINATES:
        return f"block '{key.decode()}'", int(parts[1])
    if key in _CELLS:
        return f"block '{key.decode()}'" + (" (offsets)" if new_cells else ""), int(parts[2 - new_cells])
    if key in (b"OFFSETS", b"CONNECTIVITY"):
        s, e = _line_before(mm, start)
        if key == b"CONNECTIVITY":
            k = mm.rfind(b"OFFSETS", 0, start)
            s, e = _line_before(mm, mm.rfind(b"\n", 0, k) + 1)
        cell = mm[s:e].split()
        if cell[0].upper() not in _CELLS:
            raise _Unknown
        n = int(cell[1]) if key == b"OFFSETS" else int(cell[2])
        return f"block '{cell[0].decode()}' ({key.decode().lower()})", n
    if key == b"CELL_TYPES":
        return "block 'CELL_TYPES'", int(parts[1])
    if key in _ATTRIBUTES:
        width = _ATTRIBUTES[key]
        if key == b"SCALARS":
            width = int(parts[3]) if len(parts) > 3 else 1
        elif key in (b"TEXTURE_COORDINATES", b"COLOR_SCALARS"):
            width = int(parts[2])
        return f"array '{parts[1].decode('latin-1')}'", width * _attribute_count(mm, start)
    if key == b"LOOKUP_TABLE":
        return f"lookup table '{parts[1].decode('latin-1')}'", 4 * int(parts[2])
    return None, 0


def _count_values(block: bytes) -> int:
    """Whitespace-separated values in ``block``: the starts of runs of non-blank bytes (numpy)."""
    solid = np.frombuffer(block, np.uint8) > 32
    return int(solid[:1].sum()) + int(np.count_nonzero(solid[1:] & ~solid[:-1]))


register("vtk", (".vtk",), read_vtk, None, check=check_legacy_vtk)
register("vtk", (".vtk",), read_mesh_vtk, None, kind=MESH, check=check_legacy_vtk)
