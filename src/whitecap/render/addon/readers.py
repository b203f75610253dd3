"""The add-on's readers: whitecap's own format modules where they can run in Blender, numpy
readers for the rest, and meshio for every other format.

Blender bundles numpy; the extension carries meshio and plyfile as wheels and copies of whitecap's
format modules (``whitecap blender-addon``, render/driver.py's ADDON_SHARED). Each reader returns
a :class:`Geometry`: points, polygons (flat vertex indices plus the start of each polygon) and
every point array by the name the file gives it. :func:`read` picks the reader from the
extension. Errors are ``ValueError`` with one line that starts with the file.

One parse per format (issue 33). whitecap's registry readers and these share the low-level parse
and differ only in what they keep (the registry: the fluid's standard arrays, y up turned, triangles;
here: every point array and polygon):
- BGEO: ``io/bgeo.read_points`` (numpy; no library reads partio's format);
- PLY: ``io/ply.read_geometry`` on ``read_vertices`` (plyfile, a pure-Python wheel here);
- VTU: ``io/vtu.read_mesh`` (meshio's VTU reader, which the extension carries anyway).
Still parsed twice, and why:
- legacy VTK: the registry reads with the ``vtk`` package (compiled, no wheel Blender could carry;
  meshio cannot read POLYDATA), here with :class:`_LegacyVTK`. The way to one parse is to move this
  numpy parser into ``io/vtk_legacy`` as ``read_points``' parse (its ASCII values cast to the declared
  type, and the raw cells kept for ``read_mesh_vtk``'s triangle check) and drop ``vtk`` from reading;
- VTP: no registry format; ``io/vtk_xml.read_vtp`` (vtk, for tests and tools) against
  :func:`read_vtk_xml` here;
- OBJ: the registry reads with trimesh (too large for the extension's wheels), here with
  :func:`read_obj`, which also says "truncated" on a cut file (meshio and trimesh read one silently);
- STL: read here only (:func:`read_stl`); whitecap loads obstacle STLs with trimesh.
tests/test_addon.py reads the same files with both and compares them.

Formats: legacy VTK 3.0 to 5.1 (ASCII or binary; POLYDATA and UNSTRUCTURED_GRID), VTK XML
``.vtu`` and ``.vtp`` (ascii, base64 or appended data, zlib-compressed or not), PLY (ascii and
binary), OBJ, STL (obstacles) and partio's BGEO version 5 (SPlisHSPlasH's ``.bgeo``,
gzip-compressed or not).
"""

import base64
import os
import re
import struct
import xml.etree.ElementTree as ET
import zlib

import numpy as np

try:  # inside the extension: the copies ``whitecap blender-addon`` puts in its whitecap folder
    from .whitecap.errors import WhitecapError
    from .whitecap.io import bgeo as _bgeo, ply as _ply, vtu as _vtu
except ImportError:  # whitecap's source tree, or this file loaded on its own (tests)
    from whitecap.errors import WhitecapError
    from whitecap.io import bgeo as _bgeo, ply as _ply, vtu as _vtu

EXTENSIONS = (".vtk", ".vtu", ".vtp", ".ply", ".obj", ".bgeo")


class Geometry:
    """Points (N, 3) float32; polygons as ``loops`` (flat vertex indices) and ``starts``
    (each polygon's first loop); ``arrays``: point arrays by name, (N,) or (N, k)."""

    def __init__(self, points, loops=None, starts=None, arrays=None):
        self.points = np.ascontiguousarray(points, np.float32).reshape(-1, 3)
        self.loops = np.zeros(0, np.int32) if loops is None else np.ascontiguousarray(loops, np.int32).ravel()
        self.starts = np.zeros(0, np.int32) if starts is None else np.ascontiguousarray(starts, np.int32).ravel()
        self.arrays = dict(arrays or {})
        self.normals = None  # (N, 3) where the file has point normals

    def __len__(self):
        return len(self.points)

    def check(self, path):
        """Every array has one value per point and every corner names a point, else a one-line
        ValueError naming the file and saying truncated."""
        n = len(self.points)
        for k, v in self.arrays.items():
            if len(v) != n:
                raise ValueError(f"{path}: array '{k}' has {len(v)} values for {n} points (truncated?)")
        if len(self.loops) and (self.loops.max() >= n or self.loops.min() < 0):
            raise ValueError(f"{path}: a polygon names point {int(self.loops.max())} of {n} (truncated?)")
        if len(self.starts) and self.starts.max() >= max(len(self.loops), 1):
            raise ValueError(f"{path}: polygons start past the {len(self.loops)} corners listed (truncated?)")
        return self


