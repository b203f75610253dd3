"""Moving bodies: motion laws, a kinematic paddle that never leaks, resume, run.json poses."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh

from whitecap import geometry
from whitecap.config import scene_from_dict
from whitecap.errors import InputError
from whitecap.geometry import obstacle_matrix, pose_matrix
from whitecap.io import read
from whitecap.io.run import RunInfo
from whitecap.pipeline import simulate
from whitecap.sim import bodies, obstacles as obs
from whitecap.sim.driver import build_solver

from .conftest import BPY_END


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("WHITECAP_CACHE", str(tmp_path / "cache"))


def law(motion: dict, **obstacle) -> bodies.MotionLaw:
    sc = scene_from_dict({"obstacle": [{"mesh": "m.stl", "motion": motion, **obstacle}]})
    return bodies.MotionLaw(sc.obstacle[0], sc.base_dir)


# ---------------------------------------------------------------- motion laws
def test_piston_motion_law_values(tmp_path):
    S, T = 0.1, 2.0
    p = law({"kind": "piston", "axis": [2.0, 0, 0], "stroke": S, "period": T})
    for t, x in ((0.0, 0.0), (T / 4, S / 2), (T / 2, 0.0), (3 * T / 4, -S / 2), (T / 12, S / 4)):
        R, tr = p.pose(t)
        assert np.allclose(R, np.eye(3))
        assert np.allclose(tr, [x, 0, 0], atol=1e-12), (t, tr)  # the axis is normalised
    # peak velocity π S / T at t = 0, from the step velocity the kernels use
    A, b = bodies.step_velocity(*p.pose(0.0), *p.pose(1e-6), 1e-6)
    assert np.allclose(A, 0) and b[0] == pytest.approx(math.pi * S / T, rel=1e-6)
    # a ramp starts at rest and reaches the full stroke after it
    pr = law({"kind": "piston", "axis": [0, 1, 0], "stroke": S, "period": T, "ramp": 2 * T})
    assert pr.pose(0.01)[1][1] < 1e-4 and pr.pose(2 * T + T / 4)[1][1] == pytest.approx(S / 2)
    # a time series from CSV, linearly interpolated, held past its ends
    csv = tmp_path / "piston.csv"
    csv.write_text("time,x\n0,0\n1,0.2\n2,-0.1\n")
    pc = law({"kind": "piston", "axis": [1, 0, 0], "csv": str(csv)})
    assert [pc.pose(t)[1][0] for t in (0.5, 1.5, 5.0)] == pytest.approx([0.1, 0.05, -0.1])


def test_flap_spin_and_keyframe_laws():
    f = law({"kind": "flap", "hinge_axis": [0, 1, 0], "hinge_point": [1, 0, 0], "amplitude": 10, "period": 4})
    R, T = f.pose(1.0)  # at a quarter period: the full amplitude
    assert math.degrees(math.acos((np.trace(R) - 1) / 2)) == pytest.approx(10)
    assert np.allclose(R @ [1, 0, 0] + T, [1, 0, 0])  # the hinge stays put
    s = law({"kind": "spin", "axis": [0, 0, 1], "centre": [0.5, 0.5, 0], "rpm": 60})
    R, T = s.pose(0.25)  # a quarter turn
    assert np.allclose(R @ [1.5, 0.5, 0] + T, [0.5, 1.5, 0])
    A, b = bodies.step_velocity(*s.pose(0.0), *s.pose(1e-5), 1e-5)  # u = ω × (x − c), ω = 2π ẑ
    assert np.allclose(A @ [1.5, 0.5, 0] + b, [0, 2 * math.pi, 0], atol=1e-3)
    keys = [{"time": 0, "translate": [0, 0, 0]}, {"time": 2, "translate": [1, 0, 0], "rotate": [0, 0, 90]}]
    lin = law({"kind": "keyframes", "keyframes": keys}, translate=[0.2, 0, 0])
    sm = law({"kind": "keyframes", "keyframes": keys, "interpolation": "smooth"}, translate=[0.2, 0, 0])
    assert np.allclose(lin.pose(0.5)[1] + lin.pose(0.5)[0] @ [0.2, 0, 0], [0.45, 0, 0])  # centre moves
    assert sm.pose(0.5)[1][0] + (sm.pose(0.5)[0] @ [0.2, 0, 0])[0] == pytest.approx(0.2 + 0.15625)  # smoothstep
    assert np.allclose(lin.pose(9.0)[0] @ [1, 0, 0], [0, 1, 0])  # held after the last key


@pytest.mark.parametrize("motion, msg", [
    ({"kind": "piston", "axis": [1, 0, 0]}, "needs either 'stroke' and 'period' or 'csv'"),
    ({"kind": "spin", "axis": [0, 0, 0], "centre": [0, 0, 0], "rpm": 1}, "'axis' must not be the zero vector"),
    ({"kind": "flap", "hinge_axis": [0, 1, 0], "hinge_point": [0, 0, 0], "amplitude": 5}, "needs 'period'"),
    ({"kind": "spin", "axis": [0, 0, 1], "centre": [0, 0, 0], "rpm": 1, "stroke": 2}, "'stroke' does not apply"),
])
def test_bad_motion_is_a_one_line_error_naming_the_field(motion, msg):
    with pytest.raises(InputError) as e:
        scene_from_dict({"obstacle": [{"mesh": "m.stl", "motion": motion}]}, "s.toml")
    assert str(e.value).startswith("s.toml: obstacle[0].motion") and msg in str(e.value) and "\n" not in str(e.value)


# ---------------------------------------------------------------- kinematic paddle
def paddle_scene(tmp_path, frames=4, stroke=0.12, period=0.6):
    path = tmp_path / "paddle.stl"
    trimesh.creation.box(extents=[0.03, 0.14, 0.34]).export(str(path))
    return scene_from_dict({
        "domain": {"upper": [0.5, 0.12, 0.3]},
        "solver": {"particle_radius": 0.01},
        "fluid": [{"lower": [0.0, 0.0, 0.0], "upper": [0.5, 0.12, 0.12]}],
        "obstacle": [{"mesh": str(path), "translate": [0.2, 0.06, 0.15], "friction": 0.2,
                      "motion": {"kind": "piston", "axis": [1, 0, 0], "stroke": stroke, "period": period}}],
        "foam": {"enabled": False},
        "output": {"frames": frames},
    })


def test_kinematic_paddle_never_leaks_and_keeps_every_particle(tmp_path):
    """A full-width, full-height paddle swings 12 cm at up to 0.63 m/s through the water: at the end of
    every step no particle is deeper than 0.1 r in it (in the paddle's own SDF at its pose), no particle
    has crossed it, and the count and ids are the initial ones."""
    sc = paddle_scene(tmp_path)
    s = build_solver(sc)
    r = sc.solver.particle_radius
    grid = obs.load_obstacles(sc).grids[0]
    motion = bodies.MotionLaw(sc.obstacle[0])
    n0, ids0 = s.n, np.sort(s.state.ids.to_numpy())
    x = s.state.x.to_numpy()
    left = x[:, 0] < 0.2  # the side of the paddle each particle starts on, by id
    side = dict(zip(s.state.ids.to_numpy(), left))
    dt, worst, pushed = 1 / 480, np.inf, 0.0
    for _ in range(300):  # 0.625 s: a full period and more
        s.step(dt)
        x, ids = s.state.x.to_numpy(), s.state.ids.to_numpy()
        R, T = motion.pose(s.time)
        worst = min(worst, float(grid.sample((x - T) @ R).min()))
        plate = 0.2 + T[0]
        was_left = np.array([side[i] for i in ids])
        assert not (was_left & (x[:, 0] > plate)).any() and not (~was_left & (x[:, 0] < plate)).any(), s.time
        pushed = max(pushed, float(s.state.v.to_numpy()[:, 0].max()))
    assert worst > 0.9 * r, f"a particle was {1 - worst / r:.2f} r deep in the paddle"
    assert s.n == n0 and np.array_equal(np.sort(s.state.ids.to_numpy()), ids0)
    assert pushed > 0.5  # the paddle (peak 0.63 m/s) carries the water with it


def test_resume_with_a_moving_body_is_byte_identical(tmp_path):
    sc = paddle_scene(tmp_path, frames=4, period=0.2)
    full, part = tmp_path / "full", tmp_path / "part"
    simulate(sc, out=full, show_progress=False)
    simulate(sc, out=part, frames=2, show_progress=False)
    simulate(sc, out=part, resume=True, show_progress=False)
    for i in (3, 4):
        a = (full / f"fluid/fluid_{i:05d}.ply").read_bytes()
        assert a == (part / f"fluid/fluid_{i:05d}.ply").read_bytes(), i
    assert RunInfo.load(full).frames[4].bodies == RunInfo.load(part).frames[4].bodies


def test_friction_acts_relative_to_a_moving_body(tmp_path):
    """Water on a plate sliding at 0.3 m/s with full friction rides along with it: friction damps the
    velocity relative to the body, not the velocity itself (which would hold the water back)."""
    path = tmp_path / "plate.stl"
    trimesh.creation.box(extents=[0.3, 0.14, 0.04]).export(str(path))
    sc = scene_from_dict({
        "domain": {"upper": [0.8, 0.1, 0.3]},
        "solver": {"particle_radius": 0.01},
        "fluid": [{"lower": [0.08, 0.0, 0.05], "upper": [0.22, 0.1, 0.11]}],
        "obstacle": [{"mesh": str(path), "translate": [0.15, 0.05, 0.02], "friction": 1.0,
                      "motion": {"kind": "keyframes", "keyframes": [
                          {"time": 0.0}, {"time": 2.0, "translate": [0.6, 0.0, 0.0]}]}}],
        "foam": {"enabled": False},
    })
    s = build_solver(sc)
    for _ in range(96):  # 0.4 s
        s.step(1 / 240)
    x, v = s.state.x.to_numpy(), s.state.v.to_numpy()
    on_plate = x[:, 2] < 0.04 + 0.03
    assert on_plate.sum() > 20
    assert np.median(v[on_plate, 0]) == pytest.approx(0.3, rel=0.1)
    assert v[on_plate, 2].max() < 0.3  # resting on it, not thrown off


def test_diffuse_particles_never_inside_a_moving_body(tmp_path):
    """The diffuse stage tests particles against the body at its pose of each frame, not at rest: a
    ball rolled 12 cm into the oncoming dam-break wave (0.24 m/s). Control: diffuse particles do come
    close to it (within 2 r of its surface, where it is at that frame) in most frames, so that none
    being inside it means something."""
    path = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=3, radius=0.06).export(str(path))
    sc = scene_from_dict({
        "domain": {"upper": [0.5, 0.2, 0.4]},
        "solver": {"particle_radius": 0.01},
        "fluid": [{"lower": [0, 0, 0], "upper": [0.16, 0.2, 0.3]}],
        "obstacle": [{"mesh": str(path), "translate": [0.36, 0.1, 0.06],
                      "motion": {"kind": "keyframes", "keyframes": [
                          {"time": 0.0}, {"time": 0.5, "translate": [-0.12, 0.0, 0.0]}]}}],
        "foam": {"preset": "auto", "k_ta": 400.0, "k_wc": 4000.0},
        "output": {"frames": 14},
    })
    simulate(sc, out=tmp_path / "run", show_progress=False)
    info = RunInfo.load(tmp_path / "run")
    total, near, frames_near = 0, 0, 0
    for i in range(15):
        d = read(tmp_path / f"run/diffuse/diffuse_{i:05d}.ply")
        total += len(d)
        centre = obstacle_matrix(info.obstacles[0], info.body_pose(i, 0))[:3, 3]
        if len(d):
            dist = np.linalg.norm(d.positions - centre, axis=1)
            assert dist.min() > 0.06 - 1e-3, (i, dist.min())  # outside the ball (to its facets)
            close = int((dist < 0.06 + 0.02).sum())
            near += close
            frames_near += close > 0
    assert info.body_pose(14, 0).position[0] == pytest.approx(-0.12 * 14 / 30 / 0.5)  # it moved 11 cm
    assert total > 0 and near >= 50 and frames_near >= 8, (total, near, frames_near)


# ---------------------------------------------------------------- downstream: run.json, render
def test_run_json_records_each_body_pose_per_frame(tmp_path):
    sc = paddle_scene(tmp_path, frames=3, period=0.4)
    info = simulate(sc, out=tmp_path / "run", show_progress=False)
    info = RunInfo.load(tmp_path / "run")
    o = info.obstacles[0]
    assert o.mesh.endswith("paddle.stl") and o.motion["kind"] == "piston"
    law_ = bodies.MotionLaw(sc.obstacle[0])
    for f in info.frames:
        (b,) = f.bodies
        assert b.quaternion == pytest.approx([1, 0, 0, 0])
        assert b.position == pytest.approx(law_.pose(f.time)[1].tolist(), abs=1e-12)
    # at t = 0.1 s (a quarter period) the paddle is at its full stroke, S/2 = 6 cm
    assert info.frames[3].bodies[0].position[0] == pytest.approx(0.06, rel=1e-6)
    # the world matrix composes the pose with the rest placement: the paddle's centre moved 6 cm in x
    assert obstacle_matrix(o, info.body_pose(3, 0))[:3, 3] == pytest.approx([0.26, 0.06, 0.15])
    # a damaged pose is a one-line error naming the field
    raw = json.loads((tmp_path / "run/run.json").read_text())
    raw["frames"][0]["bodies"][0]["quaternion"][0] = 7.0
    (tmp_path / "run/run.json").write_text(json.dumps(raw))
    with pytest.raises(InputError, match=r"field 'frames\[0\]\.bodies\[0\]\.quaternion': expected a unit quaternion"):
        RunInfo.load(tmp_path / "run")


RENDER_KEYS = r"""
import sys, json
import bpy
from whitecap.config import Render
from whitecap.io.run import RunInfo
from whitecap.render.scene import build_scene
info = RunInfo.load(sys.argv[1])
build_scene(info, Render(), "preview", 0, 3)
sc, obj = bpy.context.scene, bpy.data.objects["obstacle_0"]
out = {}
for f in (1, 2, 3):
    sc.frame_set(f)
    out[f] = [list(r) for r in obj.matrix_world]
sc.frame_set(1, subframe=0.5)
out["1.5"] = [list(r) for r in obj.matrix_world]
print(json.dumps(out))
"""


def test_render_keyframes_the_moving_body(tmp_path):
    pytest.importorskip("bpy")
    import os
    import subprocess
    import sys
    from pathlib import Path

    sc = scene_from_dict({**paddle_scene(tmp_path, frames=3).model_dump(exclude={"base_dir"}), "obstacle": [{
        "mesh": str(tmp_path / "paddle.stl"), "translate": [0.2, 0.06, 0.15],
        "motion": {"kind": "spin", "axis": [0, 1, 0], "centre": [0.2, 0.06, 0.15], "rpm": 60}}]})
    simulate(sc, out=tmp_path / "run", show_progress=False)
    info = RunInfo.load(tmp_path / "run")
    src = str(Path(__file__).resolve().parents[1] / "src")
    res = subprocess.run([sys.executable, "-c", RENDER_KEYS + BPY_END, str(tmp_path / "run")], capture_output=True,
                         text=True, env={**os.environ, "PYTHONPATH": src})
    assert res.returncode == 0, res.stderr[-2000:]
    got = json.loads([ln for ln in res.stdout.splitlines() if ln.startswith("{")][-1])
    for f in (1, 3):
        # the object's matrix is the pose; with the rest placement baked into the mesh the world
        # placement is obstacle_matrix (pose · placement)
        pose = pose_matrix(info.body_pose(f, 0))
        assert np.allclose(got[str(f)], pose, atol=1e-5), f
    assert not np.allclose(got["1"], got["3"], atol=1e-3)  # it moves (6° per frame at 30 fps, 60 rpm)
    # between frames the keys interpolate: half way at frame 1.5 (what motion blur samples)
    angle = {f: math.degrees(math.acos((np.trace(np.array(got[f])[:3, :3]) - 1) / 2)) for f in ("1", "2", "1.5")}
    assert angle["1"] == pytest.approx(12.0, abs=1e-3) and angle["2"] == pytest.approx(24.0, abs=1e-3)  # 60 rpm
    assert angle["1.5"] == pytest.approx(18.0, abs=0.05)
    assert np.allclose(np.array(got["1.5"])[:3, 3], (np.array(got["1"]) + np.array(got["2"]))[:3, 3] / 2, atol=2e-3)


def test_view_draws_the_body_at_each_frames_pose(tiny_run, tmp_path):
    """Playback draws a moving obstacle where run.json puts it at each frame: a red cube at rest at
    frame 0, lifted 10 cm and turned 45° about z at frame 1."""
    import shutil

    from whitecap.view.draw import project

    from .test_view import H, W, _camera, _img, _render

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    trimesh.creation.box(extents=(0.08, 0.08, 0.08)).export(run / "block.obj")
    meta = json.loads((run / "run.json").read_text())
    meta["obstacles"] = [{"mesh": "block.obj", "translate": [0.45, 0.1, 0.06], "color": [0.9, 0.1, 0.1]}]
    c45 = math.cos(math.radians(22.5))
    for f in meta["frames"]:
        lifted = f["index"] >= 1
        f["bodies"] = [{"position": [0.0, 0.0, 0.1 if lifted else 0.0],
                        "quaternion": [c45, 0.0, 0.0, math.sin(math.radians(22.5))] if lifted else [1.0, 0, 0, 0]}]
    (run / "run.json").write_text(json.dumps(meta))
    pngs = _render(run, tmp_path / "png", "--frames", 2)
    cam = _camera(run)
    # rotation about z through the world origin: the cube's centre goes to Rz(45°)·(0.45, 0.1) + lift
    moved = np.array([0.45 * math.cos(math.pi / 4) - 0.1 * math.sin(math.pi / 4),
                      0.45 * math.sin(math.pi / 4) + 0.1 * math.cos(math.pi / 4), 0.16])
    for png, centre, empty in ((pngs[0], [0.45, 0.1, 0.06], moved), (pngs[1], moved, [0.45, 0.1, 0.06])):
        img = _img(png)
        red = (img[..., 0] > img[..., 1] + 40) & (img[..., 0] > img[..., 2] + 40)
        c, r = np.round(project(np.array([centre]), cam, W, H)[0]).astype(int)
        assert red[r - 2:r + 3, c - 2:c + 3].all(), png
        c, r = np.round(project(np.array([empty]), cam, W, H)[0]).astype(int)
        assert not red[r - 2:r + 3, c - 2:c + 3].any(), png


# ---------------------------------------------------------------- dynamic bodies (two-way coupling)
def slab_scene(tmp_path, density, z, gravity=(0.0, 0.0, -9.81)):
    """A quasi-2D tank (5 particles across) with a 30 × 10 × 8 cm slab spanning its width."""
    path = tmp_path / "slab.stl"
    trimesh.creation.box(extents=[0.3, 0.1, 0.08]).export(str(path))
    return scene_from_dict({
        "domain": {"upper": [0.5, 0.1, 0.35], "gravity": list(gravity)},
        "solver": {"particle_radius": 0.01},
        "fluid": [{"lower": [0, 0, 0], "upper": [0.5, 0.1, 0.15]}],
        "obstacle": [{"mesh": str(path), "translate": [0.25, 0.05, z], "dynamic": True, "density": density,
                      "friction": 0.0}],
        "foam": {"enabled": False},
    })


def run_slab(sc, seconds=2.0):
    s = build_solver(sc)
    body = s.colliders[0].bodies[0]
    track = []
    for f in range(1, int(seconds * 30) + 1):
        s.advance_frame(f)
        R = body.pose()[0]
        track.append((s.time, body.c.copy(), math.degrees(math.acos(min(1.0, R[2, 2])))))
    return s, body, track


def water_level(x: np.ndarray, away_from: float, r: float) -> float:
    """The still-water level away from the body: the top particle of each column, median, plus r."""
    xf = x[np.abs(x[:, 0] - away_from) > 0.18]
    cols = np.floor(xf[:, 0] / (2 * r)).astype(int) * 1000 + np.floor(xf[:, 1] / (2 * r)).astype(int)
    return float(np.median([xf[cols == k, 2].max() for k in np.unique(cols)])) + r


def test_mass_properties_come_from_the_mesh(tmp_path):
    sc = slab_scene(tmp_path, 500.0, 0.18)
    body = obs.load_obstacles(sc).bodies[0]
    assert body.mass == pytest.approx(500 * 0.3 * 0.1 * 0.08, rel=1e-6)
    assert body.c0 == pytest.approx([0.25, 0.05, 0.18])
    assert np.diag(body.I0) == pytest.approx(body.mass / 12 * np.array([0.1**2 + 0.08**2, 0.3**2 + 0.08**2,
                                                                         0.3**2 + 0.1**2]), rel=1e-6)


def test_light_body_floats_upright_at_half_draft(tmp_path):
    """Archimedes: a slab of 500 kg/m³ (8 cm tall) dropped onto the water settles with half its height
    under the still-water level, within 5 % of its height (4 mm), upright within 5°, and at rest."""
    sc = slab_scene(tmp_path, 500.0, 0.18)
    s, body, track = run_slab(sc)
    draft = water_level(s.state.x.to_numpy(), body.c[0], 0.01) - (body.c[2] - 0.04)
    assert abs(draft - 0.04) < 0.05 * 0.08, draft
    assert max(t for _, _, t in track) < 5.0
    zs = [c[2] for t, c, _ in track if t > 1.5]
    assert max(zs) - min(zs) < 0.005  # settled, not bobbing or exploding


def test_heavy_body_sinks_to_the_floor(tmp_path):
    s, body, track = run_slab(slab_scene(tmp_path, 2000.0, 0.12))
    bottom = body.c[2] - 0.04
    assert bottom < 2.5 * 0.01, bottom  # on the floor, over at most the last layer of particles (2r)
    assert abs(body.V[2]) < 0.02 and track[-1][2] < 5.0


def test_neutral_body_stays_where_it_was_released(tmp_path):
    s, body, track = run_slab(slab_scene(tmp_path, 1000.0, 0.07))
    start = track[0][1]
    assert max(np.linalg.norm(c - start) for _, c, _ in track) < 0.02  # two particle radii over 2 s
    assert max(t for _, _, t in track) < 5.0


def wall_bound_body(tmp_path, gravity=(0.0, 0.0, 0.0)):
    """The slab of slab_scene (density 2000), alone: it spans the tank's width (y) exactly."""
    return obs.load_obstacles(slab_scene(tmp_path, 2000.0, 0.12, gravity)).bodies[0]


def hull_world(body) -> np.ndarray:
    return (body.hull - body.c0) @ geometry.quat_matrix(body.q).T + body.c


def test_walls_turn_back_a_body_jammed_between_them(tmp_path):
    """A slab as wide as the tank, set turning about z (yaw), meets both side walls with opposite
    corners: the walls stop the turn and turn it back, and its centre never jumps. (The walls used
    to act on the centre alone, one side per axis: the turn went on, and the centre was thrown 3 cm
    in one step, which crushed the water under a heavy body and flung it out of the tank.)"""
    body = wall_bound_body(tmp_path)
    body.W = np.array([0.0, 0.0, 2.0])
    dt = 1 / 300
    for _ in range(100):
        c = body.c.copy()
        body.advance(dt)
        assert np.linalg.norm(body.c - c) < 1e-3  # no jumps: at most a millimetre a step
        v = hull_world(body)
        assert (v >= body.lo - 1e-4).all() and (v <= body.hi + 1e-4).all()  # within a tenth of a millimetre
    R = geometry.quat_matrix(body.q)
    assert math.degrees(math.acos(min(1.0, R[0, 0]))) < 0.5  # turned back between the walls
    assert abs(body.W[2]) < 0.05 and body.c[1] == pytest.approx(0.05, abs=1e-3)


def test_a_tilted_body_dropped_on_the_floor_lands_on_it_without_gaining_energy(tmp_path):
    body = wall_bound_body(tmp_path, gravity=(0.0, 0.0, -9.81))
    body.q = np.array([math.cos(math.radians(10) / 2), 0.0, math.sin(math.radians(10) / 2), 0.0])  # 10° about y
    g, dt = 9.81, 1 / 300

    def energy():
        I = geometry.quat_matrix(body.q) @ body.I0 @ geometry.quat_matrix(body.q).T
        return 0.5 * body.mass * body.V @ body.V + 0.5 * body.W @ I @ body.W + body.mass * g * body.c[2]

    e0 = energy()
    for _ in range(300):
        body.advance(dt)
        assert hull_world(body)[:, 2].min() > -1e-4  # never through the floor
        assert energy() <= e0 + 1e-9 * abs(e0) + 1e-6
    assert hull_world(body)[:, 2].min() < 1e-3  # resting on it
    assert np.linalg.norm(body.V) < 0.05 and np.linalg.norm(body.W) < 0.5


def test_momentum_is_exchanged_between_body_and_fluid(tmp_path):
    """No gravity, no walls touched: a body pushed at 0.5 m/s through a free blob of water. The water
    gains momentum, and body + water momentum stays within 5 % of the initial push over the window.
    (XSPH and vorticity confinement, which do not conserve momentum, are off.)"""
    path = tmp_path / "cube.stl"
    trimesh.creation.box(extents=[0.08, 0.08, 0.08]).export(str(path))
    sc = scene_from_dict({
        "domain": {"upper": [0.8, 0.4, 0.4], "gravity": [0.0, 0.0, 0.0]},
        "solver": {"particle_radius": 0.01, "xsph_c": 0.0, "vorticity_epsilon": 0.0},
        "fluid": [{"lower": [0.1, 0.08, 0.08], "upper": [0.5, 0.32, 0.32]}],
        "obstacle": [{"mesh": str(path), "translate": [0.25, 0.2, 0.2], "dynamic": True, "density": 1000.0}],
        "foam": {"enabled": False},
    })
    s = build_solver(sc)
    body = s.colliders[0].bodies[0]
    body.V = np.array([0.5, 0.0, 0.0])
    p0 = body.mass * 0.5
    dt = 1 / 480
    fluid_p = 0.0
    for _ in range(48):  # 0.1 s: the cube moves 5 cm, the blob's edge is 21 cm ahead of it
        s.step(dt)
        fluid_p = s.mass * s.state.v.to_numpy().astype(np.float64).sum(0)
        total = body.mass * body.V + body.F * dt + fluid_p  # F·Δt: the reaction not yet applied
        assert np.linalg.norm(total - [p0, 0, 0]) < 0.05 * p0, (total, p0)
    assert fluid_p[0] > 0.2 * p0  # the water was pushed
    assert body.V[0] < 0.8 * 0.5  # and the body slowed


def test_resume_with_a_dynamic_body_is_byte_identical(tmp_path):
    """The body's state (centre, quaternion, velocities, pending reaction) is in the checkpoint."""
    sc = slab_scene(tmp_path, 500.0, 0.18)
    sc.output.frames = 4
    full, part = tmp_path / "full", tmp_path / "part"
    simulate(sc, out=full, show_progress=False)
    simulate(sc, out=part, frames=2, show_progress=False)
    simulate(sc, out=part, resume=True, show_progress=False)
    for i in (3, 4):
        assert (full / f"fluid/fluid_{i:05d}.ply").read_bytes() == (part / f"fluid/fluid_{i:05d}.ply").read_bytes(), i
    a, b = RunInfo.load(full), RunInfo.load(part)
    assert a.frames[4].bodies == b.frames[4].bodies
    assert a.frames[4].bodies[0].position[2] < a.frames[0].bodies[0].position[2]  # it fell in


def test_a_body_passing_into_another_is_warned_about(tmp_path, capfd):
    """Contact between bodies is not modelled, but not silent: a heavy cube falling onto a static
    block warns once, naming both."""
    path = tmp_path / "cube.stl"
    trimesh.creation.box(extents=[0.06, 0.06, 0.06]).export(str(path))
    sc = scene_from_dict({
        "domain": {"upper": [0.3, 0.3, 0.4]},
        "solver": {"particle_radius": 0.01},
        "fluid": [{"lower": [0.0, 0.0, 0.0], "upper": [0.06, 0.3, 0.06]}],
        "obstacle": [{"mesh": str(path), "translate": [0.15, 0.15, 0.05]},
                     {"mesh": str(path), "translate": [0.15, 0.15, 0.2], "dynamic": True, "density": 3000.0}],
        "foam": {"enabled": False},
    })
    s = build_solver(sc)
    for f in range(1, 9):  # 0.27 s: it falls 0.35 m, through the block's top at 0.08 m
        s.advance_frame(f)
    err = capfd.readouterr().err
    assert s.colliders[0].bodies[1].c[2] < 0.11  # it did fall into the block
    assert " ".join(err.split()).count("obstacle[1] passes into obstacle[0]") == 1, err


def test_live_view_frames_carry_the_bodies_pose(tmp_path):
    from whitecap.view.sources import LiveSource

    sc = paddle_scene(tmp_path, period=0.4)
    src = LiveSource(sc)
    law_ = bodies.MotionLaw(sc.obstacle[0])
    for _ in range(3):
        src.advance()
        fr = src.current()
        assert fr.bodies[0].position == pytest.approx(law_.pose(src.solver.time)[1].tolist(), abs=1e-12)
    assert fr.bodies[0].position[0] == pytest.approx(0.06, rel=1e-6)  # t = 0.1 s: a quarter period
    src.reset()
    assert src.current().bodies[0].position == pytest.approx([0, 0, 0], abs=1e-12)  # reset moves it back


def test_bad_piston_csv_is_a_one_line_error_naming_file_and_field(tmp_path):
    csv = tmp_path / "p.csv"
    csv.write_text("t,x\n0,0\n1,oops\n")
    motion = {"kind": "piston", "axis": [1, 0, 0], "csv": str(csv)}
    with pytest.raises(InputError, match=r"p\.csv: line 3: obstacle\[0\]\.motion\.csv: expected 'time, displacement'"):
        law(motion)
    with pytest.raises(InputError, match=r"missing\.csv: obstacle\[0\]\.motion\.csv: file not found"):
        law({**motion, "csv": str(tmp_path / "missing.csv")})


# ---------------------------------------------------------------- diffuse particles and moving bodies
def moving_box(tmp_path):
    """A 10 cm cube moving 20 cm in x and turning 30° about z over 1 s, as the diffuse stage sees it."""
    from whitecap.diffuse.generator import FoamGenerator
    from whitecap.diffuse.params import resolve

    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=[0.1, 0.1, 0.1]).export(str(path))
    sc = scene_from_dict({
        "domain": {"upper": [1.0, 0.4, 0.4]},
        "solver": {"particle_radius": 0.01},
        "fluid": [{"lower": [0, 0, 0], "upper": [0.1, 0.1, 0.1]}],
        "obstacle": [{"mesh": str(path), "translate": [0.3, 0.2, 0.2], "motion": {"kind": "keyframes", "keyframes": [
            {"time": 0.0}, {"time": 1.0, "translate": [0.2, 0.0, 0.0], "rotate": [0, 0, 30]}]}}],
    })
    (g,) = obs.load_obstacles(sc).posed_grids()
    gen = FoamGenerator(resolve(preset="ihmsen2012"), 0.01, ([0, 0, 0], [1, 0.4, 0.4]), (0, 0, -9.81), seed=1,
                        obstacles=[g])
    return g, gen, bodies.MotionLaw(sc.obstacle[0])


