"""NumPy .npz particle frames: arrays ``positions`` (N,3), optional ``velocities``,
``ids``, ``density``, ``time`` and any other per-particle arrays."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import atomic_path
from .axes import to_z_up
from .frame import ParticleFrame
from .registry import register


def read_npz(path: Path, up: str = "z", require_velocity: bool = False) -> ParticleFrame:
    try:
        z = np.load(path)
    except Exception as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from None
    keys = set(z.files)
    pos_key = next((k for k in ("positions", "x", "pos") if k in keys), None)
    if pos_key is None:
        raise InputError(f"{path}: missing array 'positions'")
    vel_key = next((k for k in ("velocities", "v", "vel") if k in keys), None)
    if vel_key is None and require_velocity:
        raise InputError(f"{path}: missing array 'velocities'")
    pos, vel = to_z_up(z[pos_key], z[vel_key] if vel_key else None, up)
    used = {pos_key, vel_key, "ids", "density", "time"}
    return ParticleFrame(
        positions=pos,
        velocities=vel,
        ids=z["ids"] if "ids" in keys else None,
        density=z["density"] if "density" in keys else None,
        time=float(z["time"]) if "time" in keys else None,
        arrays={k: z[k] for k in keys - used},
        source=str(path),
    )


def write_npz(path: Path, frame: ParticleFrame) -> None:
    arrays = dict(positions=frame.positions, ids=frame.ids, **frame.arrays)
    if frame.velocities is not None:
        arrays["velocities"] = frame.velocities
    if frame.density is not None:
        arrays["density"] = frame.density
    if frame.time is not None:
        arrays["time"] = np.float64(frame.time)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


register("npz", (".npz",), read_npz, write_npz)