def _polygons(offsets, conn, keep=None):
    """(loops, starts) from VTK-style offsets (n + 1 entries) and connectivity, keeping
    the cells where ``keep`` is true and that have three corners or more."""
    offsets = np.asarray(offsets, np.int64)
    sizes = np.diff(offsets)
    sel = sizes >= 3 if keep is None else (sizes >= 3) & keep
    if not sel.any():
        return np.zeros(0, np.int32), np.zeros(0, np.int32)
    if sel.all():
        loops = np.asarray(conn[offsets[0]:offsets[-1]], np.int32)
        return loops, (offsets[:-1] - offsets[0]).astype(np.int32)
    idx = np.concatenate([np.arange(offsets[i], offsets[i + 1]) for i in np.nonzero(sel)[0]])
    starts = np.concatenate([[0], np.cumsum(sizes[sel])[:-1]])
    return np.asarray(conn, np.int64)[idx].astype(np.int32), starts.astype(np.int32)


def _counted_cells(v):
    """VTK legacy cell list [n, i1..in, n, ...] -> (offsets, connectivity)."""
    v = np.asarray(v, np.int64)
    offs, k = [0], 0
    conn = []
    while k < len(v):
        n = int(v[k])
        conn.append(v[k + 1:k + 1 + n])
        offs.append(offs[-1] + n)
        k += n + 1
    return np.array(offs, np.int64), (np.concatenate(conn) if conn else np.zeros(0, np.int64))


# ----------------------------------------------------------------------------- legacy VTK
_VTK_TYPES = {"bit": "u1", "unsigned_char": "u1", "char": "i1", "short": "i2", "unsigned_short": "u2",
              "int": "i4", "unsigned_int": "u4", "long": "i8", "unsigned_long": "u8", "float": "f4",
              "double": "f8", "vtktypeint64": "i8", "vtktypeuint64": "u8", "vtkidtype": "i4"}
_KEYWORD = re.compile(rb"\n[ \t]*[A-Za-z]")  # a line that starts a keyword (numbers never start with a letter)
# VTK cell types drawn as faces: triangle, polygon, quad (pixels and strips are left out)
_FACE_CELLS = (5, 7, 9)


def read_vtk_legacy(path):
    """A legacy VTK file (``# vtk DataFile Version 3.0`` to ``5.1``), ASCII or BINARY."""
    with open(path, "rb") as fh:
        data = fh.read()
    r = _LegacyVTK(path, data)
    return r.parse()