def test_foam_on_a_moving_body_rides_with_it(tmp_path):
    """Foam lying on the top of a moving, turning box is carried by it frame after frame (even where
    the water would leave it in place): it ends where the body's motion takes its first position,
    with the body's velocity there; foam away from the body is left alone."""
    from whitecap.io.diffuse_types import FOAM

    g, gen, law_ = moving_box(tmp_path)
    r, dt = 0.01, 1 / 30
    on_top = np.array([[0.28, 0.2, 0.25 + r], [0.33, 0.23, 0.25 + r], [0.26, 0.17, 0.25 + 0.5 * r]])
    away = np.array([[0.7, 0.2, 0.05]])
    x0 = np.concatenate([on_top, away]).astype(np.float32)
    kind = np.full(len(x0), FOAM, np.uint8)
    x = x0.copy()
    for i in range(1, 16):  # half a second: 10 cm and 15°
        g.at_frame(i * dt, None, dt)
        x, v, alive = gen._obstacles(x, x.copy(), np.zeros_like(x), kind)  # the water does not move it
        assert alive.all()
    R, T = law_.pose(15 * dt)
    assert np.abs(x[:3] - (on_top @ R.T + T)).max() < 1e-5  # carried rigidly: 10 cm along, turned 15°
    assert np.abs(x[:3] - on_top).max() > 0.09
    A, b = bodies.step_velocity(*law_.pose(14 * dt), R, T, dt)
    assert np.allclose(v[:3], x[:3].astype(np.float64) @ A.T + b, atol=1e-4)  # the body's velocity there
    assert np.allclose(x[3], away[0]) and np.allclose(v[3], 0.0)


