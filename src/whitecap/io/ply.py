"""Binary little-endian PLY particle files (plyfile).

Fluid frames carry ``x y z vx vy vz density id``; diffuse frames add
``type lifetime radius``. Any extra float/int vertex property is read into
``ParticleFrame.arrays``. A file cut short is refused with one line: the file,
``truncated``, the element and its declared and held rows.

PLY is parsed in one place, plyfile through :func:`read_vertices`: the registry's particle and
mesh readers and the Blender add-on (:func:`read_geometry`, every vertex property and polygons of
any size) all go through it. The add-on carries this module and plyfile itself as a pure-Python
wheel (``whitecap blender-addon``), so plyfile is imported only where a file is read or written.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .atomic import atomic_path
from .frame import ParticleFrame
from .registry import register
from .threads import process_pool

_CORE = ("x", "y", "z", "vx", "vy", "vz", "density", "id")
_DTYPES = {np.dtype(np.float32): "f4", np.dtype(np.uint32): "u4", np.dtype(np.uint8): "u1", np.dtype(np.int32): "i4"}


def read_vertices(path: Path, known_list_len: dict | None = None, other_lengths: bool = False):
    """(PlyData, vertex records, property names) of a PLY with x y z, or InputError naming the file.

    ``known_list_len`` ({element: {list property: length}}) lets plyfile map
    fixed-length lists (triangles) straight from the file instead of parsing
    them row by row; a row of another length raises a PlyElementParseError
    naming the element and row, or with ``other_lengths`` reads the file again
    row by row (polygons of any size).
    """
    from plyfile import PlyData, PlyElementParseError, PlyHeaderParseError

    try:
        ply = PlyData.read(str(path), known_list_len=known_list_len or {})
    except PlyElementParseError as exc:
        if other_lengths and known_list_len and exc.message == "unexpected list length":
            return read_vertices(path)
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


def _element_error(path: Path, exc) -> InputError:
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


#: a face element's list of corners, by the names writers give it
FACE_LISTS = ("vertex_indices", "vertex_index")


def read_geometry(path: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray | None,
                                              np.ndarray | None]:
    """(points (N, 3), every other scalar vertex property by name in native byte order, polygons as
    flat corner indices and each polygon's first corner (None without faces)): what a viewer shows,
    the Blender add-on's PLY reader. Triangles are mapped in one go; other polygons row by row."""
    path = Path(path)
    ply, v, names = read_vertices(path, {"face": {k: 3 for k in FACE_LISTS}}, other_lengths=True)

    def native(a):
        a = np.asarray(a)
        return a.astype(a.dtype.newbyteorder("="))

    points = np.stack([native(v["x"]), native(v["y"]), native(v["z"])], axis=1)
    arrays = {k: native(v[k]) for k in names if k not in ("x", "y", "z") and v.dtype[k].kind != "O"}
    loops = starts = None
    if "face" in ply and ply["face"].count:
        data = ply["face"].data
        key = next((k for k in FACE_LISTS if k in (data.dtype.names or ())), None)
        if key is not None and data[key].dtype != object:  # mapped as triangles
            loops = np.asarray(data[key], np.int32).ravel()
            starts = np.arange(0, len(loops), 3, dtype=np.int32)
        elif key is not None:
            rows = [np.asarray(r, np.int32) for r in data[key] if len(r) >= 3]
            if rows:
                loops = np.concatenate(rows)
                starts = np.concatenate([[0], np.cumsum([len(r) for r in rows])[:-1]]).astype(np.int32)
    return points, arrays, loops, starts


def read_ply(path: Path, up: str = "z", require_velocity: bool = False) -> ParticleFrame:
    ply, v, names = read_vertices(path)
    pos = _vectors(v, ("x", "y", "z"))
    vel = _vectors(v, ("vx", "vy", "vz")) if all(k in names for k in ("vx", "vy", "vz")) else None
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


_PACKING = threading.local()  # each writing thread's record buffer (``buf``), kept from file to file


def _records(n: int, dtype: np.dtype) -> np.ndarray:
    """``n`` records of ``dtype`` in this thread's kept buffer, grown when a file needs more and never shrunk.
    A new array for every file was a new 100 MB of pages to fault in for each frame of 2.7 M diffuse
    particles (on an H100 machine 180 ms a diffuse file against 15 ms to write its bytes); kept, they are
    faulted in once. Per thread: two writers may pack at once."""
    need = n * dtype.itemsize
    buf = getattr(_PACKING, "buf", None)
    if buf is None or buf.nbytes < need:
        _PACKING.buf = None  # the old buffer goes before the new one is made
        buf = _PACKING.buf = np.empty(max(need, 1), np.uint8)
    return buf[:need].view(dtype)


#: Rows of a PLY packed and written by several threads at once above this many bytes a part: each thread packs a
#: run of rows into the kept buffer and writes it at its own offset of the temporary file (os.pwrite). One thread
#: packing and writing a 2.5 M-particle diffuse file (111 MB) took 150-210 ms on an H100 machine, longer than the
#: solver's frame, so the background writer set the pace of `simulate` with foam there. On that machine (16 cores,
#: ext4 on a virtual disk), parts of 4 MB against 16: a 1 M-particle fluid file 35-40 against
#: 62-66 ms (8 parts, not 2), a 2.7 M diffuse file 117-124 against 121-132 ms with 16 threads. With few cores the
#: parts' threads take them from the stage's own: on 2 cores `whitecap foam` at 100k (10 MB diffuse files, 2 parts
#: of 4 MB against one write) ran at 0.92x and 0.96x the rate with 16 MB parts (`bench_foam.py`, pairs' medians of
#: two runs), so there the parts stay at 16 MB. The parts' threads pack in parallel, but their writes to the one file
#: take turns (ext4 holds the file's inode lock through each write): a frame's files gain by being written side by
#: side, on the background writer's lanes (io.writer).
PART_BYTES = (4 << 20) if (os.cpu_count() or 1) >= 8 else (16 << 20)
#: threads that pack and write the parts of one large file (never more than the machine's cores); 16 against 8:
#: 117-124 against 124-132 ms a 2.7 M diffuse file on the H100 machine
WRITE_THREADS = min(16, os.cpu_count() or 1)


def _parts(n: int, itemsize: int) -> list[tuple[int, int]]:
    """Runs of rows [a, b) for one file's parts: one where the file is small or one thread writes."""
    k = max(1, min(WRITE_THREADS, (n * itemsize) // PART_BYTES))
    edges = [n * i // k for i in range(k + 1)]
    return list(zip(edges[:-1], edges[1:]))


def _pack(data: np.ndarray, groups: list, a: int, b: int) -> None:
    """Rows a..b of ``groups`` (property names, array) into the records ``data``."""
    n = b - a
    rows = data[a:b]
    for names, arr in groups:
        part = arr[a:b]
        if len(names) == 3 and part.dtype == np.float32 and part.flags.c_contiguous:
            # the three components as one 12-byte item a row: a third of the copies (fewer turns of the GIL)
            _field_bytes(rows, names[0], 12)[...] = part.reshape(n, 3).view("V12")[:, 0]
        else:
            for c, k in enumerate(names):
                rows[k] = part[:, c] if len(names) > 1 else part


def _pwrite_all(fd: int, buf, offset: int) -> None:
    """All of ``buf`` (bytes, or a 1-D uint8 array) at ``offset`` of the open file ``fd``."""
    view = memoryview(buf)
    while len(view):
        done = os.pwrite(fd, view, offset)
        view, offset = view[done:], offset + done


def _groups(frame: ParticleFrame) -> list[tuple[tuple[str, ...], np.ndarray]]:
    """(property names, array) of a frame's vertex records, in the file's order: a vector's three components side
    by side, a column's one."""
    n = len(frame)
    vel = frame.velocities if frame.velocities is not None else np.zeros((n, 3), np.float32)
    groups: list[tuple[tuple[str, ...], np.ndarray]] = [(("x", "y", "z"), frame.positions), (("vx", "vy", "vz"), vel)]
    if frame.density is not None:
        groups.append((("density",), frame.density))
    groups += [((k,), a) for k, a in frame.arrays.items()]
    groups.append((("id",), frame.ids))
    return groups


def _record_dtype(groups: list[tuple[tuple[str, ...], np.ndarray]]) -> np.dtype:
    dtype = []
    for names, a in groups:
        dt = np.dtype(a.dtype)
        dtype += [(k, _DTYPES[dt if dt in _DTYPES else np.dtype(np.float32)]) for k in names]
    return np.dtype(dtype)


def record_dtype(frame: ParticleFrame) -> np.dtype:
    """The vertex record :func:`write_ply` writes for a frame with these arrays (packed, little-endian): a
    producer that makes its frames' records itself (the solver and the foam stage, on the device: sim.records)
    builds them to this layout, and ParticleFrame.from_records hands them over."""
    return _record_dtype(_groups(frame))


def field_offsets(dtype: np.dtype) -> dict[str, int]:
    """Where each field of a record starts, in bytes."""
    fields = dtype.fields
    return {} if fields is None else {k: int(v[1]) for k, v in fields.items()}


def _packed(frame: ParticleFrame, groups: list, dtype: np.dtype) -> np.ndarray | None:
    """The frame's records as they are, where its arrays are the fields of one record array of the layout written
    (``frame.records``, ParticleFrame.from_records: the same memory, so the same values even if written through
    the arrays since); else None, and the rows are packed here. An array put in a field's place since (another
    object) has another address, so it is never written from records that no longer hold it."""
    rec = frame.records
    if rec is None or rec.dtype != dtype or rec.ndim != 1 or len(rec) != len(frame):
        return None
    base, at = rec.__array_interface__["data"][0], field_offsets(dtype)
    for names, a in groups:
        if (a.__array_interface__["data"][0] != base + at[names[0]] or not a.strides
                or a.strides[0] != dtype.itemsize):
            return None
    return rec


def _header(ply) -> bytes:
    """The bytes of plyfile's header for the PlyData ``ply``, as its write puts them before the rows."""
    return (ply.header + "\n").encode("ascii")


def write_ply(path: Path, frame: ParticleFrame) -> None:
    from plyfile import PlyData, PlyElement

    n = len(frame)
    groups = _groups(frame)
    dtype = _record_dtype(groups)
    packed = _packed(frame, groups, dtype) if n else None
    data = packed if packed is not None else _records(n, dtype)
    ply = PlyData([PlyElement.describe(data, "vertex")], byte_order="<")
    # Parts are for packing in parallel: records made elsewhere (ParticleFrame.from_records) go in one write. Writes
    # to one file take turns whatever the threads (ext4's inode lock), and each part is a turn of the GIL for a pool
    # thread, which on the H100 machine waited up to Python's switch interval (5 ms) beside a busy loop. A 2.7 M
    # diffuse file of records on 2 cores, one write against 2 parts: 28-34 against 28-32 ms (ext4), 38-40 against
    # 38-44 (tmpfs), the 4 fastest of 6 each.
    parts = _parts(n, data.dtype.itemsize) if packed is None else [(0, n)]
    with atomic_path(path) as tmp:
        if len(parts) == 1:
            if packed is None and n:  # (no rows: nothing to pack)
                _pack(data, groups, 0, n)
            ply.write(str(tmp))
            return
        # (arrays only: records made elsewhere are written whole above) plyfile's own header, then each part's rows,
        # packed, at its offset: the bytes plyfile writes from the whole array
        head = _header(ply)
        fd = os.open(tmp, os.O_WRONLY | os.O_TRUNC)
        try:
            _pwrite_all(fd, head, 0)

            def part(ab: tuple[int, int]) -> None:
                a, b = ab
                _pack(data, groups, a, b)
                _pwrite_all(fd, data[a:b].view(np.uint8), len(head) + a * data.dtype.itemsize)

            pool = process_pool("whitecap-ply", WRITE_THREADS)
            jobs = [pool.submit(part, ab) for ab in parts]
            for job in jobs:  # every part done (or failed) before the file is closed: no write after the close
                job.exception()
            for job in jobs:
                job.result()  # the first part's error (a full disk), raised here
        finally:
            os.close(fd)


_F32 = np.dtype("<f4")


def _vectors(v: np.ndarray, names: tuple[str, str, str]) -> np.ndarray:
    """The three properties ``names`` of the records ``v`` as an (N, 3) array: where they are little-endian
    float32 side by side (as whitecap and most solvers write them), copied as one 12-byte item a row, a third of
    the copies of stacking the columns (a 98k-particle frame read in 2.4 ms, of which 1.5 were the stacks)."""
    fields = v.dtype.fields or {}
    first = fields[names[0]][1]
    if all(fields[k][0] == _F32 and fields[k][1] == first + 4 * c for c, k in enumerate(names)):
        return np.ascontiguousarray(_field_bytes(v, names[0], 12)).view(_F32).reshape(len(v), 3)
    return np.stack([v[k] for k in names], axis=1)


def _field_bytes(data: np.ndarray, name: str, size: int) -> np.ndarray:
    """The ``size`` bytes of each record of ``data`` from field ``name`` on, as one void item a row (a view)."""
    offset = data.dtype.fields[name][1]
    return data.view(np.dtype({"names": ["b"], "formats": [f"V{size}"], "offsets": [offset],
                               "itemsize": data.dtype.itemsize}))["b"]


_PLY_BYTES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
              "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def check_ply(path: Path) -> None:
    """The cheap completeness check (:func:`whitecap.io.registry.check`): for a binary file of
    fixed-size rows, the size the header declares against the file's size; for an ASCII file, its
    lines (one per row) against the rows declared, and an end of line at the end. Anything else
    (lists in a binary file, a bad header) and any shortfall is read for the exact error."""
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(1 << 16)
        f.seek(0, 2)
        size = f.tell()
    end = head.find(b"end_header")
    nl = head.find(b"\n", end)
    if end < 0 or nl < 0:
        read_vertices(path)
        return
    words = [ln.split() for ln in head[:end].decode("latin-1").splitlines()]
    fmt = next((w[1] for w in words if len(w) > 1 and w[0] == "format"), "")
    if fmt == "ascii":  # one row per line: count the lines (no parse)
        rows = sum(int(w[2]) for w in words if len(w) == 3 and w[0] == "element" and w[2].isdigit())
        with open(path, "rb") as f:
            f.seek(nl + 1)
            if f.read().count(b"\n") < rows or not _ends_with_newline(path):
                read_vertices(path)
        return
    offset = nl + 1
    elements: list[list[Any]] = []  # [name, rows, bytes a row]
    for w in words:
        if w and w[0] == "element" and len(w) == 3 and w[2].isdigit():
            elements.append([w[1], int(w[2]), 0])
        elif w and w[0] == "property" and elements:
            if len(w) != 3 or w[1] not in _PLY_BYTES:  # a list, or a type not known here
                read_vertices(path)
                return
            elements[-1][2] += _PLY_BYTES[w[1]]
    for name, count, row in elements:
        if offset + count * row > size:
            raise InputError(f"{path}: truncated: element '{name}' declares {count} rows, "
                             f"the file holds {(size - offset) // row if row else 0}")
        offset += count * row


def written_as_read(path: Path, frame: ParticleFrame, up: str = "z", require_velocity: bool = False) -> bool:
    """Whether :func:`write_ply` writes ``frame``, read from the PLY file ``path`` by :func:`read_ply` with these
    options (and not changed since), as that file's very bytes: read as it is (z up), the file's header the one
    write_ply writes for the frame, and nothing after its rows. The values are the file's, so its rows are
    the bytes write_ply would pack (io.registry.write_copy copies the file instead)."""
    if up != "z":
        return False
    from plyfile import PlyData, PlyElement

    dtype = _record_dtype(_groups(frame))
    rows = np.broadcast_to(np.zeros(1, dtype), (len(frame),))  # the header needs the count, not the rows
    head = _header(PlyData([PlyElement.describe(rows, "vertex")], byte_order="<"))
    try:
        if path.stat().st_size != len(head) + len(frame) * dtype.itemsize:
            return False
        with open(path, "rb") as f:
            return f.read(len(head)) == head
    except OSError:
        return False


register("ply", (".ply",), read_ply, write_ply, check=check_ply, as_read=written_as_read)
