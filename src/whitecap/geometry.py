"""Rotations and poses: the one place whitecap turns angles, axes and quaternions into matrices.

Conventions, shared by every stage:

- an obstacle's *rest placement* (``[[obstacle]] scale, rotate, translate``) is
  x_rest = T(translate) · Rz · Ry · Rx · S(scale) · x_mesh, the angles in degrees
  about x, then y, then z (:func:`obstacle_transform`);
- a *pose*, as ``run.json`` records one per frame and body, is a
  :class:`whitecap.io.record.Pose` (position [x, y, z], quaternion [w, x, y, z]), the rigid motion
  x_world = R(q) · x_rest + position (:func:`pose_matrix`);
- an obstacle in the world is the pose times the rest placement
  (:func:`obstacle_matrix`).

Quaternions are unit (w, x, y, z), w ≥ 0 where one is made from a matrix.
The 4×4 compositions go through trimesh's transformations module, as they
always have, so that placements stay bit for bit what earlier runs recorded.
"""

from __future__ import annotations

import math

import numpy as np

from .io.record import Pose


def axis_rotation(axis, angle: float) -> np.ndarray:
    """3×3 rotation by ``angle`` [rad] about ``axis`` (right-hand rule; Rodrigues), float64."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def euler_rotation(deg) -> np.ndarray:
    """Rotation about x, then y, then z [deg], as the obstacles' ``rotate`` (R = Rz·Ry·Rx)."""
    rx, ry, rz = (math.radians(v) for v in deg)
    return axis_rotation([0, 0, 1], rz) @ axis_rotation([0, 1, 0], ry) @ axis_rotation([1, 0, 0], rx)


def quaternion(R: np.ndarray) -> list[float]:
    """Unit quaternion (w, x, y, z) of a 3×3 rotation matrix, w ≥ 0."""
    import trimesh.transformations as tf

    M = np.eye(4)
    M[:3, :3] = R
    q = tf.quaternion_from_matrix(M)
    if q[0] < 0:
        q = -q
    return [float(v) for v in q]


def quat_matrix(q) -> np.ndarray:
    """3×3 rotation of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def unit_quat_matrix(q) -> np.ndarray:
    """3×3 rotation of a quaternion (w, x, y, z) of any length (normalised first; zero: identity)."""
    q = np.asarray(q, np.float64)
    return quat_matrix(q / (np.linalg.norm(q) or 1.0))


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a·b of quaternions (w, x, y, z)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def placement_matrix(scale, rotate, translate) -> np.ndarray:
    """4×4 T(translate)·Rz·Ry·Rx·S(scale), ``rotate`` in degrees about x, then y, then z."""
    import trimesh.transformations as T

    rx, ry, rz = (math.radians(a) for a in rotate)
    R = T.concatenate_matrices(T.rotation_matrix(rz, [0, 0, 1]), T.rotation_matrix(ry, [0, 1, 0]),
                               T.rotation_matrix(rx, [1, 0, 0]))
    return T.concatenate_matrices(T.translation_matrix(translate), R, T.scale_matrix(scale))


def obstacle_transform(o) -> np.ndarray:
    """The 4×4 rest placement of an obstacle mesh (:func:`placement_matrix` of its ``scale``,
    ``rotate``, ``translate``): a run's :class:`whitecap.io.record.Obstacle` or the scene's
    :class:`whitecap.config.Obstacle`."""
    return placement_matrix(o.scale, o.rotate, o.translate)


def pose_matrix(pose: Pose | None) -> np.ndarray:
    """The 4×4 rigid motion T(position)·R(quaternion) of a recorded pose; identity for None."""
    import trimesh.transformations as T

    if pose is None:
        return np.eye(4)
    return T.concatenate_matrices(T.translation_matrix(pose.position), T.quaternion_matrix(pose.quaternion))


def pose_record(R: np.ndarray, t) -> Pose:
    """A pose as ``run.json`` records it, from a rotation matrix and a translation."""
    return Pose(position=[float(v) for v in t], quaternion=quaternion(R))


def apply_pose(pose: Pose | None, points: np.ndarray) -> np.ndarray:
    """Rest-placement points carried by a pose, float64."""
    M = pose_matrix(pose)
    return np.asarray(points, np.float64) @ M[:3, :3].T + M[:3, 3]


def obstacle_matrix(o, pose: Pose | None = None) -> np.ndarray:
    """The 4×4 world matrix of an obstacle mesh: its rest placement (:func:`obstacle_transform`)
    carried by the pose ``pose`` (None: at rest). World = T(position)·R(quaternion)·placement."""
    M = obstacle_transform(o)
    if pose is None:
        return M
    return pose_matrix(pose) @ M
