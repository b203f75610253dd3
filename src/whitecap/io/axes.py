"""Up-axis conversion. whitecap is z-up everywhere; readers of y-up data call this."""

from __future__ import annotations

import numpy as np

from ..errors import InputError


def to_z_up(pos: np.ndarray, vel: np.ndarray | None, up: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Rotate y-up data to z-up (x, y, z) -> (x, -z, y), a proper rotation."""
    if up == "z":
        return pos, vel
    if up != "y":
        raise InputError(f"up axis must be 'y' or 'z', got {up!r}")

    def rot(a: np.ndarray | None) -> np.ndarray | None:
        if a is None:
            return None
        return np.stack([a[:, 0], -a[:, 2], a[:, 1]], axis=1).astype(np.float32)

    return rot(pos), rot(vel)  # type: ignore[return-value]
