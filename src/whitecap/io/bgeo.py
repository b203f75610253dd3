"""Houdini BGEO particle files (``.bgeo``): the partio format that SPlisHSPlasH's
partio exporter writes (``partio/ParticleData_Fluid_N.bgeo``, gzip-compressed
BGEO version 5, y up by default: read them with ``up='y'``).

Layout (big-endian): ``BgeoV``, nine int32 (version 5, points, primitives,
point groups, primitive groups, point attributes, vertex attributes, primitive
attributes, attributes), one descriptor per point attribute (int16 name length,
name, int16 size, int32 type: 0 FLOAT, 1 INT, 5 VECTOR, then ``size`` default
values), then per point ``x y z w`` and every attribute's values as 4-byte words,
then any primitives and detail attributes (skipped), then the two end bytes
``00 ff``. Point attributes are matched by name as in the VTK readers:
``velocity``/``v``, ``density``, ``id``; the rest stay in ``arrays``.

A file cut short is refused with one line naming the file and saying
``truncated`` (the point count the header declares against the points the file
holds); so is a gzip stream that stops before its end.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from ..errors import InputError
from .axes import to_z_up
from .frame import ParticleFrame
from .registry import DENSITY_NAMES, ID_NAMES, VELOCITY_NAMES, find_array, register

GZIP_MAGIC = b"\x1f\x8b"
END = b"\x00\xff"
#: partio attribute types read here: FLOAT, INT, VECTOR (4, indexed strings, is not supported)
TYPES = {0: "FLOAT", 1: "INT", 5: "VECTOR"}


def _gunzip(path: Path, require_gzip: bool = True) -> tuple[bytes, bool]:
    """(the decompressed bytes, whether the gzip stream was complete); an uncompressed file as it
    is where ``require_gzip`` is off."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if raw[:2] != GZIP_MAGIC and not require_gzip:
        return raw, True
    if raw[:2] != GZIP_MAGIC:
        # SPlisHSPlasH (partio with compression on) writes the files gzip-compressed.
        raise InputError(f"{path}: not a gzip-compressed BGEO file (SPlisHSPlasH/partio write them compressed); "
                         f"compress it with gzip and keep the .bgeo name")
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        data = d.decompress(raw)
    except zlib.error as exc:
        raise InputError(f"{path}: not a readable BGEO V5 particle file (damaged gzip data: {exc})") from None
    return data, d.eof


def _fail(path: Path, what: str) -> InputError:
    return InputError(f"{path}: not a readable BGEO V5 particle file: {what}")


def _parse(path: Path, data: bytes, complete: bool) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(positions (N, 3), attributes by name) of a decompressed BGEO V5 file."""
    if data[:5] != b"BgeoV" and len(data) >= 5:
        raise _fail(path, "no BgeoV header (Houdini's newer JSON BGEO is not supported)")
    try:
        version, npts, nprim, _, _, nattr, _, _, ndetail = struct.unpack_from(">9i", data, 5)
        at = 41
        attrs = []
        for _ in range(nattr):
            (length,) = struct.unpack_from(">h", data, at)
            name = data[at + 2:at + 2 + length].decode("utf-8", "replace")
            size, typ = struct.unpack_from(">hi", data, at + 2 + length)
            at += 2 + length + 6 + 4 * size
            attrs.append((name, size, typ))
        if at > len(data):
            raise struct.error
    except struct.error:
        raise _fail(path, "truncated: the file ends inside its header") from None
    if version != 5:
        raise _fail(path, f"version {version}, only version 5 is read")
    for name, size, typ in attrs:
        if typ not in TYPES or size < 1:
            raise _fail(path, f"attribute '{name}': type {typ} of size {size} is not supported")
    width = 4 + sum(size for _, size, _ in attrs)  # x y z w and the attributes, 4 bytes each
    held = (len(data) - at) // (4 * width)
    if npts < 0 or held < npts:
        raise _fail(path, f"truncated: the point data declares {npts} points, the file holds {held}")
    end = at + 4 * width * npts
    if not complete:
        raise _fail(path, "truncated: the compressed stream stops before its end")
    # the end bytes follow the points, or the primitives and detail attributes (not read here) after them
    if len(data) < end + 2 or not (data[end:end + 2] == END if nprim == 0 and ndetail == 0 else data.endswith(END)):
        raise _fail(path, "truncated: the file ends before its two end bytes" if len(data) < end + 2 else
                    "the two end bytes 00 ff do not follow the point data")
    block = np.frombuffer(data, ">f4", width * npts, at).reshape(npts, width)
    arrays, col = {}, 4
    for name, size, typ in attrs:
        a = block[:, col:col + size]
        a = a.view(">i4") if typ == 1 else a
        arrays[name] = a[:, 0] if size == 1 else a
        col += size
    return block[:, :3], arrays


def read_points(path: str | Path, require_gzip: bool = True) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The one BGEO parse: (positions (N, 3) as stored, every point attribute by its name), big-endian
    views of the file. The Blender add-on reads ``.bgeo`` through this function too (a copy inside
    the extension; it needs numpy only), there with uncompressed files allowed (``require_gzip``
    off)."""
    path = Path(path)
    data, complete = _gunzip(path, require_gzip)
    return _parse(path, data, complete)