class _LegacyVTK:
    def __init__(self, path, data):
        self.path, self.data, self.pos = path, data, 0
        head = [self.line() for _ in range(3)]
        if not head[0].startswith(b"# vtk DataFile"):
            raise ValueError(f"{path}: not a legacy VTK file (no '# vtk DataFile' header)")
        self.binary = head[2].strip().upper() == b"BINARY"

    def line(self):
        end = self.data.find(b"\n", self.pos)
        end = len(self.data) if end < 0 else end
        s = self.data[self.pos:end].strip()
        self.pos = end + 1
        return s

    def truncated(self, got, count):
        return ValueError(f"{self.path}: the file ends after {got} of {count} values (truncated?)")

    def values(self, count, typ):
        dt = _VTK_TYPES.get(typ.lower())
        if dt is None:
            raise ValueError(f"{self.path}: unknown data type '{typ}'")
        if self.binary:
            size = np.dtype(dt).itemsize
            chunk = self.data[self.pos:self.pos + size * count]
            if len(chunk) < size * count:
                raise self.truncated(len(chunk) // size, count)
            self.pos += size * count
            return np.frombuffer(chunk, ">" + dt, count).astype(dt)
        m = _KEYWORD.search(self.data, self.pos)
        end = m.start() if m else len(self.data)
        tokens = self.data[self.pos:end].split()
        if len(tokens) < count:
            if m is None:
                raise self.truncated(len(tokens), count)
            word = self.data[m.start() + 1:].split()[0].decode("latin-1")
            raise ValueError(f"{self.path}: expected {count} values before '{word}', found {len(tokens)}")
        try:
            out = np.array(tokens[:count], dtype=np.float64 if dt[0] == "f" else np.int64)
        except ValueError:
            raise ValueError(f"{self.path}: a value that is not a number near byte {self.pos}") from None
        self.pos = end + 1 if len(tokens) == count else self._after(count)
        return out

    def _after(self, count):
        """Byte offset just after the ``count``-th token from pos (extra values on the line)."""
        it = re.finditer(rb"\S+", self.data[self.pos:])
        for k, t in enumerate(it):
            if k == count - 1:
                return self.pos + t.end()
        return len(self.data)

    def cells(self, parts):
        """A cell block, in the counted (<= 4.2) or OFFSETS/CONNECTIVITY (5.1) layout -> (offsets, conn)."""
        n, size = int(parts[1]), int(parts[2])
        save = self.pos
        nxt = self.line()
        if nxt.upper().startswith(b"OFFSETS"):
            offsets = self.values(n, nxt.split()[1].decode())
            hdr = self.line()
            while not hdr:
                hdr = self.line()
            if not hdr.upper().startswith(b"CONNECTIVITY"):
                raise ValueError(f"{self.path}: OFFSETS without CONNECTIVITY")
            conn = self.values(size, hdr.split()[1].decode())
            return np.asarray(offsets, np.int64), np.asarray(conn, np.int64)
        self.pos = save
        return _counted_cells(self.values(size, "int"))

    def parse(self):
        points = np.zeros((0, 3), np.float32)
        npts, ncell, faces, ctypes, arrays, where = 0, 0, None, None, {}, None
        while self.pos < len(self.data):
            line = self.line()
            if not line:
                continue
            parts = line.decode("latin-1").split()
            key = parts[0].upper()
            if key == "POINTS":
                npts = int(parts[1])
                points = self.values(3 * npts, parts[2]).reshape(-1, 3)
            elif key in ("POLYGONS", "CELLS"):
                faces = self.cells(parts)
            elif key in ("VERTICES", "LINES", "TRIANGLE_STRIPS"):
                self.cells(parts)
            elif key == "CELL_TYPES":
                ctypes = self.values(int(parts[1]), "int")
            elif key == "POINT_DATA":
                where = "point"
            elif key == "CELL_DATA":
                where, ncell = "cell", int(parts[1])
            elif key == "METADATA":
                while self.pos < len(self.data) and self.line():
                    pass
            elif key in ("SCALARS", "VECTORS", "NORMALS", "COLOR_SCALARS", "TENSORS"):
                name = parts[1]
                ncomp = {"VECTORS": 3, "NORMALS": 3, "TENSORS": 9}.get(
                    key, int(parts[3]) if len(parts) > 3 and key == "SCALARS" else 1)
                # colours are bytes in binary files, floats in 0..1 in ASCII ones
                typ = parts[2] if key != "COLOR_SCALARS" else ("unsigned_char" if self.binary else "float")
                if key == "COLOR_SCALARS":
                    ncomp = int(parts[2])
                if key == "SCALARS":
                    save = self.pos
                    if not self.line().upper().startswith(b"LOOKUP_TABLE"):
                        self.pos = save
                count = npts if where == "point" else ncell
                v = self.values(count * ncomp, typ)
                if where == "point":
                    arrays[name] = v.reshape(npts, ncomp) if ncomp > 1 else v
            elif key == "LOOKUP_TABLE" and len(parts) > 2:
                self.values(4 * int(parts[2]), "float" if not self.binary else "unsigned_char")
            elif key == "FIELD":
                for _ in range(int(parts[2])):
                    hdr = self.line()
                    while not hdr:
                        hdr = self.line()
                    name, ncomp, ntup, typ = hdr.decode("latin-1").split()[:4]
                    ncomp, ntup = int(ncomp), int(ntup)
                    v = self.values(ncomp * ntup, typ)
                    if where in (None, "point") and ntup == npts:
                        arrays[name] = v.reshape(ntup, ncomp) if ncomp > 1 else v
            elif key == "DATASET":
                if parts[1].upper() not in ("POLYDATA", "UNSTRUCTURED_GRID"):
                    raise ValueError(f"{self.path}: DATASET {parts[1]} is not supported "
                                     "(POLYDATA or UNSTRUCTURED_GRID)")
        loops = starts = None
        if faces is not None:
            keep = None
            if ctypes is not None and len(ctypes) == len(faces[0]) - 1:
                keep = np.isin(ctypes, _FACE_CELLS)
            loops, starts = _polygons(faces[0], faces[1], keep)
        return Geometry(points, loops, starts, arrays)


# ----------------------------------------------------------------------------- VTK XML
_XML_TYPES = {"Int8": "i1", "UInt8": "u1", "Int16": "i2", "UInt16": "u2", "Int32": "i4", "UInt32": "u4",
              "Int64": "i8", "UInt64": "u8", "Float32": "f4", "Float64": "f8"}


def read_vtk_xml(path):
    """A ``.vtu`` or ``.vtp`` file: points, polygons (Polys or polygon cells) and point data."""
    with open(path, "rb") as fh:
        data = fh.read()
    appended, enc = b"", "raw"
    a = data.find(b"<AppendedData")
    if a >= 0:
        tag = data[a:data.index(b">", a)]
        enc = "base64" if b'"base64"' in tag else "raw"
        start = data.index(b"_", a + len(tag)) + 1
        end = data.rfind(b"</AppendedData>")
        appended, data = data[start:end], data[:a] + data[end + len(b"</AppendedData>"):]
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        if b"</VTKFile>" not in data:
            raise ValueError(f"{path}: the file ends before </VTKFile> (truncated?)") from None
        raise ValueError(f"{path}: not a readable VTK XML file ({exc})") from None
    little = root.get("byte_order", "LittleEndian") == "LittleEndian"
    header = _XML_TYPES[root.get("header_type", "UInt32")]
    compressed = root.get("compressor") is not None
    piece = root.find(".//Piece")
    if piece is None:
        raise ValueError(f"{path}: no Piece element")
    end = "<" if little else ">"

    def array(el, name=None):
        dt = np.dtype(end + _XML_TYPES[el.get("type")])
        fmt = el.get("format", "ascii")
        ncomp = int(el.get("NumberOfComponents", "1"))
        if fmt == "ascii":
            v = np.array((el.text or "").split(), dtype=dt.newbyteorder("="))
        elif fmt == "binary":
            v = np.frombuffer(_inline(path, (el.text or "").strip().encode(), header, end, compressed), dt)
        else:
            v = np.frombuffer(_appended(path, appended, int(el.get("offset")), header, end, compressed, enc), dt)
        v = v.astype(dt.newbyteorder("="))
        return v.reshape(-1, ncomp) if ncomp > 1 else v

    pts = piece.find("Points/DataArray")
    points = array(pts) if pts is not None else np.zeros((0, 3))
    arrays = {}
    for el in piece.findall("PointData/DataArray"):
        arrays[el.get("Name")] = array(el)
    loops = starts = None

    def named(parent, n):
        for el in parent.findall("DataArray"):
            if el.get("Name") == n:
                return array(el)
        raise ValueError(f"{path}: {parent.tag} has no '{n}' array")

    polys, cells = piece.find("Polys"), piece.find("Cells")
    if polys is not None and int(piece.get("NumberOfPolys", "0")):
        offs = named(polys, "offsets")
        loops, starts = _polygons(np.concatenate([[0], offs]), named(polys, "connectivity"))
    elif cells is not None and int(piece.get("NumberOfCells", "0")):
        offs, types = named(cells, "offsets"), named(cells, "types")
        loops, starts = _polygons(np.concatenate([[0], offs]), named(cells, "connectivity"),
                                  np.isin(types, _FACE_CELLS))
    return Geometry(points, loops, starts, arrays)


def _inline(path, text, header, end, compressed):
    try:
        hsize = np.dtype(header).itemsize
        if not compressed:
            hl = _b64len(hsize)
            if text[hl - 1:hl] == b"=":  # VTK encodes the header on its own, meshio with the data
                n = int(np.frombuffer(base64.b64decode(text[:hl]), end + header, 1)[0])
                return base64.b64decode(text[hl:hl + _b64len(n)])[:n]
            buf = base64.b64decode(text)
            n = int(np.frombuffer(buf[:hsize], end + header, 1)[0])
            return buf[hsize:hsize + n]
        # the header is base64-encoded on its own, then the blocks
        first = base64.b64decode(text[:_b64len(hsize)])
        nb = int(np.frombuffer(first[:hsize], end + header, 1)[0])
        hl = _b64len(hsize * (3 + nb))
        h = np.frombuffer(base64.b64decode(text[:hl]), end + header, 3 + nb)
        body = base64.b64decode(text[hl:hl + _b64len(int(h[3:].sum()))])
        out, k = [], 0
        for c in h[3:]:
            out.append(zlib.decompress(body[k:k + int(c)]))
            k += int(c)
        return b"".join(out)
    except (ValueError, zlib.error) as exc:
        raise ValueError(f"{path}: a damaged binary array ({exc})") from None


def _b64len(n):
    return 4 * ((n + 2) // 3)


def _appended(path, blob, offset, header, end, compressed, enc):
    hsize = np.dtype(header).itemsize
    try:
        if enc == "base64":
            # each array: base64 of header, then base64 of the data (as VTK writes them)
            text = blob[offset:].strip()
            return _inline(path, text, header, end, compressed)
        pos = [offset]

        def take(n):
            b = blob[pos[0]:pos[0] + n]
            if len(b) < n:
                raise ValueError(f"{path}: the file ends inside its appended data (truncated?)")
            pos[0] += n
            return b

        if not compressed:
            n = int(np.frombuffer(take(hsize), end + header, 1)[0])
            return take(n)
        nb = int(np.frombuffer(blob[offset:offset + hsize], end + header, 1)[0])
        h = np.frombuffer(take(hsize * (3 + nb)), end + header, 3 + nb)
        return b"".join(zlib.decompress(take(int(c))) for c in h[3:])
    except zlib.error as exc:
        raise ValueError(f"{path}: damaged compressed data ({exc})") from None


# ----------------------------------------------------------------------------- PLY
def read_ply(path):
    """A PLY file (ascii or binary), parsed once for whitecap and the add-on: whitecap's
    ``io/ply.read_geometry`` (plyfile, which the extension carries as a wheel). Every scalar vertex
    property becomes an array; ``vx vy vz`` and ``nx ny nz`` become ``velocity`` and ``normals``."""
    pts, verts, loops, starts = _ply.read_geometry(path)
    if all(k in verts for k in ("vx", "vy", "vz")):
        verts["velocity"] = np.stack([verts.pop("vx"), verts.pop("vy"), verts.pop("vz")], axis=1)
    if all(k in verts for k in ("nx", "ny", "nz")):  # the file's normals: custom split normals
        verts["normals"] = np.stack([verts.pop("nx"), verts.pop("ny"), verts.pop("nz")], axis=1)
    return Geometry(pts, loops, starts, verts)


# ----------------------------------------------------------------------------- OBJ, STL
def read_obj(path):
    """Vertices and faces of a Wavefront OBJ (``v``/``f`` statements; other statements ignored)."""
    verts, loops, starts = [], [], []
    with open(path, "rb") as fh:
        lines = fh.read().split(b"\n")
    # OBJ declares no counts: a cut file shows as a last statement without its line end (every
    # writer ends its lines; a file cut inside a number could not be told from a whole one otherwise)
    cut = " (truncated?)" if lines and lines[-1].strip() else ""
    if cut and len(lines) > 1 and lines[-1].split()[0] in (b"v", b"vn", b"vt", b"f"):
        raise ValueError(f"{path}: line {len(lines)}: the last statement has no line end: the file is cut short "
                         "(truncated?)")
    for k, raw in enumerate(lines):
        if raw.startswith(b"v "):
            if len(raw.split()) < 4:
                raise ValueError(f"{path}: line {k + 1}: a 'v' statement without three numbers"
                                 f"{cut if k == len(lines) - 1 else ''}")
            verts.append(raw.split()[1:4])
        elif raw.startswith(b"f "):
            ids = [int(t.split(b"/")[0]) for t in raw.split()[1:]]
            if len(ids) < 3:
                raise ValueError(f"{path}: line {k + 1}: a face of {len(ids)} corners"
                                 f"{cut if k == len(lines) - 1 else ''}")
            starts.append(len(loops))
            loops += [i - 1 if i > 0 else len(verts) + i for i in ids]
    try:
        pts = np.array(verts, np.float64).reshape(-1, 3)
    except ValueError:
        raise ValueError(f"{path}: a 'v' statement without three numbers") from None
    if loops and (min(loops) < 0 or max(loops) >= len(pts)):
        raise ValueError(f"{path}: a face refers to a vertex that does not exist{cut}")
    return Geometry(pts, loops, starts)


def read_stl(path):
    """Triangles of a binary or ASCII STL, vertices shared where they coincide."""
    with open(path, "rb") as fh:
        data = fh.read()
    n = struct.unpack("<I", data[80:84])[0] if len(data) >= 84 else -1
    if n >= 0 and len(data) == 84 + 50 * n:
        rec = np.frombuffer(data, np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]), n, 84)
        tri = rec["v"].reshape(-1, 3)
    elif not data.lstrip().startswith(b"solid"):  # binary: 80 bytes, a count, 50 bytes a triangle
        if n >= 0 and len(data) < 84 + 50 * n:
            raise ValueError(f"{path}: the file ends after {(len(data) - 84) // 50} of {n} triangles (truncated?)")
        raise ValueError(f"{path}: not an STL file (binary size {len(data)} does not match {n} triangles)")
    else:
        if b"endsolid" not in data:
            raise ValueError(f"{path}: the file ends before 'endsolid' (truncated?)")
        tri = np.array(re.findall(rb"vertex\s+(\S+)\s+(\S+)\s+(\S+)", data), np.float64).reshape(-1, 3)
    pts, inv = np.unique(tri, axis=0, return_inverse=True)
    return Geometry(pts, inv.ravel(), np.arange(0, len(tri), 3))


