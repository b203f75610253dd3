"""Dynamic bodies with held degrees of freedom and a drive (issue 32: a boat that makes way).

A held DOF stays exactly where it started over a run in waves; a driven body moves at the set
speed, the water resisting it; the free DOFs still answer the water (a driven body dropped into
still water settles to its buoyant draft); resume stays byte-identical with the drive on.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from whitecap import geometry
from whitecap.config import scene_from_dict
from whitecap.errors import InputError
from whitecap.io.run import RunInfo
from whitecap.pipeline import simulate
from whitecap.sim import bodies
from whitecap.sim.driver import build_solver

from .test_bodies import water_level

R = 0.01  # particle radius of every scene here [m]


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("WHITECAP_CACHE", str(tmp_path / "cache"))


def box_mesh(tmp_path, extents) -> str:
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=extents).export(str(path))
    return str(path)


def angles(q) -> np.ndarray:
    """Roll, pitch, yaw [deg] of q (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    M = geometry.quat_matrix(q)
    return np.degrees([math.atan2(M[2, 1], M[2, 2]), -math.asin(max(-1.0, min(1.0, M[2, 0]))),
                       math.atan2(M[1, 0], M[0, 0])])


# ---------------------------------------------------------------- settings
@pytest.mark.parametrize("extra, key, msg", [
    ({"dynamic": True, "density": 500.0, "translation_dof": [True, False]}, "obstacle[0].translation_dof",
     "at least 3"),
    ({"dynamic": True, "density": 500.0, "rotation_dof": [True, True, True, False]}, "obstacle[0].rotation_dof",
     "at most 3"),
    ({"drive": {"velocity": [0.3, 0.0, 0.0]}}, "obstacle[0]", "'drive' applies only with dynamic = true"),
    ({"rotation_dof": [True, True, False]}, "obstacle[0]", "'rotation_dof' applies only with dynamic = true"),
    ({"dynamic": True, "density": 500.0, "drive": {"velocity": [0.3, 0.0, 0.0]}}, "obstacle[0]",
     "moves the body along x, a free DOF"),
    ({"dynamic": True, "density": 500.0, "translation_dof": [False, True, True],
      "drive": {"velocity": [0.3, 0.0, 0.0], "ramp": -1.0}}, "obstacle[0].drive.ramp", "greater than or equal"),
])
def test_bad_dof_or_drive_is_a_one_line_error_naming_file_and_field(extra, key, msg):
    with pytest.raises(InputError) as e:
        scene_from_dict({"obstacle": [{"mesh": "m.stl", **extra}]}, "s.toml")
    text = str(e.value)
    assert text.startswith(f"s.toml: {key}:") and msg in text and "\n" not in text, text


def test_twist_free_keeps_only_the_turns_about_free_axes():
    def about(axis, deg):
        a = np.radians(deg) / 2
        return np.array([math.cos(a), *(math.sin(a) * np.asarray(axis, float))])

    q = geometry.quat_mul(about([0, 0, 1], 20), geometry.quat_mul(about([0, 1, 0], 10), about([1, 0, 0], 5)))
    s = bodies.twist_free(q, np.array([True, True, False]))
    M, Mq = geometry.quat_matrix(s), geometry.quat_matrix(q)
    assert s[3] == pytest.approx(0.0, abs=1e-15)  # no turn about z left
    assert np.allclose(M[:, 2], Mq[:, 2])  # the same tilt: the swing carries z where q does
    p = bodies.twist_free(q, np.array([False, True, False]))
    assert p[1] == p[3] == 0.0 and p[2] > 0  # pitch alone
    assert np.array_equal(bodies.twist_free(q, np.array([False] * 3)), [1.0, 0.0, 0.0, 0.0])
    assert bodies.twist_free(q, np.array([True] * 3)) is q


# ---------------------------------------------------------------- held DOFs in waves
def wave_tank(tmp_path, **body) -> dict:
    """A 1.2 × 0.4 m tank, 12 cm deep, with a piston wave maker at x = 0 and a 24 × 10 × 6 cm
    block of 500 kg/m³ turned 30° about z, so that the waves push it sideways and turn it."""
    paddle = tmp_path / "paddle.stl"
    trimesh.creation.box(extents=[0.03, 0.44, 0.3]).export(str(paddle))
    return scene_from_dict({
        "domain": {"upper": [1.2, 0.4, 0.35]},
        "solver": {"particle_radius": R, "xsph_c": 0.0, "vorticity_epsilon": 0.0},
        "fluid": [{"lower": [0.05, 0.0, 0.0], "upper": [1.2, 0.4, 0.12]}],
        "obstacle": [
            {"mesh": box_mesh(tmp_path, [0.24, 0.1, 0.06]), "translate": [0.6, 0.2, 0.13],
             "rotate": [0.0, 0.0, 30.0], "dynamic": True, "density": 500.0, "friction": 0.0, **body},
            {"mesh": str(paddle), "translate": [0.025, 0.2, 0.15], "friction": 0.0,
             "motion": {"kind": "piston", "axis": [1, 0, 0], "stroke": 0.05, "period": 0.7, "ramp": 0.3}},
        ],
        "foam": {"enabled": False},
    })


def track(sc, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """(centres, roll/pitch/yaw in degrees) of body 0 at every frame."""
    s = build_solver(sc)
    body = s.colliders[0].bodies[0]
    cs, angs = [], []
    for f in range(1, int(seconds * sc.solver.frame_rate) + 1):
        s.advance_frame(f)
        cs.append(body.c.copy())
        angs.append(angles(body.q))
    return np.array(cs), np.array(angs)


def test_held_sway_roll_and_yaw_stay_put_in_waves_while_heave_and_pitch_answer(tmp_path):
    """The turned block in waves: free, it is pushed sideways and turned (the scene does excite
    them); with sway, roll and yaw held it keeps y and its roll and yaw exactly, and still heaves,
    pitches and drifts with the waves."""
    free_c, free_a = track(wave_tank(tmp_path), 2.0)
    assert np.abs(free_c[:, 1] - 0.2).max() > 0.005 and np.abs(free_a[:, 2]).max() > 1.0  # sways and yaws

    held_c, held_a = track(wave_tank(tmp_path, translation_dof=[True, False, True],
                                     rotation_dof=[False, True, False]), 2.0)
    assert held_c[0, 1] == pytest.approx(0.2, abs=1e-12) and (held_c[:, 1] == held_c[0, 1]).all()  # no sway
    assert np.abs(held_a[:, [0, 2]]).max() < 1e-9  # no roll, no yaw
    assert held_c[:, 2].max() - held_c[:, 2].min() > 0.005  # heaves in the waves
    assert np.abs(held_a[:, 1]).max() > 1.0  # pitches
    assert np.abs(held_c[:, 0] - held_c[0, 0]).max() > 0.002  # surge stays free


# ---------------------------------------------------------------- the drive
U, RAMP = 0.25, 0.4  # the drive's speed [m/s] and ramp [s]


def towed_block(tmp_path, frames: int = 45, z: float = 0.18) -> dict:
    """A 20 × 10 × 8 cm block of 500 kg/m³ dropped from above the water of a 1.2 × 0.4 m tank,
    15 cm deep, and driven along −x at U, held in sway, roll and yaw."""
    return scene_from_dict({
        "domain": {"upper": [1.2, 0.4, 0.35]},
        "solver": {"particle_radius": R},
        "fluid": [{"lower": [0.0, 0.0, 0.0], "upper": [1.2, 0.4, 0.15]}],
        "obstacle": [{"mesh": box_mesh(tmp_path, [0.2, 0.1, 0.08]), "translate": [0.9, 0.2, z],
                      "dynamic": True, "density": 500.0, "friction": 0.0,
                      "translation_dof": [False, False, True], "rotation_dof": [False, True, False],
                      "drive": {"velocity": [-U, 0.0, 0.0], "ramp": RAMP}}],
        "foam": {"enabled": False},
        "output": {"frames": frames},
    })


def test_a_driven_body_moves_at_the_set_speed_and_settles_to_its_draft(tmp_path):
    """Driven through the water: x follows the eased-in speed (U·(t − ramp/2) once the ramp is
    over), the water resists it (the fluid's force on it points back, against the drive), and
    heave is still answered by the water: dropped from 3 cm above its float, it settles with half
    its height below the still water (Archimedes, 500 kg/m³), within 10 % of its height (8 mm;
    the contact coupling floats a body a little deep: held still in this tank, 4.8 cm, measured)."""
    sc = towed_block(tmp_path)
    s = build_solver(sc)
    body = s.colliders[0].bodies[0]
    x0, y0 = body.c[0], body.c[1]
    t, x, z, fx = [], [], [], []
    for f in range(1, 46):
        s.advance_frame(f)
        t.append(s.time)
        x.append(body.c[0])
        z.append(body.c[2])
        fx.append(body.F[0])
    t, x, z = np.array(t), np.array(x), np.array(z)
    late = t > RAMP + 0.1
    # The smoothstep's lag is ramp/2; the steps' rectangle rule adds about U·Δt/2 (Δt a few ms).
    assert x[late] == pytest.approx(x0 - U * (t[late] - RAMP / 2), abs=5e-3 * U)
    speed = -np.diff(x[late]) / np.diff(t[late])
    assert speed == pytest.approx(U, rel=1e-6)
    assert body.c[1] == y0 and np.abs(angles(body.q)[[0, 2]]).max() < 1e-9
    assert np.mean(np.array(fx)[late]) > 0.0  # resistance: the water pushes back along +x
    draft = water_level(s.state.x.to_numpy(), body.c[0], R) - (body.c[2] - 0.04)
    assert abs(draft - 0.04) < 0.1 * 0.08, draft
    assert z[t > 1.0].max() - z[t > 1.0].min() < 0.005  # settled, not bobbing


def test_resume_with_a_driven_body_is_byte_identical(tmp_path):
    """Stopped and resumed inside the drive's ramp: the same bytes and poses as one run."""
    sc = towed_block(tmp_path, frames=6)
    sc.obstacle[0].drive.ramp = 0.15  # frames 3-6 run on past the ramp's end (0.15 s = frame 4.5)
    full, part = tmp_path / "full", tmp_path / "part"
    simulate(sc, out=full, show_progress=False)
    simulate(sc, out=part, frames=3, show_progress=False)
    simulate(sc, out=part, resume=True, show_progress=False)
    for i in (4, 5, 6):
        assert (full / f"fluid/fluid_{i:05d}.ply").read_bytes() == (part / f"fluid/fluid_{i:05d}.ply").read_bytes(), i
    a, b = RunInfo.load(full), RunInfo.load(part)
    assert a.frames[6].bodies == b.frames[6].bodies
    assert a.frames[6].bodies[0].position[0] < a.frames[0].bodies[0].position[0] - 0.02  # it moved
