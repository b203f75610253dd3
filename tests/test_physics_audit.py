"""Physics checks that catch realistic one-line bugs the other tests let through
(scripts/mutation_audit.py): a rigid body spun about a non-principal axis, the torque
the fluid puts on a body hit off its centre, keyframes that do not start at t = 0, the
density of the layer resting on an obstacle and on an upper wall."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from whitecap import geometry
from whitecap.config import scene_from_dict
from whitecap.sim import bodies
from whitecap.sim.driver import build_solver


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("WHITECAP_CACHE", str(tmp_path / "cache"))


# ---------------------------------------------------------------- a free rigid body
def free_box(extents=(0.3, 0.2, 0.1)) -> bodies.RigidBody:
    """A box of three different principal moments, alone in zero gravity, far from every wall."""
    sc = scene_from_dict({"domain": {"upper": [4.0, 4.0, 4.0], "gravity": [0.0, 0.0, 0.0]},
                          "obstacle": [{"mesh": "box.stl", "dynamic": True, "density": 500.0}]})
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation([2.0, 2.0, 2.0])
    return bodies.RigidBody(mesh, sc.obstacle[0], sc.domain.gravity, sc.domain.lower, sc.domain.upper)


def world_inertia(b) -> np.ndarray:
    R = geometry.quat_matrix(b.q)
    return R @ b.I0 @ R.T


def test_a_body_spun_about_a_non_principal_axis_keeps_its_angular_momentum_and_energy():
    """Torque free, a box spun about an axis that is none of its principal axes tumbles: its
    angular velocity Ω wanders in the world frame while the angular momentum L = R I₀ Rᵀ Ω stays
    fixed, as does the kinetic energy ½ Ω·L (Euler's equations). Over 1 s (1000 steps, the box
    turns about 170°) both hold within 1 %. (Measured: 0.13 %. With the inertia tensor left in
    the body frame L drifts 100 %; with Ω applied in the body frame (q ⊗ Ω instead of Ω ⊗ q) 21 %;
    with the gyroscopic term's sign flipped 130 %.)"""
    b = free_box()
    assert len(set(np.round(np.diag(b.I0), 6))) == 3 and np.allclose(b.I0, np.diag(np.diag(b.I0)))
    b.W = np.array([3.0, 0.4, 2.0])  # far from the principal axes (x, y, z of the box)
    L0 = world_inertia(b) @ b.W
    E0 = 0.5 * b.W @ L0
    W0 = b.W.copy()
    worst_L = worst_E = wander = 0.0
    for _ in range(1000):
        b.advance(1e-3)
        L = world_inertia(b) @ b.W
        worst_L = max(worst_L, np.linalg.norm(L - L0) / np.linalg.norm(L0))
        worst_E = max(worst_E, abs(0.5 * b.W @ L / E0 - 1.0))
        wander = max(wander, np.linalg.norm(b.W - W0) / np.linalg.norm(W0))
    R = geometry.quat_matrix(b.q)
    turned = math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    # controls: the body really turned far, and Ω really moved (a spin about a principal axis keeps Ω
    # and would pass whatever the inertia tensor's frame)
    assert turned > 90.0 and wander > 0.3, (turned, wander)
    assert worst_L < 0.01, f"angular momentum drifted {worst_L:.1%}"
    assert worst_E < 0.01, f"kinetic energy drifted {worst_E:.1%}"
    assert np.allclose(b.c, [2.0, 2.0, 2.0]) and np.allclose(b.V, 0.0)  # no force: the centre stays


def test_a_body_pushed_through_water_off_its_centre_conserves_angular_momentum(tmp_path):
    """No gravity, no wall touched: a cube moving at 0.5 m/s runs into a block of water that covers
    only the +y half of its leading face. The water pushes back on that half, so the cube turns
    (+z), and the angular momentum about the origin of cube + water (+ the reaction not yet
    applied) stays within 1 % of the initial one over 0.125 s. (Measured: 0.07 %; with the fluid's
    moment moved to the centre of mass with the wrong sign, 30 % and the cube spins wildly.)"""
    path = tmp_path / "cube.stl"
    trimesh.creation.box(extents=[0.08, 0.08, 0.08]).export(str(path))
    sc = scene_from_dict({
        "domain": {"upper": [0.8, 0.4, 0.4], "gravity": [0.0, 0.0, 0.0]},
        "solver": {"particle_radius": 0.01, "xsph_c": 0.0, "vorticity_epsilon": 0.0},
        "fluid": [{"lower": [0.32, 0.2, 0.08], "upper": [0.5, 0.32, 0.32]}],
        "obstacle": [{"mesh": str(path), "translate": [0.25, 0.2, 0.2], "dynamic": True, "density": 1000.0}],
        "foam": {"enabled": False},
    })
    s = build_solver(sc)
    body = s.colliders[0].bodies[0]
    body.V = np.array([0.5, 0.0, 0.0])

    def body_L():
        return np.cross(body.c, body.mass * body.V) + world_inertia(body) @ body.W

    L0 = body_L()
    dt = 1 / 480
    worst = 0.0
    for _ in range(60):
        s.step(dt)
        x, v = s.state.x.to_numpy().astype(np.float64), s.state.v.to_numpy().astype(np.float64)
        fluid_L = s.mass * np.cross(x, v).sum(0)
        pending = np.cross(body.c, body.F * dt) + body.tau * dt  # the reaction applied at the next step
        worst = max(worst, np.linalg.norm(body_L() + fluid_L + pending - L0) / np.linalg.norm(L0))
    assert body.W[2] > 0.3, body.W  # control: the off-centre push turned the cube, the right way
    assert np.linalg.norm(fluid_L) > 0.1 * np.linalg.norm(L0)  # and the water took its share
    assert worst < 0.01, f"angular momentum changed by {worst:.1%}"


def test_friction_acts_along_the_surface_of_a_turned_body(tmp_path):
    """test_bodies' sliding plate, but one whose mesh stands upright and which its motion turns 90°
    about y to lie flat: the contact response must use the normal turned with the body. Water on it
    with full friction rides along at the plate's 0.3 m/s. (Measured: 0.30 m/s; with the rest-frame
    normal, which is horizontal here, 0.07 m/s.)"""
    path = tmp_path / "plate.stl"
    trimesh.creation.box(extents=[0.04, 0.14, 0.3]).export(str(path))  # upright: thin in x
    turned = [0.0, 90.0, 0.0]
    sc = scene_from_dict({
        "domain": {"upper": [0.8, 0.1, 0.4]},
        "solver": {"particle_radius": 0.01},
        "fluid": [{"lower": [0.08, 0.0, 0.05], "upper": [0.22, 0.1, 0.11]}],
        "obstacle": [{"mesh": str(path), "translate": [0.15, 0.05, 0.2], "friction": 1.0,
                      "motion": {"kind": "keyframes", "keyframes": [
                          {"time": 0.0, "translate": [0.0, 0.0, -0.18], "rotate": turned},
                          {"time": 2.0, "translate": [0.6, 0.0, -0.18], "rotate": turned}]}}],
        "foam": {"enabled": False},
    })
    s = build_solver(sc)
    R, T = bodies.MotionLaw(sc.obstacle[0]).pose(0.0)
    assert np.allclose(R @ [1.0, 0.0, 0.0], [0.0, 0.0, -1.0])  # the plate's thin side is now vertical
    for _ in range(96):  # 0.4 s
        s.step(1 / 240)
    x, v = s.state.x.to_numpy(), s.state.v.to_numpy()
    on_plate = x[:, 2] < 0.04 + 0.03
    assert on_plate.sum() > 20
    assert np.median(v[on_plate, 0]) == pytest.approx(0.3, rel=0.1)
    assert v[on_plate, 2].max() < 0.3


def test_foam_the_water_carries_into_a_body_is_put_back_on_its_surface(tmp_path):
    """Foam more than BODY_CONTACT r behind a moving, turning box (so not riding on it) that a fast
    current (1.5 m/s) carries into the box within a frame ends the frame outside it, a radius off
    the face it came through, moving with the body: never inside. (test_bodies checks spray and
    bubbles the same way; foam goes its own way in the generator.)"""
    from whitecap.diffuse.generator import BODY_CONTACT
    from whitecap.io.diffuse_types import FOAM

    from .test_bodies import moving_box

    g, gen, law_ = moving_box(tmp_path)
    dt = 1 / 30
    for i in range(1, 4):
        g.at_frame(i * dt, None, dt)
    R, T = law_.pose(3 * dt)
    back = np.array([[-0.05 - 0.035, 0.0, 0.0], [-0.05 - 0.032, 0.02, -0.01], [-0.05 - 0.034, -0.03, 0.02]])
    x0 = (back @ R.T + (R @ [0.3, 0.2, 0.2] + T)).astype(np.float32)  # 3.2-3.5 cm behind its −x face
    assert (g.sample(x0, before=True) > BODY_CONTACT * 0.01).all()
    v = np.tile((R @ [1.5, 0.0, 0.0]).astype(np.float32), (3, 1))
    moved = x0 + v * dt  # 5 cm along: inside the box
    assert (g.sample(moved) < -0.005).all()
    x, v_new, alive = gen._obstacles(x0, moved, v, np.full(3, FOAM, np.uint8))
    assert alive.all()
    d = g.sample(x)
    assert (d > 0).all(), d  # outside
    assert np.allclose(d, 0.01, atol=0.002), d  # one radius (SURFACE_OFFSET r) off the face
    assert np.allclose(v_new, g.velocity(x), atol=1e-4)  # moving with the body, not into it


# ---------------------------------------------------------------- keyframes
def keyframe_law(keys, **motion):
    sc = scene_from_dict({"obstacle": [{"mesh": "m.stl", "translate": [0.2, 0.1, 0.0],
                                        "motion": {"kind": "keyframes", "keyframes": keys, **motion}}]})
    return bodies.MotionLaw(sc.obstacle[0], sc.base_dir)


def test_keyframes_that_start_late_interpolate_within_each_segment():
    """Keys at 1.5 s, 2.5 s and 4 s (none at 0): held before the first, linear in each segment
    by the time since that segment's start, rotations about x, then y, then z about the
    obstacle's own position."""
    keys = [{"time": 1.5}, {"time": 2.5, "translate": [1.0, 0.0, 0.0]},
            {"time": 4.0, "translate": [1.0, 0.6, 0.0], "rotate": [90.0, 0.0, 90.0]}]
    law_ = keyframe_law(keys)
    c = np.array([0.2, 0.1, 0.0])  # the motion centre: the obstacle's translate

    def centre_at(t):
        R, T = law_.pose(t)
        return R @ c + T

    for t, want in ((0.0, [0.2, 0.1, 0.0]), (1.5, [0.2, 0.1, 0.0]), (1.75, [0.45, 0.1, 0.0]),
                    (2.0, [0.7, 0.1, 0.0]), (2.5, [1.2, 0.1, 0.0]), (3.25, [1.2, 0.4, 0.0]), (9.0, [1.2, 0.7, 0.0])):
        assert centre_at(t) == pytest.approx(want, abs=1e-12), t
    R, _ = law_.pose(3.25)  # half way: 45° about x, then 45° about z
    s = math.sqrt(0.5)
    Rx = np.array([[1, 0, 0], [0, s, -s], [0, s, s]])
    Rz = np.array([[s, -s, 0], [s, s, 0], [0, 0, 1]])
    assert np.allclose(R, Rz @ Rx, atol=1e-12)
    R, _ = law_.pose(4.0)  # x then z, 90° each: x̂ → ŷ, ŷ → ẑ, ẑ → x̂
    assert np.allclose(R @ np.eye(3), [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-12)
    # smooth: smoothstep of the segment's own fraction, 0.15625 at a quarter
    sm = keyframe_law(keys, interpolation="smooth")
    R, T = sm.pose(1.75)
    assert (R @ c + T)[0] == pytest.approx(0.2 + 0.15625, abs=1e-12)


# ---------------------------------------------------------------- density next to boundaries
def layer_densities(s, rest_density: float, distance, frames=45, average_from=30, layers=5, r=0.01) -> np.ndarray:
    """Mean density / ρ0 of the particle layers (2r thick) at increasing ``distance`` from a boundary,
    averaged over the frames after ``average_from`` (the water has settled by 1 s)."""
    rows = []
    for f in range(1, frames + 1):
        s.advance_frame(f)
        if f > average_from:
            a = s.arrays()
            d, rho = distance(a["positions"]), a["density"] / rest_density
            rows.append([rho[(d >= 2 * k * r) & (d < 2 * (k + 1) * r)].mean() for k in range(layers)])
    return np.mean(rows, axis=0)


def test_water_resting_on_an_obstacle_has_the_density_of_the_water_above_it(tmp_path):
    """The obstacle analogue of test_solver's wall-layer test: a 30 cm column rests on a static slab
    obstacle that fills the bottom 6 cm of the tank. The obstacle's density share ψ and its gradient
    ∇ψ stand in for the fluid missing below its surface, so the layer resting on it is at the density
    of the layers above within 1.5 ‰, as at the walls. (Measured: 0.8 ‰. Without the obstacle's ∇ψ,
    3.7 ‰; with its ψ replacing the walls' share instead of adding to it, 3.6 ‰.)"""
    r, top = 0.01, 0.06
    path = tmp_path / "slab.stl"
    trimesh.creation.box(extents=[0.12, 0.12, top]).export(str(path))
    sc = scene_from_dict({
        "domain": {"upper": [0.12, 0.12, 0.5]},
        "solver": {"particle_radius": r, "iterations": 8},
        "fluid": [{"lower": [0.0, 0.0, top], "upper": [0.12, 0.12, top + 0.3]}],
        "obstacle": [{"mesh": str(path), "translate": [0.06, 0.06, top / 2]}],
        "foam": {"enabled": False},
    })
    s = build_solver(sc)
    m = layer_densities(s, sc.solver.rest_density, lambda x: x[:, 2] - top)
    assert s.state.x.to_numpy()[:, 2].min() > top + 0.99 * r  # resting on the slab, a radius above it
    assert abs(m[1:].mean() - 1) < 0.005, m  # the water above is near rest density
    excess = m[0] - m[1:].mean()
    assert abs(excess) < 1.5e-3, f"layer on the obstacle {m[0]:.4f} vs {m[1:].mean():.4f} above it"


def test_water_pressed_against_an_upper_wall_has_the_density_of_the_water_behind_it():
    """Gravity along +x presses the water against the upper x wall: the layer touching it is at the
    density of the layers behind within 1.5 ‰, as on the floor (the upper walls' ∇ψ points back
    into the fluid, −x̂). (Measured: 0.6 ‰; with the upper walls' gradient sign flipped, 18 ‰.)"""
    r = 0.01
    sc = scene_from_dict({
        "domain": {"upper": [0.4, 0.12, 0.12], "gravity": [9.81, 0.0, 0.0]},
        "solver": {"particle_radius": r, "iterations": 8},
        "fluid": [{"lower": [0.1, 0.0, 0.0], "upper": [0.4, 0.12, 0.12]}],
        "foam": {"enabled": False},
    })
    s = build_solver(sc)
    m = layer_densities(s, sc.solver.rest_density, lambda x: 0.4 - x[:, 0])
    assert s.state.x.to_numpy()[:, 0].max() > 0.4 - 1.01 * r  # the water is against the wall
    assert abs(m[1:].mean() - 1) < 0.005, m
    excess = m[0] - m[1:].mean()
    assert abs(excess) < 1.5e-3, f"layer at the wall {m[0]:.4f} vs {m[1:].mean():.4f} behind it"