# ----------------------------------------------------------------------------- BGEO
def read_bgeo(path):
    """partio's BGEO version 5 particles (SPlisHSPlasH ``.bgeo``), gzip-compressed or not: whitecap's
    one BGEO parse (``io/bgeo.read_points``), every attribute by its name in native byte order."""
    points, arrays = _bgeo.read_points(path, require_gzip=False)
    return Geometry(points, None, None, {k: v.astype(v.dtype.newbyteorder("=")) for k, v in arrays.items()})


def read_vtu(path):
    """A ``.vtu`` file, parsed once for whitecap and the add-on: whitecap's ``io/vtu.read_mesh``
    (meshio's VTU reader, checked for a cut file), faces and point data as :func:`read_meshio` takes them."""
    return _geometry(path, _vtu.read_mesh(path))


READERS = {".vtk": read_vtk_legacy, ".vtu": read_vtu, ".vtp": read_vtk_xml, ".ply": read_ply,
           ".obj": read_obj, ".stl": read_stl, ".bgeo": read_bgeo}
NORMAL_NAMES = ("normals", "normal", "n")  # point arrays read as the file's normals


def meshio_extensions():
    """The extensions meshio reads (none when the wheel is missing)."""
    try:
        import meshio
    except ImportError:
        return ()
    return tuple(sorted(e for e in meshio.extension_to_filetypes if e not in READERS))


