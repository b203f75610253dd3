"""SPlisHSPlasH's rigid-body export (``enableRigidBodyExport``): ``rigid_bodies/rb_data_<k>.bin``.

The one reader of these files, for ``whitecap import`` (cases/splishsplash.py) and the Blender
add-on (which carries this module, rigid_fit and geometry in its ``whitecap`` folder).

Layout (all little-endian): the first file of a run starts with the body list, uint32 N, then
per body uint32 L, L bytes of mesh file name, 3 float32 scale, 1 byte isWall, 4 float32 colour;
every file then holds one pose per body, 3 float32 translation t and 9 float32 rotation R
stored column by column; world = R·(s ∘ v) + t for a model vertex v.

Imports only numpy, errors and rigid_fit (geometry), so that Blender can run it.
"""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.record import Pose
from .rigid_fit import pose

BIN_FILE = re.compile(r"^rb_data_(?P<k>\d+)\.bin$")
POSE_BYTES = 12 * 4  # 3 + 9 float32 per body and frame
ROTATION_TOL = 1e-3  # |RᵀR − I| above this: not a rotation (float32 poses are ~1e-7 off)


def bin_files(d: str | Path) -> dict[int, Path]:
    """{frame k: path} of the ``rb_data_<k>.bin`` files in a folder (empty when there is none)."""
    d = Path(d)
    if not d.is_dir():
        return {}
    return {int(m["k"]): p for p in d.iterdir() if (m := BIN_FILE.match(p.name))}


def read_bytes(path: Path) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None


def cut(held: int, declared: int) -> str:
    """The words that say a block is short because the file was cut."""
    return " (truncated)" if held < declared else ""


def read_bin_header(path: Path) -> tuple[list[tuple[str, np.ndarray, bool]], int]:
    """The body list of the first BIN file, [(mesh file name, scale (3,), isWall)], and the
    offset of its pose block."""
    buf = read_bytes(path)

    def take(fmt: str, at: int, field: str):
        size = struct.calcsize(fmt)
        if at + size > len(buf):
            raise InputError(f"{path}: {field}: truncated: the file ends at byte {len(buf)}, {at + size} needed")
        return struct.unpack_from(fmt, buf, at), at + size

    (n,), at = take("<I", 0, "number of bodies")
    if n == 0 or n * (4 + 1 + 12 + 1 + 16 + POSE_BYTES) > len(buf):
        raise InputError(f"{path}: number of bodies: {n} does not fit a file of {len(buf)} bytes (not an rb_data BIN?)")
    bodies = []
    for i in range(n):
        (length,), at = take("<I", at, f"body {i} mesh name length")
        if at + length > len(buf):
            raise InputError(f"{path}: body {i} mesh name: truncated: {length} bytes, past the end of the file")
        try:
            name = buf[at:at + length].decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(f"{path}: body {i} mesh name: not text (not an rb_data BIN?)") from None
        at += length
        if not name or "/" in name or "\\" in name:
            raise InputError(f"{path}: body {i} mesh name: {name!r} is not a file name")
        scale, at = take("<3f", at, f"body {i} scale")
        (wall,), at = take("<B", at, f"body {i} isWall")
        _, at = take("<4f", at, f"body {i} colour")
        if not all(math.isfinite(s) and s > 0 for s in scale):
            raise InputError(f"{path}: body {i} scale: {scale} is not positive")
        if wall > 1:
            raise InputError(f"{path}: body {i} isWall: byte {wall} is not 0 or 1 (not an rb_data BIN?)")
        bodies.append((name, np.asarray(scale, np.float64), bool(wall)))
    if len(buf) - at != n * POSE_BYTES:
        raise InputError(f"{path}: pose block: {len(buf) - at} bytes after the header, {n * POSE_BYTES} "
                         f"expected for {n} bodies{cut(len(buf) - at, n * POSE_BYTES)}")
    return bodies, at


def read_bin_poses(path: Path, offset: int, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per body (R, t) of one file's pose block at ``offset``."""
    buf = read_bytes(path)
    if len(buf) - offset != n * POSE_BYTES:
        raise InputError(f"{path}: pose block: {len(buf) - offset} bytes, {n * POSE_BYTES} expected "
                         f"for the {n} bodies of the first file{cut(len(buf) - offset, n * POSE_BYTES)}")
    a = np.frombuffer(buf, "<f4", n * 12, offset).astype(np.float64).reshape(n, 12)
    out = []
    for i in range(n):
        t, R = a[i, :3], a[i, 3:].reshape(3, 3).T  # column-major storage
        if not np.isfinite(a[i]).all():
            raise InputError(f"{path}: body {i} pose: not finite")
        if np.abs(R.T @ R - np.eye(3)).max() > ROTATION_TOL or np.linalg.det(R) < 0:
            raise InputError(f"{path}: body {i} rotation: not a rotation matrix")
        out.append((R, t))
    return out


def read_bin_run(bins: dict[int, Path], ks: list[int]):
    """The body list of the first file of ``ks`` and every body's (Rs, ts) over the frames ``ks``:
    (header, Rs[body][frame], ts[body][frame])."""
    first = ks[0]
    header, offset = read_bin_header(bins[first])
    n = len(header)
    Rs: list[list[np.ndarray]] = [[] for _ in range(n)]
    ts: list[list[np.ndarray]] = [[] for _ in range(n)]
    for k in ks:
        for i, (R, t) in enumerate(read_bin_poses(bins[k], offset if k == first else 0, n)):
            Rs[i].append(R)
            ts[i].append(t)
    return header, Rs, ts


def relative_poses(Rs: list[np.ndarray], ts: list[np.ndarray], M: np.ndarray) -> list[Pose]:
    """run.json poses from the first frame's placement, z up: world_k = R'·world_1 + t' with
    R' = M R_k R_1ᵀ Mᵀ and t' = M (t_k − R_k R_1ᵀ t_1); M takes the solver's axes to z up."""
    poses: list[Pose] = []
    R1, t1 = Rs[0], ts[0]
    for R, t in zip(Rs, ts):
        D = R @ R1.T
        poses.append(pose(M @ D @ M.T, M @ (t - D @ t1), poses[-1] if poses else None))
    return poses


def first_world(vertices: np.ndarray, scale: np.ndarray, R1: np.ndarray, t1: np.ndarray, M: np.ndarray) -> np.ndarray:
    """A body's model vertices at the first frame, z up: M (R_1 (s ∘ v) + t_1)."""
    return ((np.asarray(vertices, np.float64) * scale) @ R1.T + t1) @ M.T
