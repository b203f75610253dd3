"""whitecap.geometry: the one definition of rotations, placements and poses."""

import numpy as np
import pytest

from whitecap import geometry as G
from whitecap.io.record import Obstacle


def test_euler_rotation_is_the_placement_rotation():
    """The solver's Euler rotation (Rodrigues) and the placement matrix (trimesh) are one convention:
    about x, then y, then z."""
    ang = (30.0, -45.0, 120.0)
    M = G.placement_matrix(1.0, ang, (0.0, 0.0, 0.0))
    np.testing.assert_allclose(M[:3, :3], G.euler_rotation(ang), atol=1e-12)
    # x first: a quarter turn about x then about z sends y to z, then z stays z.
    R = G.euler_rotation((90.0, 0.0, 90.0))
    np.testing.assert_allclose(R @ [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


def test_quaternion_round_trip_and_sign():
    rng = np.random.default_rng(1)
    for _ in range(20):
        axis, angle = rng.normal(size=3), rng.uniform(-3.0, 3.0)
        R = G.axis_rotation(axis, angle)
        q = G.quaternion(R)
        assert q[0] >= 0.0 and np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(G.quat_matrix(q), R, atol=1e-12)
        np.testing.assert_allclose(G.unit_quat_matrix(3.0 * np.asarray(q)), R, atol=1e-12)
    # the Hamilton product composes rotations: R(a·b) = R(a) R(b)
    a, b = G.quaternion(G.axis_rotation([1, 2, 3], 0.7)), G.quaternion(G.axis_rotation([0, 1, 0], -1.1))
    np.testing.assert_allclose(G.quat_matrix(G.quat_mul(np.array(a), np.array(b))),
                               G.quat_matrix(a) @ G.quat_matrix(b), atol=1e-12)


def test_obstacle_matrix_is_pose_times_placement():
    o = Obstacle(mesh="x.obj", scale=2.0, rotate=[0.0, 0.0, 90.0], translate=[1.0, 0.0, 0.0])
    # rest: scale, rotate a quarter turn about z, translate
    np.testing.assert_allclose(G.obstacle_matrix(o) @ [1.0, 0.0, 0.0, 1.0], [1.0, 2.0, 0.0, 1.0], atol=1e-12)
    pose = G.pose_record(G.axis_rotation([0, 0, 1], np.pi), [0.0, 0.0, 0.5])
    assert G.pose_matrix(None) == pytest.approx(np.eye(4))
    M = G.obstacle_matrix(o, pose)
    np.testing.assert_allclose(M @ [1.0, 0.0, 0.0, 1.0], [-1.0, -2.0, 0.5, 1.0], atol=1e-12)
    np.testing.assert_allclose(M, G.pose_matrix(pose) @ G.obstacle_transform(o), atol=0)
    np.testing.assert_allclose(G.apply_pose(pose, [[1.0, 2.0, 0.0]]), [[-1.0, -2.0, 0.5]], atol=1e-12)
    # missing keys take the record's defaults: identity placement
    np.testing.assert_array_equal(G.obstacle_transform(Obstacle.model_validate({"mesh": "x.obj"})), np.eye(4))