# meshio cell types -> their boundary faces (corner indices): volume meshes show their surface
_BOUNDARY = {
    "tetra": ((0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)),
    "hexahedron": ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)),
    "wedge": ((0, 2, 1), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)),
    "pyramid": ((0, 3, 2, 1), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)),
}


def read_meshio(path):
    """Any format meshio reads: triangles, quads and polygons as faces, tetrahedra, hexahedra,
    wedges and pyramids as their boundary (faces that only one cell has), point data by name."""
    try:
        import meshio
    except ImportError:
        raise ValueError(f"{path}: this format needs meshio, which is not installed with the add-on") from None
    try:
        m = meshio.read(path)
    except Exception as exc:  # meshio raises many kinds; one line naming the file
        # meshio's readers do not say why a file fails; a cut file is the common cause
        raise ValueError(f"{path}: not readable by meshio, truncated or damaged? ({type(exc).__name__}: {exc})"
                         .replace("\n", " ")) from None
    return _geometry(path, m)


def _geometry(path, m):
    """A meshio ``Mesh`` as a :class:`Geometry`: triangles, quads and polygons as faces, volume
    cells as their boundary, point data by name."""
    faces = []
    for block in m.cells:
        data = np.asarray(block.data)
        if block.type in ("triangle", "quad") or block.type.startswith("polygon"):
            faces += [tuple(c) for c in data.tolist()]
        elif block.type in _BOUNDARY:
            seen = {}
            for cell in data.tolist():
                for f in _BOUNDARY[block.type]:
                    face = tuple(cell[i] for i in f)
                    key = tuple(sorted(face))
                    seen[key] = None if key in seen else face
            faces += [f for f in seen.values() if f is not None]
    pts = np.asarray(m.points, np.float64)
    if pts.shape[1] == 2:
        pts = np.c_[pts, np.zeros(len(pts))]
    loops = np.array([i for f in faces for i in f], np.int64)
    starts = np.cumsum([0] + [len(f) for f in faces[:-1]]) if faces else np.zeros(0)
    g = Geometry(pts, loops, starts, {k: np.asarray(v) for k, v in m.point_data.items()})
    return g


