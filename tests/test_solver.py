"""Physics of the PBF solver: rest state, conservation, dam break vs experiment, what s_corr, XSPH and
vorticity confinement each do, blow-ups, resume."""

from __future__ import annotations

import numpy as np
import pytest

from whitecap import io
from whitecap.config import scene_from_dict
from whitecap.errors import SimulationError
from whitecap.io.run import RunInfo
from whitecap.pipeline import simulate
from whitecap.sim.driver import build_solver

from .conftest import tiny_scene_dict


def test_rest_state_settles():
    """A tank of water settles: density error < 1 %, small speeds, nothing leaves, no NaN."""
    r = 0.01
    sc = scene_from_dict(
        {
            "domain": {"upper": [0.3, 0.2, 0.4]},
            "solver": {"particle_radius": r},
            "fluid": [{"lower": [0, 0, 0], "upper": [0.3, 0.2, 0.24]}],
        }
    )
    s = build_solver(sc)
    for f in range(1, 61):  # 2 s
        s.advance_frame(f)
    a = s.arrays()
    x, v, rho = a["positions"], a["velocities"], a["density"]
    rho0 = sc.solver.rest_density
    assert np.isfinite(x).all() and np.isfinite(v).all()
    lo, hi = np.array(sc.domain.lower), np.array(sc.domain.upper)
    assert (x >= lo).all() and (x <= hi).all()
    # Compression error, as PBF/SPlisHSPlasH report it: mean of max(ρ − ρ0, 0)/ρ0.
    compression = np.maximum(rho - rho0, 0).mean() / rho0
    assert compression < 0.01, compression
    # In the bulk (a kernel support below the surface) the density is at rest density.
    top = x[:, 2].max()
    bulk = x[:, 2] < top - s.h
    assert abs(rho[bulk].mean() / rho0 - 1) < 0.01, rho[bulk].mean()
    # Small speeds against the column's characteristic speed √(gH) ≈ 1.5 m/s.
    speed = np.linalg.norm(v, axis=1)
    assert speed.max() < 0.1 * np.sqrt(9.81 * 0.24), speed.max()
    assert speed.mean() < 0.02, speed.mean()
    # Nothing stuck to the walls: particles in the wall layer have near-rest density too.
    near_wall = (x[:, 0] < lo[0] + 2 * r) & bulk
    assert abs(rho[near_wall].mean() / rho0 - 1) < 0.03


def test_wall_layer_rests_at_the_density_of_the_water_above_it():
    """The walls' density share ψ and its gradient ∇ψ (in ∇_i C_i of λ, and in Δp as λ_i ∇ψ_i) stand in
    for the fluid missing beyond a wall: the layer resting on the floor, a distance r above it, is at the
    density of the layers above. Without ∇ψ in λ the wall layer's correction is too weak, without it in Δp
    the wall does not push back at all: either way the wall layer ends up 2-4 ‰ denser than the water
    above it (measured), against under 1 ‰ with both."""
    r = 0.01
    sc = scene_from_dict(
        {
            "domain": {"upper": [0.12, 0.12, 0.4]},
            "solver": {"particle_radius": r, "iterations": 8},
            "fluid": [{"lower": [0, 0, 0], "upper": [0.12, 0.12, 0.3]}],
        }
    )
    s = build_solver(sc)
    layers = []
    for f in range(1, 46):  # 1.5 s: settled after 1 s; average the last 0.5 s
        s.advance_frame(f)
        if f > 30:
            a = s.arrays()
            z, rho = a["positions"][:, 2], a["density"] / sc.solver.rest_density
            layers.append([rho[(z >= 2 * k * r) & (z < 2 * (k + 1) * r)].mean() for k in range(5)])
    m = np.mean(layers, axis=0)
    assert abs(m[1:].mean() - 1) < 0.005, m  # the water above is near rest density
    excess = m[0] - m[1:].mean()
    assert abs(excess) < 1.5e-3, f"wall layer {m[0]:.4f} vs {m[1:].mean():.4f} above it"


def test_mass_and_ids_preserved(tiny_run):
    info = RunInfo.load(tiny_run)
    files = info.files("fluid")
    assert [i for i, _ in files] == [0, 1, 2, 3]
    frames = [io.read(tiny_run / rel) for _, rel in files]
    n = len(frames[0])
    assert n > 1000
    for f in frames:
        assert len(f) == n
        assert np.array_equal(np.sort(f.ids), np.arange(n, dtype=np.uint32))
    # Same particle, same id: particle 0 moves continuously (no relabelling).
    p0 = [f.positions[np.argsort(f.ids)][:50] for f in frames]
    for a, b in zip(p0, p0[1:]):
        assert np.linalg.norm(a - b, axis=1).max() < 0.1
    # The fluid has moved (it is a dam break, not a still image).
    assert frames[-1].positions[:, 0].max() > frames[0].positions[:, 0].max() + 0.02
    assert info.particle_mass > 0 and info.rest_density == 1000.0
    assert info.frames[3].time == pytest.approx(3 / info.frame_rate)