def read_bgeo(path: Path, up: str = "z", require_velocity: bool = True, by_id: bool = False) -> ParticleFrame:
    """One partio BGEO frame; ``by_id``: rows in increasing id order (the file must hold ids,
    see :meth:`ParticleFrame.sorted_by_id`)."""
    path = Path(path)
    points, arrays = read_points(path)
    vk, rk, ik = find_array(arrays, VELOCITY_NAMES), find_array(arrays, DENSITY_NAMES), find_array(arrays, ID_NAMES)
    if vk is None and require_velocity:
        raise InputError(f"{path}: missing attribute 'velocity'; found {sorted(arrays) or 'no attributes'} "
                         "(SPlisHSPlasH: add velocity to particleAttributes)")
    if by_id and ik is None:
        raise InputError(f"{path}: missing attribute 'id' (persistent particle ids) to order the particles by; "
                         f"found {sorted(arrays) or 'no attributes'} (SPlisHSPlasH: add id to particleAttributes)")
    # The file is big-endian; ParticleFrame converts to native float32/uint32.
    vel = arrays[vk].reshape(-1, 3) if vk else None
    pos, vel = to_z_up(points, vel, up)
    frame = ParticleFrame(
        positions=pos,
        velocities=vel,
        ids=arrays[ik] if ik else None,
        density=arrays[rk] if rk else None,
        arrays={k: v for k, v in arrays.items() if k not in (vk, rk, ik) and v.ndim == 1},
        source=str(path),
    )
    return frame.sorted_by_id() if by_id else frame


def check_bgeo(path: Path) -> None:
    """The cheap completeness check (:func:`whitecap.io.registry.check`): the size the header
    declares against the size the gzip trailer records (its last 4 bytes), decompressing only the
    header; a file where they differ is read in full for the exact error."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - 4))
            isize = int.from_bytes(f.read(4), "little")
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if head[:2] == GZIP_MAGIC and size >= 18:
        try:
            data = zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(head, 1 << 16)
            fields = struct.unpack_from(">9i", data, 5)
            npts, nattr = fields[1], fields[5]
            at, width = 41, 4
            for _ in range(nattr):
                (length,) = struct.unpack_from(">h", data, at)
                (n,) = struct.unpack_from(">h", data, at + 2 + length)
                at, width = at + 2 + length + 6 + 4 * n, width + n
            if at <= len(data) and (at + 4 * width * npts + len(END)) % (1 << 32) == isize \
                    and fields[2] == 0 and fields[8] == 0:  # with primitives, the size is not known from the header
                return
        except (zlib.error, struct.error):
            pass
    read_bgeo(path, require_velocity=False)  # raises the reason in one line (or the file is fine)


register("bgeo", (".bgeo",), read_bgeo, None, check=check_bgeo)