def test_spray_bounces_off_a_moving_body_and_bubbles_inside_go(tmp_path):
    """Spray fired at 2 m/s against the face of a box coming towards it never ends a frame inside
    the box: it bounces, its normal velocity relative to the body reversed and scaled by the
    restitution. Bubbles the body moves over are removed."""
    from whitecap.diffuse.generator import SPRAY_RESTITUTION
    from whitecap.io.diffuse_types import BUBBLE, SPRAY

    g, gen, _ = moving_box(tmp_path)
    dt = 1 / 30
    x = np.array([[0.62, 0.2, 0.2], [0.6, 0.18, 0.22], [0.64, 0.23, 0.19]], np.float32)
    v = np.tile(np.float32([-2.0, 0.0, 0.0]), (3, 1))
    kind = np.full(3, SPRAY, np.uint8)
    bounced = 0
    for i in range(1, 10):
        g.at_frame(i * dt, None, dt)
        moved = x + v * dt  # ballistic over the frame
        inside = g.sample(moved) <= 0
        x, v_new, alive = gen._obstacles(x, moved, v, kind)
        assert alive.all() and (g.sample(x) > 0).all(), i
        if inside.any():
            n, u = g.normal(x[inside]), g.velocity(x[inside])
            before = ((v[inside] - u) * n).sum(1)
            after = ((v_new[inside] - u) * n).sum(1)
            assert (before < -1.0).all() and np.allclose(after, -SPRAY_RESTITUTION * before, rtol=1e-3), i
            bounced += int(inside.sum())
        v = v_new
    assert bounced >= 3 and (v[:, 0] > 0).all()  # every drop hit the box and flies back
    g.at_frame(10 * dt, None, dt)
    xb = np.array([[0.37, 0.2, 0.2], [0.9, 0.2, 0.2]], np.float32)  # in the box, and far from it
    _, _, alive = gen._obstacles(xb, xb.copy(), np.zeros_like(xb), np.full(2, BUBBLE, np.uint8))
    assert alive.tolist() == [False, True]