def read(path):
    """The geometry of one file, by its extension, checked (:meth:`Geometry.check`); the file's
    point normals, where it has them, as ``normals``."""
    ext = os.path.splitext(path)[1].lower()
    reader = READERS.get(ext)
    if reader is None and ext in meshio_extensions():
        reader = read_meshio
    if reader is None:
        raise ValueError(f"{path}: no reader for '{ext}' files (known: {', '.join(sorted(READERS))} and meshio's)")
    if not os.path.isfile(path):
        raise ValueError(f"{path}: file not found")
    try:
        g = reader(path)
    except ValueError:
        raise
    except WhitecapError as exc:  # whitecap's own parsers (io/bgeo, io/ply, io/vtu) say it in one line too
        raise ValueError(str(exc).replace("\n", " ")) from None
    except (IndexError, KeyError, AttributeError, TypeError, struct.error, UnicodeDecodeError, OverflowError,
            EOFError, zlib.error, OSError) as exc:
        raise ValueError(f"{path}: not a readable {ext[1:].upper()} file ({type(exc).__name__}: {exc})") from None
    g.check(path)
    low = {k.lower(): k for k in g.arrays}
    nk = next((low[n] for n in NORMAL_NAMES if n in low), None)
    if nk is not None and np.ndim(g.arrays[nk]) == 2 and np.shape(g.arrays[nk])[1] == 3:
        g.normals = np.asarray(g.arrays.pop(nk), np.float32)
    elif all(k in g.arrays for k in ("nx", "ny", "nz")):
        g.normals = np.stack([g.arrays.pop(k) for k in ("nx", "ny", "nz")], axis=1).astype(np.float32)
    return g
