"""Diffuse particles (Ihmsen et al. 2012): physics, determinism, readers and errors."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from whitecap import io
from whitecap.cli import main
from whitecap.config import scene_from_dict
from whitecap.errors import InputError
from whitecap.diffuse import postprocess
from whitecap.diffuse.params import PRESETS, read_ini, resolve
from whitecap.io.run import RunInfo
from whitecap.pipeline import simulate

from .conftest import DATA, tiny_scene_dict

FOAM = {"preset": "auto", "budget": 2.0}


@pytest.fixture(scope="module")
def foam_run(tmp_path_factory) -> Path:
    """A dam break with in-simulation foam, 12 frames."""
    out = tmp_path_factory.mktemp("foam") / "run"
    simulate(scene_from_dict(tiny_scene_dict(output={"frames": 12}, foam=FOAM)), out=out, show_progress=False)
    return out


def diffuse(run: Path, i: int):
    return io.read(run / f"diffuse/diffuse_{i:05d}.ply")


@pytest.fixture(scope="module")
def settled_tank(tmp_path_factory) -> Path:
    """A tank of water left to settle for 1.5 s (no foam), then 10 more frames."""
    out = tmp_path_factory.mktemp("still") / "run"
    d = tiny_scene_dict(
        domain={"upper": [0.3, 0.2, 0.4]},
        fluid=[{"lower": [0, 0, 0], "upper": [0.3, 0.2, 0.2]}],
        output={"frames": 55},
        foam={"enabled": False},
    )
    simulate(scene_from_dict(d), out=out, show_progress=False)
    return out


@pytest.mark.parametrize("preset", ["ihmsen2012", "splishsplash", "dualsphysics", "auto"])
def test_still_water_makes_no_foam(settled_tank, tmp_path, preset):
    pattern = str(settled_tank / "fluid" / "fluid_0004[5-9].ply")
    info = postprocess(pattern, out=tmp_path, preset=preset, dt=1 / 30, radius=0.01, show_progress=False)
    assert len(info.files("diffuse")) == 5
    rows = np.loadtxt(tmp_path / "diffuse" / "counts.csv", delimiter=",", skiprows=1)
    assert rows.shape == (5, 5) and rows[:, 2:].sum() == 0


def test_still_water_in_simulation_makes_no_foam(tmp_path):
    d = tiny_scene_dict(domain={"upper": [0.3, 0.2, 0.4]}, fluid=[{"lower": [0, 0, 0], "upper": [0.3, 0.2, 0.2]}],
                        output={"frames": 6})
    simulate(scene_from_dict(d), out=tmp_path, show_progress=False)
    rows = np.loadtxt(tmp_path / "diffuse" / "counts.csv", delimiter=",", skiprows=1)
    assert rows.shape == (7, 5) and rows[:, 2:].sum() == 0


def test_dam_break_makes_all_three_types(foam_run):
    rows = np.loadtxt(foam_run / "diffuse" / "counts.csv", delimiter=",", skiprows=1)
    both = [i for i in range(13) if (rows[i, 2:] > 0).all()]
    assert both, rows
    d = diffuse(foam_run, both[-1])
    assert set(np.unique(d.arrays["type"])) == {0, 1, 2}
    info = RunInfo.load(foam_run)
    assert info.files("diffuse")[-1] == (12, "diffuse/diffuse_00012.ply")
    # The file follows the contract.
    from plyfile import PlyData

    names = PlyData.read(str(foam_run / "diffuse/diffuse_00012.ply"))["vertex"].data.dtype
    assert names.names == ("x", "y", "z", "vx", "vy", "vz", "type", "lifetime", "radius", "id")
    assert names["type"] == np.uint8 and names["id"] == np.uint32


def test_spray_above_surface_bubbles_inside_and_rising(foam_run):
    from scipy.spatial import cKDTree

    info = RunInfo.load(foam_run)
    h = 4 * info.particle_radius
    rows = np.loadtxt(foam_run / "diffuse" / "counts.csv", delimiter=",", skiprows=1)
    frames = [i for i in range(4, 13) if rows[i, 2] > 5 and rows[i, 4] > 20]
    assert len(frames) >= 3, rows
    for i in frames:
        f, d = io.read(foam_run / f"fluid/fluid_{i:05d}.ply"), diffuse(foam_run, i)
        tree = cKDTree(f.positions)
        t = d.arrays["type"]
        spray, bub = d.positions[t == 0], d.positions[t == 2]
        # Spray: above the local fluid (higher than the mean of the fluid within 3h, or clear of it).
        assert len(spray) > 0
        over = []
        for p in spray:
            js = tree.query_ball_point(p, 3 * h)
            over.append(not js or p[2] > f.positions[js, 2].mean())
        assert np.mean(over) > 0.9, np.mean(over)
        # Bubbles: inside the fluid (fluid all round), rising relative to the local fluid.
        # Types are assigned where a particle was at the start of the frame, before it moved:
        # a bubble moves by x += Δt v, a new one has not moved yet (its id is new this frame).
        dt = 1 / info.frame_rate
        prev_ids = diffuse(foam_run, i - 1).ids
        moved = d.ids[t == 2] <= (prev_ids.max() if len(prev_ids) else -1)
        start = bub - dt * d.velocities[t == 2] * moved[:, None]
        counts = np.array([len(tree.query_ball_point(p, h)) for p in start])
        assert (counts > 10).mean() > 0.9, (counts > 10).mean()
        # Rising: bubbles that were already bubbles last frame (new ones start at the fluid's
        # velocity) move up relative to the kernel-averaged velocity of the fluid round them
        # where they were when the fluid dragged them.
        prev = diffuse(foam_run, i - 1)
        old = set(prev.ids[prev.arrays["type"] == 2].tolist())
        sel = np.array([int(k) in old for k in d.ids[t == 2]])
        assert sel.sum() > 10
        rel = []
        for p, v in zip(start[sel], d.velocities[t == 2][sel]):
            js = tree.query_ball_point(p, h)
            w = 1 - np.linalg.norm(f.positions[js] - p, axis=1) / h
            rel.append(v[2] - (w @ f.velocities[js][:, 2]) / w.sum() if len(js) else np.nan)
        assert np.nanmean(rel) > 0.05  # (a bubble that has just left the water has no fluid round it)


def test_foam_lifetime_falls_and_foam_disappears_at_zero(foam_run):
    info = RunInfo.load(foam_run)
    dt = 1 / info.frame_rate
    a, b = diffuse(foam_run, 10), diffuse(foam_run, 11)
    foam_a = a.arrays["type"] == 1
    assert foam_a.sum() > 10
    ids_b = {int(k): n for n, k in enumerate(b.ids)}
    # A particle that was foam and moved as foam in the next frame has lived dt less.
    was = [(n, ids_b[int(k)]) for n, k in enumerate(a.ids) if foam_a[n] and int(k) in ids_b]
    was = [(n, m) for n, m in was if b.arrays["type"][m] == 1]
    assert len(was) > 10
    drops = np.array([a.arrays["lifetime"][n] - b.arrays["lifetime"][m] for n, m in was])
    assert np.allclose(drops, dt, atol=1e-5)
    # Foam about to expire is gone the frame after; no foam is kept at or below zero.
    dying = [int(k) for n, k in enumerate(a.ids) if foam_a[n] and a.arrays["lifetime"][n] <= dt + 1e-6]
    gone = [k for k in dying if k not in ids_b or b.arrays["type"][ids_b[k]] != 1]
    assert len(gone) >= 0.8 * len(dying)
    for i in range(13):
        d = diffuse(foam_run, i)
        assert (d.arrays["lifetime"][d.arrays["type"] == 1] > -1e-6).all()


def test_in_simulation_equals_post_processing_byte_for_byte(foam_run, tmp_path):
    out = tmp_path / "post"
    # Post-processing keeps the simulation's running 'auto' estimate when told not to look ahead.
    postprocess(foam_run, out=out, look_ahead=False, show_progress=False)
    for i in range(13):
        name = f"diffuse/diffuse_{i:05d}.ply"
        assert (out / name).read_bytes() == (foam_run / name).read_bytes(), name
    assert (out / "diffuse/counts.csv").read_text() == (foam_run / "diffuse/counts.csv").read_text()
    assert (out / "fluid/fluid_00012.ply").exists()  # a complete run for the next stages


THREADS = r"""
import sys, taichi as ti
ti.init(arch=ti.cpu, cpu_max_num_threads=int(sys.argv[3]), log_level=ti.WARN)
import whitecap.sim.runtime as rt
rt._ARCH = "cpu"
from whitecap.diffuse import postprocess
postprocess(sys.argv[1], out=sys.argv[2], show_progress=False)
"""


def test_same_seed_same_bytes_whatever_the_thread_count(foam_run, tmp_path):
    src = Path(__file__).resolve().parents[1] / "src"
    for threads in (1, 2):
        subprocess.run([sys.executable, "-c", THREADS, str(foam_run), str(tmp_path / f"t{threads}"), str(threads)],
                       check=True, env={**os.environ, "PYTHONPATH": str(src), "WHITECAP_PROGRESS": "0"})
    for i in (4, 8, 12):
        name = f"diffuse/diffuse_{i:05d}.ply"
        assert (tmp_path / "t1" / name).read_bytes() == (tmp_path / "t2" / name).read_bytes()
    # A different seed gives different particles.
    postprocess(foam_run, out=tmp_path / "s9", seed=9, show_progress=False)
    assert (tmp_path / "s9/diffuse/diffuse_00012.ply").read_bytes() != (tmp_path / "t1/diffuse/diffuse_00012.ply").read_bytes()


def test_dualsphysics_partvtk_makes_foam(tmp_path):
    src = DATA / "dualsphysics"
    info = postprocess(src, out=tmp_path, preset="auto", show_progress=False)
    assert info.particle_radius == pytest.approx(0.01)  # dp/2 from CaseDambreak.xml
    assert info.frame_rate == pytest.approx(50.0)  # TimeOut 0.02 s
    d = io.read(tmp_path / "diffuse/diffuse_00014.ply")
    assert (d.arrays["type"] == 1).sum() > 0
    assert len(io.read(tmp_path / "fluid/fluid_00014.ply")) == 9600


def test_missing_vel_array_is_named(tmp_path, capsys):
    import vtk

    r = vtk.vtkGenericDataObjectReader()
    r.SetFileName(str(DATA / "dualsphysics" / "PartFluid_0012.vtk"))
    r.Update()
    ds = r.GetOutput()
    ds.GetPointData().RemoveArray("Vel")
    (tmp_path / "in").mkdir()
    w = vtk.vtkPolyDataWriter()
    w.SetFileName(str(tmp_path / "in" / "PartFluid_0012.vtk"))
    w.SetInputData(ds)
    w.SetFileTypeToBinary()
    w.Write()
    code = main(["foam", str(tmp_path / "in"), "--out", str(tmp_path / "o"), "--dt", "0.02", "--radius", "0.01"])
    err = capsys.readouterr().err.strip()
    assert code != 0 and "PartFluid_0012.vtk" in err and "'Vel'" in err and len(err.splitlines()) == 1


def test_input_errors(tmp_path, capsys):
    assert main(["foam", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) != 0
    assert "no such file or directory" in capsys.readouterr().err
    (tmp_path / "seq").mkdir()
    shutil.copy(DATA / "dualsphysics" / "PartFluid_0012.vtk", tmp_path / "seq")
    assert main(["foam", str(tmp_path / "seq"), "--out", str(tmp_path / "o")]) != 0
    assert "--dt" in capsys.readouterr().err


def test_presets_and_ini(tmp_path):
    p = resolve(preset="dualsphysics")
    assert (p.ta_min, p.ta_max, p.wc_min, p.wc_max, p.ke_min, p.ke_max) == (5, 20, 2, 8, 5, 50)
    assert (p.k_ta, p.k_wc, p.spray_below, p.bubble_above, p.lifetime_multiplier, p.buoyancy, p.drag) == (
        40, 40, 6, 9, 10, 0.8, 0.5)
    s = resolve(preset="splishsplash")
    assert (s.vo_min, s.vo_max, s.k_ta, s.k_wc, s.k_vo, s.lifetime_min, s.lifetime_max, s.buoyancy, s.drag,
            s.spray_below, s.bubble_above) == (5, 20, 4000, 50000, 4000, 2, 5, 2.0, 0.8, 6, 20)
    assert set(PRESETS) >= {"ihmsen2012", "dualsphysics", "splishsplash", "auto"}
    ini = tmp_path / "case.ini"
    ini.write_text("[DiffuseCalculator]\nTaMin = 3\nTaMax = 12\nKTa = 77\nSprayMax = 4\n")
    q = resolve(ini=ini, preset="dualsphysics")
    assert (q.ta_min, q.ta_max, q.k_ta, q.spray_below, q.k_wc) == (3, 12, 77, 4, 40)
    ini.write_text("[x]\nTaMin = lots\n")
    with pytest.raises(InputError, match="(?i)tamin"):
        read_ini(ini)


def test_splishsplash_partio_sequence_gives_the_same_foam_as_the_same_frames_in_ply(foam_run, tmp_path):
    # The run's fluid frames written as SPlisHSPlasH writes them (partio BGEO, y up) and
    # post-processed with --up y give byte-identical diffuse files to the same frames as z-up PLY.
    from .conftest import write_partio_bgeo

    def y_up(a):  # the inverse of the reader's y-up to z-up rotation
        return np.stack([a[:, 0], a[:, 2], -a[:, 1]], axis=1)

    (tmp_path / "partio").mkdir()
    for i in range(13):
        f = io.read(foam_run / f"fluid/fluid_{i:05d}.ply")
        write_partio_bgeo(tmp_path / "partio" / f"ParticleData_Fluid_{i}.bgeo", y_up(f.positions),
                          {"id": f.ids.astype(np.int32), "velocity": y_up(f.velocities), "density": f.density})
    info = RunInfo.load(foam_run)
    common = ["--dt", str(1.0 / info.frame_rate), "--radius", str(info.particle_radius), "--preset", "auto"]
    assert main(["foam", str(tmp_path / "partio"), "--out", str(tmp_path / "a"), "--up", "y", *common]) == 0
    assert main(["foam", str(foam_run / "fluid"), "--out", str(tmp_path / "b"), *common]) == 0
    made = 0
    for i in range(13):
        name = f"diffuse/diffuse_{i:05d}.ply"
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
        made += len(io.read(tmp_path / "a" / name))
    assert made > 0  # the comparison is not between empty files


# ------------------------------------------------------------------ the model, kernel by kernel
def _lattice(n=10, r=0.01):
    g = np.arange(n) * 2 * r
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3).astype(np.float32) + 0.1


def _potentials(x, v, r=0.01):
    """Trapped air, wave crest, kinetic energy and the surface flag of each fluid particle."""
    import taichi as ti

    from whitecap.diffuse import kernels as K
    from whitecap.diffuse.generator import SURFACE_FRACTION, FoamGenerator

    gen = FoamGenerator(resolve(preset="ihmsen2012"), r, ([0, 0, 0], [1, 1, 1]), (0, 0, -9.81), seed=1)
    n = len(x)
    fx, fv, _, _ = gen._prepare(io.ParticleFrame(x, v), n)
    g = gen.grid
    normal, surface = ti.Vector.ndarray(3, ti.f32, n), ti.ndarray(ti.i32, n)
    v_diff, e_k, vort, crest = (ti.ndarray(ti.f32, n) for _ in range(4))
    K.fluid_potentials(n, fx, fv, g.nb_count, g.nb, gen.h, SURFACE_FRACTION, normal, surface, v_diff, e_k, vort)
    K.wave_crest(n, fx, fv, g.nb_count, g.nb, normal, surface, gen.h, crest)
    return v_diff.to_numpy(), crest.to_numpy(), e_k.to_numpy(), surface.to_numpy().astype(bool)


def test_trapped_air_sees_colliding_fluid_only():
    x = _lattice()
    ta, _, ke, _ = _potentials(x, np.tile([[1.0, 0.0, 0.0]], (len(x), 1)))
    assert not ta.any() and np.allclose(ke, 0.5)  # uniform motion traps no air; E_k = ½|v|²
    left = x[:, 0] < x[:, 0].mean()
    v = np.where(left[:, None], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]).astype(np.float32)
    ta_in, _, _, _ = _potentials(x, v)  # two halves running into each other
    ta_out, _, _, _ = _potentials(x, -v)  # the same halves pulling apart
    seam = np.abs(x[:, 0] - x[:, 0].mean()) < 0.02
    far = np.abs(x[:, 0] - x[:, 0].mean()) > 0.05  # more than a kernel support from the seam
    assert ta_in[seam].min() > 0 and not ta_in[far].any()
    # (1 − v̂_ij·x̂_ij) weighs approaching pairs up to 2 and separating ones down to 0.
    assert ta_in[seam].mean() > 3 * ta_out[seam].mean()


def test_wave_crest_needs_the_surface_moving_along_its_normal():
    x = _lattice(12)
    c = x.mean(0)
    ball = x[np.linalg.norm(x - c, axis=1) < 0.1]
    out = (ball - c) / np.maximum(np.linalg.norm(ball - c, axis=1, keepdims=True), 1e-9)
    _, wc_out, _, surf = _potentials(ball, out)  # a ball bursting outward: the surface moves along n̂
    _, wc_in, _, _ = _potentials(ball, -out)  # collapsing: v̂·n̂ < 0.6, so δ_vn = 0
    assert surf.sum() > 100 and (wc_out[surf] > 0).mean() > 0.9 and not wc_out[~surf].any()
    assert not wc_in.any()


def _generate(v_diff, ta_range=(1.0, 3.0), k_ta=100.0, dt=0.05, r=0.01):
    """Run the generation kernels on n fluid particles at the origin moving at 2 m/s along z, with
    the given trapped-air potentials, I_k = 1 and no wave-crest or vorticity share."""
    import taichi as ti

    from whitecap.diffuse import kernels as K
    from whitecap.diffuse.generator import _nd
    from whitecap.sim import runtime

    runtime.init(runtime.current() or "cpu")
    n = len(v_diff)
    zeros = np.zeros(n, np.float32)
    x, v = _nd(np.zeros((n, 3), np.float32), ti.f32, True), _nd(np.tile([[0.0, 0.0, 2.0]], (n, 1)).astype(np.float32), ti.f32, True)
    tau = _nd(np.array([*ta_range, 1, 2, 0, 1e-3, 1, 2], np.float32), ti.f32)
    ids = _nd(np.arange(n, dtype=np.uint32), ti.u32)
    ek = _nd(np.ones(n, np.float32), ti.f32)  # above ke_max: I_k = 1
    cnt, rate = ti.ndarray(ti.i32, n), ti.ndarray(ti.f32, n)
    K.birth_counts(n, ids, _nd(np.asarray(v_diff, np.float32), ti.f32), _nd(zeros, ti.f32), ek, _nd(zeros, ti.f32),
                   tau, k_ta, 0.0, 0.0, dt, 7, 3, 0, cnt, rate)
    counts = cnt.to_numpy()
    total = int(counts.sum())
    offset = _nd(np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32), ti.i32)
    m = max(total, 1)
    ox, ov, ol = ti.Vector.ndarray(3, ti.f32, m), ti.Vector.ndarray(3, ti.f32, m), ti.ndarray(ti.f32, m)
    K.generate(n, x, v, ids, ek, tau, cnt, offset, 1.0, 2.0, 0.0, r, dt, 7, 3, ox, ov, ol)
    return counts, ox.to_numpy()[:total], ov.to_numpy()[:total], ol.to_numpy()[:total]


def test_generation_count_follows_the_clamped_potential():
    n = 4000
    # φ(I, τmin, τmax): 0 below τmin, linear between, 1 above τmax; n_d = I_k k_ta φ Δt = 5 φ here.
    for i_ta, expect in ((0.5, 0.0), (1.0, 0.0), (2.0, 2.5), (3.0, 5.0), (50.0, 5.0)):
        counts, *_ = _generate(np.full(n, i_ta))
        assert counts.mean() == pytest.approx(expect, abs=0.08), i_ta
        # The fraction is rounded stochastically: only the two neighbouring integers occur.
        assert set(np.unique(counts)) <= {int(np.floor(expect)), int(np.ceil(expect))}


def test_new_particles_fill_the_cylinder_around_the_velocity():
    r, dt = 0.01, 0.05
    counts, x, v, life = _generate(np.full(3000, 5.0), r=r, dt=dt)
    assert counts.sum() == 15000
    radial, axial = np.linalg.norm(x[:, :2], axis=1), x[:, 2]
    # Radius r_V, height |v|Δt = 0.1 m along v̂ = z, uniform in volume.
    assert radial.max() <= r * (1 + 1e-5) and axial.min() >= 0 and axial.max() <= 2.0 * dt * (1 + 1e-5)
    assert (radial < r / np.sqrt(2)).mean() == pytest.approx(0.5, abs=0.02)  # uniform over the disc's area
    assert axial.mean() == pytest.approx(dt, rel=0.03)
    # Velocity: the fluid's, plus the same radial offset, so particles spread out of the cylinder.
    assert np.allclose(v[:, 2], 2.0) and np.allclose(v[:, :2], x[:, :2], atol=1e-6)
    assert life.min() >= 1.0 and life.max() <= 2.0  # lifetime drawn from [lifetime_min, lifetime_max]


# ------------------------------------------------------------------ 'auto' and the budget
def _gentle_then_violent(folder: Path, frames: int = 24, r: float = 0.01) -> str:
    """A block of water at rest (frame 0), stirred gently (frame 1: ~0.1 m/s), then violently
    (frames 2...: a swirl about y of ~1 m/s at the edge and turbulent noise of 0.5 m/s)."""
    folder.mkdir(parents=True, exist_ok=True)
    ax = [np.arange(r, 0.3, 2 * r), np.arange(r, 0.2, 2 * r), np.arange(r, 0.24, 2 * r)]
    x = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3) + 0.2
    rng = np.random.default_rng(0)
    c = x.mean(0)
    for k in range(frames):
        omega, noise = (0.0, 0.0) if k == 0 else (0.6, 0.01) if k == 1 else (6.0, 0.5)
        d = x - c
        v = omega * np.stack([d[:, 2], np.zeros(len(x)), -d[:, 0]], 1) + rng.normal(0, noise, x.shape)
        io.write(folder / f"f_{k:04d}.ply", io.ParticleFrame(x.astype(np.float32), v.astype(np.float32)))
        a = omega / 30  # rotated exactly, so the block keeps its shape
        rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        x = c + d @ rot.T
    return str(folder / "f_*.ply")


def _peak(out: Path, n_fluid: int) -> tuple[np.ndarray, np.ndarray]:
    rows = np.loadtxt(out / "diffuse" / "counts.csv", delimiter=",", skiprows=1)
    return rows[:, 2:].sum(1) / n_fluid, rows


def _auto(**kw):
    from whitecap.config import Foam

    return resolve(Foam(preset="auto", **kw))


N_BLOCK = 15 * 10 * 12


def test_auto_from_the_whole_run_keeps_a_gentle_start_from_flooding_the_violent_middle(tmp_path, capsys):
    src = _gentle_then_violent(tmp_path / "in")
    postprocess(src, out=tmp_path / "o", params=_auto(budget=2.0), dt=1 / 30, radius=0.01, show_progress=False)
    err = capsys.readouterr().err
    ratio, rows = _peak(tmp_path / "o", N_BLOCK)
    assert 1.0 <= ratio.max() <= 3.0, ratio.max()  # the budget ±50 %
    assert "saturated" not in err and "warning" not in err, err
    assert "budget of 2" in err and "peak diffuse per fluid particle" in err  # what it chose, what it reached
    # The count follows the violence: the gentle frame makes a sliver of what a violent one makes.
    born = np.diff(rows[:, 2:].sum(1), prepend=0)
    assert born[1] < 0.05 * born[2:].max(), born[:4]
    # In the simulation (no look-ahead) the running estimate also keeps within the budget.
    postprocess(src, out=tmp_path / "s", params=_auto(budget=2.0), dt=1 / 30, radius=0.01, show_progress=False,
                look_ahead=False)
    err = capsys.readouterr().err
    ratio_s, _ = _peak(tmp_path / "s", N_BLOCK)
    assert 0.3 <= ratio_s.max() <= 3.0, ratio_s.max()
    assert "saturated" not in err, err


def test_the_budget_scales_the_count(tmp_path):
    src = _gentle_then_violent(tmp_path / "in")
    peaks = []
    for b in (1.0, 2.0):
        postprocess(src, out=tmp_path / f"b{b}", params=_auto(budget=b), dt=1 / 30, radius=0.01, show_progress=False)
        peaks.append(_peak(tmp_path / f"b{b}", N_BLOCK)[0].max())
    assert peaks[1] / peaks[0] == pytest.approx(2.0, abs=0.5), peaks


def test_a_type_multiplier_changes_only_its_type(tmp_path):
    src = _gentle_then_violent(tmp_path / "in", frames=6)
    runs = {}
    for name, kw in (("one", {}), ("spray2", {"spray_multiplier": 2.0}), ("bubbles0", {"bubble_multiplier": 0.0})):
        postprocess(src, out=tmp_path / name, params=_auto(**kw), dt=1 / 30, radius=0.01, show_progress=False)
        runs[name] = [io.read(tmp_path / name / f"diffuse/diffuse_{i:05d}.ply") for i in range(6)]
    first = next(i for i in range(6) if len(runs["one"][i]))

    def of(d, t):
        sel = d.arrays["type"] == t
        return d.positions[sel][np.lexsort(d.positions[sel].T)]

    a, b, c = runs["one"][first], runs["spray2"][first], runs["bubbles0"][first]
    assert (of(a, 0) is not None) and len(of(a, 0)) > 20 and len(of(a, 2)) > 20
    # Twice the spray multiplier: the same foam and bubbles, particle for particle; twice the spray.
    assert np.array_equal(of(a, 1), of(b, 1)) and np.array_equal(of(a, 2), of(b, 2))
    assert len(of(b, 0)) / len(of(a, 0)) == pytest.approx(2.0, rel=0.2)
    # No bubbles: the same spray and foam, no bubbles.
    assert np.array_equal(of(a, 0), of(c, 0)) and np.array_equal(of(a, 1), of(c, 1)) and len(of(c, 2)) == 0


def test_a_capacity_below_the_budget_warns(tmp_path, capsys):
    src = _gentle_then_violent(tmp_path / "in", frames=4)
    postprocess(src, out=tmp_path / "o", params=_auto(budget=2.0, max_particles=1000), dt=1 / 30, radius=0.01,
                show_progress=False)
    err = capsys.readouterr().err
    # Said at the start, from the budget (before any frame saturates), and again when it does.
    assert "foam.budget = 2 asks for about" in err and "beyond foam.max_particles = 1,000" in err, err