# ---------------------------------------------------------------- wave maker
def test_piston_wave_maker_matches_biesel_theory():
    """A piston (stroke 4 cm, period 1 s, 0.5 s ramp) at one end of a quasi-2D flume 2 m long and 0.2 m
    deep (r = 7.5 mm, two particles across) makes waves whose height, fitted over two periods at a
    gauge 0.2–0.3 m from the paddle (past the evanescent modes, before the reflection from the far
    wall returns), matches Biésel's linear wave-maker theory, H/S = 2(cosh 2kh − 1)/(sinh 2kh + 2kh),
    within 15 %. The solver runs with the README's wave-maker settings: no XSPH viscosity and no
    vorticity confinement, which damp the wave further."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "wave_maker.py"
    spec = importlib.util.spec_from_file_location("wave_maker", path)
    wm = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(wm)
    assert wm.biesel(1.0, 0.2) == pytest.approx(1.015, abs=0.001)  # kh = 1.04
    _, _, H, H_th, (t0, t1), _ = wm.run_flume(r=0.0075, length=2.0, ramp=0.5, gauge=0.25, gauge_width=0.05,
                                              duration=3.4, solver={"xsph_c": 0.0, "vorticity_epsilon": 0.0})
    assert t1 - t0 == pytest.approx(2.0)  # two whole periods
    assert abs(H / H_th - 1.0) < 0.15, (H, H_th)
