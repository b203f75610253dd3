"""Colours: the fluid colour map and the diffuse-type palette."""

from __future__ import annotations

import numpy as np

# A perceptually ordered blue -> teal -> yellow map, sampled at five stops
# (close to matplotlib's "viridis"; hand-written to avoid a matplotlib dependency).
COLORMAP_STOPS = np.array(
    [[0.267, 0.005, 0.329], [0.229, 0.322, 0.546], [0.128, 0.567, 0.551], [0.369, 0.789, 0.383], [0.993, 0.906, 0.144]],
    np.float32,
)

# Diffuse particle colours by type code (io.diffuse_types: 0 spray, 1 foam, 2 bubble), RGB in [0, 1].
DIFFUSE_COLORS = np.array([[1.0, 1.0, 1.0], [0.78, 0.78, 0.78], [0.62, 0.80, 1.0]], np.float32)


def colormap(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Map scalars to RGB (N, 3) float32 over [lo, hi] (clamped)."""
    t = np.clip((np.asarray(values, np.float32) - lo) / max(hi - lo, 1e-12), 0.0, 1.0) * (len(COLORMAP_STOPS) - 1)
    i = np.minimum(t.astype(np.int32), len(COLORMAP_STOPS) - 2)
    w = (t - i)[:, None]
    return ((1 - w) * COLORMAP_STOPS[i] + w * COLORMAP_STOPS[i + 1]).astype(np.float32)


def fluid_scalar(positions_velocities_density: dict, mode: str) -> np.ndarray:
    """The per-particle value the fluid is coloured by: speed [m/s] or density [kg/m³]."""
    d = positions_velocities_density
    n = len(d["positions"])
    if mode == "density" and d.get("density") is not None:
        return np.asarray(d["density"], np.float32)
    v = d.get("velocities")
    return np.linalg.norm(v, axis=1).astype(np.float32) if v is not None else np.zeros(n, np.float32)


GRAVITY = 9.81  # |g| for the default speed range [m/s²]


def free_fall_speed(bounds) -> float:
    """v = sqrt(2 |g| H) over the box height H: the speed scale of a dam break [m/s]."""
    height = float(np.asarray(bounds.upper)[2] - np.asarray(bounds.lower)[2])
    return float(np.sqrt(2.0 * GRAVITY * max(height, 0.0)))


def fitted_range(values: np.ndarray, mode: str, speed_scale: float) -> tuple[float, float]:
    """The colour range fitted to a frame: density from its 2nd to 98th percentile;
    speed from 0 to the larger of ``speed_scale`` (:func:`free_fall_speed`, so that a
    resting first frame does not fix a range of zero) and the 99th percentile."""
    s = np.asarray(values)
    if mode == "density":
        lo, hi = (float(np.percentile(s, 2)), float(np.percentile(s, 98))) if len(s) else (0.0, 1.0)
    else:
        lo, hi = 0.0, max(speed_scale, float(np.percentile(s, 99)) if len(s) else 0.0)
    return lo, (hi if hi > lo else lo + 1.0)
