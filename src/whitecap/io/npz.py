"""NumPy .npz particle frames: arrays ``positions`` (N,3), optional ``velocities``,
``ids``, ``density``, ``time`` and any other per-particle arrays.

A file cut short (its zip directory, at the end, is gone) is refused with one
line naming the file, ``truncated`` and the array the file stops inside; a
damaged array is named too.
"""

from __future__ import annotations

import struct
import zipfile
from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import write_arrays
from .axes import to_z_up
from .frame import ParticleFrame
from .registry import register

_LOCAL = b"PK\x03\x04"  # a zip member's local header
_LOCAL_HEADER = struct.Struct("<4sHHHHHIIIHH")  # signature ... compressed size, size, name and extra lengths
_ZIP64 = 0x0001  # the extra field holding 64-bit sizes


def _where_cut(raw: bytes) -> str:
    """Where a zip that lost its end stops: inside which array, or after every array (in its directory)."""
    at = 0
    while raw[at:at + 4] == _LOCAL:
        if at + _LOCAL_HEADER.size > len(raw):
            return "the file ends inside the header of an array"
        _, _, flags, _, _, _, _, csize, _, nlen, xlen = _LOCAL_HEADER.unpack_from(raw, at)
        start = at + 30 + nlen + xlen
        if at + 30 + nlen > len(raw):
            return "the file ends inside the header of an array"
        name = raw[at + 30:at + 30 + nlen].decode("utf-8", "replace").removesuffix(".npy")
        if start > len(raw):
            return f"the file ends inside the header of array '{name}'"
        extra, k = raw[at + 30 + nlen:start], 0
        while k + 4 <= len(extra):
            tag, size = struct.unpack_from("<HH", extra, k)
            if tag == _ZIP64 and csize == 0xFFFFFFFF and size >= 16 and k + 20 <= len(extra):
                csize = struct.unpack_from("<Q", extra, k + 12)[0]  # after the 8-byte size
            k += 4 + size
        if flags & 8:  # sizes in a descriptor after the data: the member cannot be skipped
            return f"the file ends inside or after array '{name}'"
        if start + csize > len(raw):
            return f"array '{name}' declares {csize} bytes, the file holds {len(raw) - start}"
        at = start + csize
    return "every array is complete but the zip directory at the end of the file is missing or cut"


def read_npz(path: Path, up: str = "z", require_velocity: bool = False) -> ParticleFrame:
    try:
        z = np.load(path)
    except zipfile.BadZipFile as exc:
        with open(path, "rb") as f:
            raw = f.read()
        if raw.startswith(_LOCAL):
            raise InputError(f"{path}: truncated: {_where_cut(raw)}") from None
        raise InputError(f"{path}: not a readable .npz file ({exc})") from None
    except Exception as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise InputError(f"{path}: not a readable .npz file (one array, not an archive of named arrays)")
    with z:
        keys = set(z.files)

        def get(k: str) -> np.ndarray:
            try:
                return z[k]
            except Exception as exc:  # a bad CRC, damaged compressed data, an .npy header that lies
                raise InputError(f"{path}: array '{k}': damaged ({exc})") from None

        pos_key = next((k for k in ("positions", "x", "pos") if k in keys), None)
        if pos_key is None:
            raise InputError(f"{path}: missing array 'positions'")
        vel_key = next((k for k in ("velocities", "v", "vel") if k in keys), None)
        if vel_key is None and require_velocity:
            raise InputError(f"{path}: missing array 'velocities'")
        pos, vel = to_z_up(get(pos_key), get(vel_key) if vel_key else None, up)
        used = {pos_key, vel_key, "ids", "density", "time"}
        return ParticleFrame(
            positions=pos,
            velocities=vel,
            ids=get("ids") if "ids" in keys else None,
            density=get("density") if "density" in keys else None,
            time=float(get("time")) if "time" in keys else None,
            arrays={k: get(k) for k in keys - used},
            source=str(path),
        )


def write_npz(path: Path, frame: ParticleFrame) -> None:
    arrays: dict[str, np.ndarray | np.float64] = dict(positions=frame.positions, ids=frame.ids, **frame.arrays)
    if frame.velocities is not None:
        arrays["velocities"] = frame.velocities
    if frame.density is not None:
        arrays["density"] = frame.density
    if frame.time is not None:
        arrays["time"] = np.float64(frame.time)
    write_arrays(path, arrays)  # closes its zip on a failed write (np.savez left it to __del__)


def check_npz(path: Path) -> None:
    """The cheap completeness check (:func:`whitecap.io.registry.check`): the zip directory's end
    record within the file's last bytes; a file without one is read for the exact error."""
    with open(path, "rb") as f:
        f.seek(0, 2)
        size = f.tell()
        f.seek(max(0, size - (1 << 16) - 22))  # the end record, then a comment of at most 64 KiB
        tail = f.read()
    k = tail.rfind(b"PK\x05\x06")
    if k >= 0 and k + 22 <= len(tail) and k + 22 + int.from_bytes(tail[k + 20:k + 22], "little") == len(tail):
        return
    read_npz(Path(path))


register("npz", (".npz",), read_npz, write_npz, check=check_npz)
