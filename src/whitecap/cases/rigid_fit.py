"""Least-squares rigid motion of a body from its particles (Kabsch 1976, with Umeyama's reflection guard).

Given a body's particles in its rest placement ``P`` (body frame, the first
frame) and the same particles at a later frame ``Q`` (row ``i`` of both is
the same particle), the rotation ``R`` and translation ``t`` minimising
``Σ_i |R p_i + t − q_i|²`` are

    H = Σ (p_i − p̄)(q_i − q̄)ᵀ = U S Vᵀ,   d = sign det(V Uᵀ),
    R = V diag(1, 1, d) Uᵀ,               t = q̄ − R p̄

(W. Kabsch, Acta Cryst. A32 (1976) 922; S. Umeyama, IEEE PAMI 13 (1991) 376:
``d`` keeps ``R`` a proper rotation when noise would make the best orthogonal
fit a reflection). The result is a pose as ``run.json`` records it,
``{"position": t, "quaternion": q(R) (w, x, y, z)}``: world = T(t)·R·rest,
the form :func:`whitecap.geometry.obstacle_matrix` composes.
"""

from __future__ import annotations

import numpy as np

from ..geometry import apply_pose as _apply_pose, quaternion
from ..io.record import Pose


def kabsch(rest: np.ndarray, moved: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R (3, 3), t (3,)) minimising Σ |R rest_i + t − moved_i|² (row i of both is one particle)."""
    P = np.asarray(rest, np.float64).reshape(-1, 3)
    Q = np.asarray(moved, np.float64).reshape(-1, 3)
    if P.shape != Q.shape or len(P) < 3:
        raise ValueError(f"kabsch: need matching point sets of at least 3 points, got {P.shape} and {Q.shape}")
    p_bar, q_bar = P.mean(0), Q.mean(0)
    H = (P - p_bar).T @ (Q - q_bar)
    U, _, Vt = np.linalg.svd(H)
    d = 1.0 if np.linalg.det(Vt.T @ U.T) >= 0 else -1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, q_bar - R @ p_bar


def pose(R: np.ndarray, t: np.ndarray, previous: Pose | None = None) -> Pose:
    """A run.json pose from a rotation and translation. With ``previous``, the quaternion's sign
    is the one nearer the previous pose's, so that keys interpolated per component (Blender)
    take the short way between frames."""
    q = np.asarray(quaternion(R))  # w ≥ 0; the one conversion, shared with the rigid-body solver
    q = q / np.linalg.norm(q)
    if previous is not None and float(np.dot(q, previous.quaternion)) < 0:
        q = -q
    return Pose(position=[float(x) for x in t], quaternion=[float(x) for x in q])


def fit_pose(rest: np.ndarray, moved: np.ndarray, previous: Pose | None = None) -> Pose:
    """The pose carrying the body's rest particles onto ``moved``, by least squares."""
    R, t = kabsch(rest, moved)
    return pose(R, t, previous)


def fit_poses(rest: np.ndarray, frames: list[np.ndarray]) -> list[Pose]:
    """One pose per frame (each an array matching ``rest`` row for row), signs kept continuous."""
    out: list[Pose] = []
    for moved in frames:
        out.append(fit_pose(rest, moved, out[-1] if out else None))
    return out


def apply_pose(body: Pose, points: np.ndarray) -> np.ndarray:
    """Rest-placement points carried by a pose (``geometry.apply_pose``)."""
    return _apply_pose(body, points)