# Martin & Moyce (1952), surge front x/a against T = t sqrt(2g/a).
T_EXP = np.array([0.41, 0.84, 1.19, 1.43, 1.63, 1.82, 1.97, 2.20, 2.32, 2.50])
X_EXP = np.array([1.11, 1.23, 1.44, 1.67, 1.89, 2.11, 2.33, 2.56, 2.78, 3.00])
# The experiment's gate took time to lift; simulations released instantly run
# ahead. We shift the simulated curve by a fixed ΔT = 0.3 (a common choice for
# this data set); no other fitting is done.
GATE_SHIFT = 0.3


def test_dam_break_against_martin_moyce():
    a, r = 0.2, 0.005  # 20 particles across a
    sc = scene_from_dict(
        {
            "domain": {"upper": [1.0, 0.05, 0.45]},
            "solver": {"particle_radius": r, "frame_rate": 200, "vorticity_epsilon": 0.0},
            "fluid": [{"lower": [0, 0, 0], "upper": [a, 0.05, 2 * a]}],
        }
    )
    s = build_solver(sc)
    scale = np.sqrt(2 * 9.81 / a)
    T, X = [0.0], [a]
    f = 0
    while s.time * scale < 2.6:
        f += 1
        s.advance_frame(f)
        T.append(s.time * scale)
        X.append(s.state.x.to_numpy()[:, 0].max())
    T, X = np.array(T) + GATE_SHIFT, np.array(X) / a
    sel = (T_EXP >= 0.5) & (T_EXP <= 2.5)
    sim = np.interp(T_EXP[sel], T, X)
    rel = np.abs(sim - X_EXP[sel]) / X_EXP[sel]
    assert rel.max() < 0.10, dict(zip(T_EXP[sel], np.round(sim, 2)))


def test_blow_up_stops_with_frame_and_keeps_frames(tmp_path):
    d = tiny_scene_dict(fluid=[{"lower": [0, 0, 0], "upper": [0.2, 0.2, 0.3], "velocity": [0.0, 0.0, 500.0]}])
    sc = scene_from_dict(d)
    with pytest.raises(SimulationError, match="blew up at frame 1"):
        simulate(sc, out=tmp_path, show_progress=False, foam=False)
    assert (tmp_path / "fluid" / "fluid_00000.ply").exists()
    assert RunInfo.load(tmp_path).files("fluid") == [(0, "fluid/fluid_00000.ply")]


def test_existing_run_is_not_overwritten(tiny_run, tmp_path):
    import shutil

    from whitecap.errors import WhitecapError

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    before = (run / "fluid" / "fluid_00003.ply").read_bytes()
    with pytest.raises(WhitecapError, match="already holds a run"):
        simulate(scene_from_dict(tiny_scene_dict()), out=run, show_progress=False)
    assert (run / "fluid" / "fluid_00003.ply").read_bytes() == before


def test_resume_equals_uninterrupted_run(tmp_path):
    sc = scene_from_dict(tiny_scene_dict(output={"frames": 4}, solver={"particle_radius": 0.01, "reorder_interval": 3}))
    full, part = tmp_path / "full", tmp_path / "part"
    simulate(sc, out=full, show_progress=False, foam=False)
    simulate(sc, out=part, frames=2, show_progress=False, foam=False)  # "interrupted" after frame 2
    assert not (part / "fluid" / "fluid_00003.ply").exists()
    simulate(sc, out=part, resume=True, show_progress=False, foam=False)
    for i in range(5):
        name = f"fluid/fluid_{i:05d}.ply"
        assert (full / name).read_bytes() == (part / name).read_bytes(), name
    assert len(RunInfo.load(part).frames) == 5


def test_sphere_block_and_initial_velocity():
    sc = scene_from_dict(
        tiny_scene_dict(
            fluid=[{"shape": "sphere", "center": [0.3, 0.1, 0.2], "radius": 0.08, "velocity": [1.0, 0.0, 0.0]}]
        )
    )
    s = build_solver(sc)
    x = s.state.x.to_numpy()
    assert np.linalg.norm(x - [0.3, 0.1, 0.2], axis=1).max() <= 0.08 + 1e-6
    assert abs(len(x) - 4 / 3 * np.pi * 0.08**3 / 0.02**3) / len(x) < 0.15
    assert np.allclose(s.state.v.to_numpy(), [1.0, 0.0, 0.0])


def _weightless(r=0.01, upper=(0.4, 0.4, 0.4), fluid=None, **solver):
    """A solver in zero gravity, far from the walls."""
    fluid = fluid or [{"lower": [0.18, 0.19, 0.19], "upper": [0.18 + 4 * r, 0.19 + 2 * r, 0.19 + 2 * r]}]  # 2 particles
    sc = scene_from_dict({
        "domain": {"upper": list(upper), "gravity": [0.0, 0.0, 0.0]},
        "solver": {"particle_radius": r, "substeps": 4, **solver},
        "fluid": fluid,
        "foam": {"enabled": False},
    })
    return build_solver(sc)


def test_scorr_pushes_a_close_pair_apart_and_nothing_else_does():
    # Two spray particles half a spacing apart: far below rest density, so the clamped density
    # constraint (λ = 0) leaves them alone; only the artificial pressure s_corr separates them.
    def gap_after_a_frame(**solver):
        s = _weightless(**solver)
        x = s.state.x.to_numpy()
        x = x.mean(0) + 0.5 * (x - x.mean(0))
        s.state.x.from_numpy(x.astype(np.float32))
        s.advance_frame(1)
        x, v = s.state.x.to_numpy(), s.state.v.to_numpy()
        return np.linalg.norm(x[0] - x[1]), v

    gap, v = gap_after_a_frame()
    assert gap > 0.01 * 1.01 and np.allclose(v.sum(0), 0, atol=1e-7)  # apart, momentum kept
    gap0, v0 = gap_after_a_frame(scorr_k=0.0)
    assert gap0 == pytest.approx(0.01, rel=1e-5) and not v0.any()


def test_xsph_damps_relative_velocity_and_keeps_momentum():
    def after_a_frame(c):
        s = _weightless(xsph_c=c, scorr_k=0.0, vorticity_epsilon=0.0)
        s.state.v.from_numpy(np.array([[0, 0.1, 0], [0, -0.1, 0]], np.float32))  # shearing past each other
        s.advance_frame(1)
        return s.state.v.to_numpy()

    v = after_a_frame(0.05)
    assert 0.5 * 0.2 < v[0, 1] - v[1, 1] < 0.95 * 0.2
    assert np.allclose(v.sum(0), 0, atol=1e-7)
    v0 = after_a_frame(0.0)
    assert v0[0, 1] - v0[1, 1] == pytest.approx(0.2, rel=1e-5)


def test_vorticity_confinement_feeds_rotation_back():
    # A ball of water spinning in zero gravity: without confinement its angular momentum only
    # decays a little (XSPH); confinement (f = ε N × ω) spins it up, the more the larger ε.
    def angular_momentum(eps):
        s = _weightless(upper=(0.6, 0.6, 0.6), fluid=[{"shape": "sphere", "center": [0.3, 0.3, 0.3], "radius": 0.1}],
                        vorticity_epsilon=eps, substeps=None)
        d = s.state.x.to_numpy() - [0.3, 0.3, 0.3]
        s.state.v.from_numpy((np.cross([0.0, 0.0, 3.0], d)).astype(np.float32))  # ω = 3 rad/s about z

        def lz():
            d, v = s.state.x.to_numpy() - [0.3, 0.3, 0.3], s.state.v.to_numpy()
            return float((d[:, 0] * v[:, 1] - d[:, 1] * v[:, 0]).mean())

        l0 = lz()
        for f in range(1, 11):
            s.advance_frame(f)
        return lz() / l0

    none, some, more = angular_momentum(0.0), angular_momentum(0.05), angular_momentum(0.2)
    assert 0.95 < none <= 1.0
    assert some > none + 0.05 and more > some + 0.1, (none, some, more)


def test_grouped_scan_and_padded_lists_do_not_change_the_step():
    """The CPU's list building (four particles a scan, rows padded with the particle itself to a
    multiple of 8) against one particle a scan and no padding: the scan gives the same lists, so
    the same bytes; the padding only reorders the sums, so positions agree to rounding."""
    out = {}
    for pad, group in [(1, 1), (1, 4), (8, 4)]:
        s = build_solver(scene_from_dict(tiny_scene_dict()))
        s.grid.pad, s.grid.group = pad, group  # whatever this processor would choose
        for f in range(1, 4):
            s.advance_frame(f)
        out[pad, group] = s.state.x.to_numpy(), s.state.v.to_numpy()
    x0, v0 = out[1, 1]
    assert np.array_equal(out[1, 4][0], x0) and np.array_equal(out[1, 4][1], v0)
    x, v = out[8, 4]
    assert np.abs(x - x0).max() < 1e-5 and np.abs(v - v0).max() < 1e-3  # r = 1 cm; speeds up to 1.6 m/s


def test_frames_read_back_use_the_same_host_blocks_and_a_held_frame_keeps_its_values():
    """PBFSolver.arrays hands out views of a few host blocks (io.array_pool): frames dropped after use take
    no new block, a frame still held (as the writer's queue holds one) is never written over, and a frame
    handed out after it has its own memory, with the particles as they are then."""
    sc = scene_from_dict({"domain": {"upper": [0.2, 0.1, 0.2]}, "solver": {"particle_radius": 0.01},
                          "fluid": [{"lower": [0, 0, 0], "upper": [0.1, 0.1, 0.12]}]})
    s = build_solver(sc)
    s.advance_frame(1)
    held = s.arrays()
    kept = {k: a.copy() for k, a in held.items()}
    made = s._frames.made
    for f in range(2, 12):  # the dam collapses: every particle moves
        s.advance_frame(f)
        a = s.arrays()
        assert not np.shares_memory(a["positions"], held["positions"])
        del a
    assert s._frames.made == made + 1, "one block for the frames after the held one, used again by each"
    for k, a in kept.items():
        assert np.array_equal(held[k], a), f"the held frame's {k} changed"
    now = s.arrays()["positions"]
    assert np.abs(now - kept["positions"]).max() > 0.01
