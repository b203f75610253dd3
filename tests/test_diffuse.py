"""Diffuse particles (Ihmsen et al. 2012): physics, determinism, readers and errors."""

from __future__ import annotations

import math
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
from whitecap.diffuse import postprocess
from whitecap.diffuse.params import PRESETS, read_ini, resolve
from whitecap.errors import InputError
from whitecap.io.run import RunInfo
from whitecap.pipeline import simulate

from .conftest import DATA, kill_when, tiny_scene_dict

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


@pytest.mark.parametrize("preset", ["ihmsen2012", "splishsplash", "splishsplash-manual", "dualsphysics", "auto"])
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
    # counts.csv names its columns as the contract does, and counts each type code of the frame.
    assert (foam_run / "diffuse" / "counts.csv").read_text().splitlines()[0] == "frame,time,spray,foam,bubbles"
    row = rows[rows[:, 0] == both[-1]][0]  # the frame read above
    assert row[2:].tolist() == [(d.arrays["type"] == t).sum() for t in (0, 1, 2)]
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
    rising = []  # bubbles' upward velocity relative to the fluid round them, over the frames
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
        sel = np.array([int(k) in old for k in d.ids[t == 2]], bool)
        rel = []
        for p, v in zip(start[sel], d.velocities[t == 2][sel]):
            js = tree.query_ball_point(p, h)
            w = 1 - np.linalg.norm(f.positions[js] - p, axis=1) / h
            rel.append(v[2] - (w @ f.velocities[js][:, 2]) / w.sum() if len(js) else np.nan)
        rising += rel
    assert len(rising) > 10, len(rising)
    assert np.nanmean(rising) > 0.05  # (a bubble that has just left the water has no fluid round it)


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
    for i in range(13):
        d = diffuse(foam_run, i)
        assert (d.arrays["lifetime"][d.arrays["type"] == 1] > -1e-6).all()


def test_short_lived_foam_expires(foam_run, tmp_path):
    """Foam lives 0.05-0.1 s here (1.5-3 frames): foam with at most one frame's countdown left is
    gone the frame after, while longer-lived foam carries on with that much less. The countdown
    is dt, or λ dt (the same for all foam of a frame) where 'auto' ages foam past its share faster."""
    from whitecap.config import Foam

    params = resolve(Foam(**FOAM, lifetime_min=0.05, lifetime_max=0.1))
    out = tmp_path / "short"
    info = postprocess(foam_run, out=out, params=params, show_progress=False)
    dt = 1 / info.frame_rate
    dying = survived = 0
    for i in range(4, 12):
        a, b = diffuse(out, i), diffuse(out, i + 1)
        foam_a = a.arrays["type"] == 1
        assert (a.arrays["lifetime"][foam_a] <= 0.1 + 1e-6).all()
        assert (a.arrays["lifetime"][foam_a] > 0).all()  # none kept at or below zero
        foam_b = {int(k): float(life) for k, life, t in zip(b.ids, b.arrays["lifetime"], b.arrays["type"]) if t == 1}
        drops = [life - foam_b[int(k)] for k, life in zip(a.ids[foam_a], a.arrays["lifetime"][foam_a])
                 if int(k) in foam_b]
        if not drops:
            continue
        step = float(np.median(drops))
        assert step >= dt - 1e-5
        for k, life in zip(a.ids[foam_a], a.arrays["lifetime"][foam_a]):
            if life <= step - 1e-5:  # runs out during the next frame
                dying += 1
                assert int(k) not in foam_b, (i, int(k), life)
            elif int(k) in foam_b:
                survived += 1
                assert foam_b[int(k)] == pytest.approx(life - step, abs=1e-5)
    assert dying > 20 and survived > 20, (dying, survived)


def test_in_simulation_equals_post_processing_byte_for_byte(foam_run, tmp_path):
    out = tmp_path / "post"
    # Post-processing keeps the simulation's running 'auto' estimate when told not to look ahead.
    postprocess(foam_run, out=out, look_ahead=False, show_progress=False)
    for i in range(13):
        name = f"diffuse/diffuse_{i:05d}.ply"
        assert (out / name).read_bytes() == (foam_run / name).read_bytes(), name
    assert (out / "diffuse/counts.csv").read_text() == (foam_run / "diffuse/counts.csv").read_text()
    assert (out / "fluid/fluid_00012.ply").exists()  # a complete run for the next stages


def test_sampled_frames_potentials_kept_from_the_look_ahead_give_the_same_bytes(foam_run, tmp_path, monkeypatch):
    """'auto' post-processing computes the potentials of the frames it samples once: step uses those calibrate
    kept (and builds their grid without lists) instead of computing them again, with the same result."""
    from whitecap.diffuse.generator import FoamGenerator
    from whitecap.sim.grid import NeighborGrid

    builds = []  # per grid build: whether any neighbour list was built for it (all, or the energetic's)
    build, marked, bare = NeighborGrid.build, NeighborGrid.build_marked, NeighborGrid.build_sorted

    def counted(self, x, n, lists=True):
        builds.append(lists)
        return build(self, x, n, lists)

    def counted_bare(self, *a):
        builds.append(False)
        return bare(self, *a)

    def counted_marked(self, *a):
        builds[-1] = True
        return marked(self, *a)

    monkeypatch.setattr(NeighborGrid, "build", counted)
    monkeypatch.setattr(NeighborGrid, "build_sorted", counted_bare)
    monkeypatch.setattr(NeighborGrid, "build_marked", counted_marked)
    postprocess(foam_run, out=tmp_path / "kept", show_progress=False)
    assert builds.count(False) >= 3  # the sampled frames' grids, built again without lists when processed
    calibrate = FoamGenerator.calibrate
    monkeypatch.setattr(FoamGenerator, "calibrate", lambda self, *a, **kw: calibrate(self, *a[:5]))  # nothing kept
    builds.clear()
    postprocess(foam_run, out=tmp_path / "fresh", show_progress=False)
    assert False not in builds
    for i in range(13):
        name = f"diffuse/diffuse_{i:05d}.ply"
        assert (tmp_path / "kept" / name).read_bytes() == (tmp_path / "fresh" / name).read_bytes(), name


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
    s9, t1 = (tmp_path / f"{d}/diffuse/diffuse_00012.ply" for d in ("s9", "t1"))
    assert s9.read_bytes() != t1.read_bytes()


@pytest.mark.parametrize("where", ["copy", "in place"])
def test_a_pass_stopped_half_way_never_lists_an_earlier_pass_s_frames(foam_run, tmp_path, monkeypatch, where):
    """A foam pass remakes every frame from the first: stopped at frame 8, the run lists its frames 0-7 alone,
    not beside frames 8-12 of the earlier pass (another seed here; in place, simulate's own foam), whose files
    and counts.csv are gone; remove_run then leaves no diffuse file behind."""
    from whitecap.io.run import remove_run

    if where == "copy":
        out = tmp_path / "o"
        postprocess(foam_run, out=out, seed=0, show_progress=False)
        run = foam_run
    else:
        out = run = tmp_path / "run"
        shutil.copytree(foam_run, run)
    before = {i: (out / rel).read_bytes() for i, rel in RunInfo.load(out).files("diffuse")}
    assert sorted(before) == list(range(13))
    _stop_foam_at(monkeypatch, 8)
    with pytest.raises(KeyboardInterrupt):
        postprocess(run, out=out, seed=9, show_progress=False)
    listed = dict(RunInfo.load(out).files("diffuse"))
    assert sorted(listed) == list(range(8))
    made = [i for i in listed if len(before[i]) > 400]  # frames with diffuse particles: this pass's own
    assert made and all((out / listed[i]).read_bytes() != before[i] for i in made)
    assert sorted(p.name for p in (out / "diffuse").glob("diffuse_*.ply")) == [f"diffuse_{i:05d}.ply" for i in range(8)]
    rows = np.loadtxt(out / "diffuse" / "counts.csv", delimiter=",", skiprows=1, ndmin=2)
    assert rows[:, 0].tolist() == list(range(8))
    remove_run(out)
    assert not (out / "diffuse").exists()


@pytest.mark.parametrize("lost", [0, 3])
def test_a_stopped_pass_resumes_into_the_same_bytes(foam_run, tmp_path, monkeypatch, capsys, lost):
    """A pass stopped at frame 8 and run again continues from its last complete frame and makes the bytes an
    unstopped pass makes: every diffuse frame, counts.csv, the fluid copies and the frames run.json lists. With
    ``lost``, the last records never reached the disk (a kill -9 between a frame's run.json and its record):
    the frames listed after the last record are made again. Then, with nothing left to do, nothing is written;
    another seed starts over."""
    from whitecap.diffuse import driver
    from whitecap.diffuse.generator import FoamGenerator
    from whitecap.io.run import FOAM_RESUME

    whole, out = tmp_path / "whole", tmp_path / "stopped"
    postprocess(foam_run, out=whole, show_progress=False)
    step, write_arrays = FoamGenerator.step, driver.write_arrays
    made = []

    def stopped(self, fluid, index, dt, **kw):
        if index == 8:
            raise KeyboardInterrupt
        made.append(index)
        return step(self, fluid, index, dt, **kw)

    def record(path, data):
        if int(data["frame"]) < 8 - lost:
            write_arrays(path, data)

    monkeypatch.setattr(FoamGenerator, "step", stopped)
    monkeypatch.setattr(driver, "write_arrays", record)
    with pytest.raises(KeyboardInterrupt):
        postprocess(foam_run, out=out, show_progress=False)
    assert sorted(dict(RunInfo.load(out).files("diffuse"))) == list(range(8))
    monkeypatch.undo()
    monkeypatch.setattr(FoamGenerator, "step", lambda self, fluid, index, dt, **kw: made.append(index) or step(
        self, fluid, index, dt, **kw))
    made.clear()
    capsys.readouterr()
    postprocess(foam_run, out=out, show_progress=False)
    assert made == list(range(8 - lost, 13))
    assert f"resuming at frame {8 - lost}" in capsys.readouterr().err
    a, b = RunInfo.load(whole), RunInfo.load(out)
    assert a.files("diffuse") == b.files("diffuse") and a.files("fluid") == b.files("fluid")
    assert a.extra["foam_pass"] == b.extra["foam_pass"] and b.extra["foam_pass"]["seed"] == a.extra["seed"]
    for rel in [r for _, r in a.files("diffuse") + a.files("fluid")] + ["diffuse/counts.csv"]:
        assert (whole / rel).read_bytes() == (out / rel).read_bytes(), rel
    # Complete: run again, nothing is made or written.
    stamp = {q: q.stat().st_mtime_ns for q in out.rglob("*.*") if q.suffix in (".ply", ".csv", ".npz")}
    listing = (out / "run.json").read_bytes()
    made.clear()
    assert main(["foam", str(foam_run), "--out", str(out)]) == 0
    said = capsys.readouterr()
    assert made == [] and "nothing to do" in said.err and "wrote" not in said.out
    assert {q: q.stat().st_mtime_ns for q in stamp} == stamp and (out / "run.json").read_bytes() == listing
    # A listed frame's file gone: the pass is made again whole, the same bytes.
    (out / "diffuse/diffuse_00003.ply").unlink()
    postprocess(foam_run, out=out, show_progress=False)
    assert made == list(range(13))
    assert (out / "diffuse/diffuse_00003.ply").read_bytes() == (whole / "diffuse/diffuse_00003.ply").read_bytes()
    # Another seed: a pass of its own from the first frame, recorded with its seed.
    made.clear()
    postprocess(foam_run, out=out, seed=5, show_progress=False)
    assert made == list(range(13)) and RunInfo.load(out).extra["foam_pass"]["seed"] == 5
    assert (out / FOAM_RESUME).is_file()


def test_simulate_going_on_after_a_foam_pass_never_lists_frames_of_both(tmp_path, capsys):
    """A run post-processed by `foam` (another seed), then simulated on: with no frame to make, the pass's frames
    stay as they are; with frames to make, simulate's own foam goes on from its checkpoint and the pass's frames
    leave the run (never listed beside simulate's), with a note saying so."""
    d = tiny_scene_dict(output={"frames": 5}, foam=FOAM)
    run = tmp_path / "run"
    simulate(scene_from_dict(d), out=run, show_progress=False)
    assert "diffuse/live_file" in _checkpoint(run)
    postprocess(run, seed=9, show_progress=False)
    # simulate's own diffuse frames left with the pass: the checkpoint now holds the live particles itself
    ck = _checkpoint(run)
    assert "diffuse/live_file" not in ck and len(ck["diffuse/positions"]) == int(ck["diffuse/counts"][-1][2:].sum())
    info = RunInfo.load(run)
    post = {i: (run / rel).read_bytes() for i, rel in info.files("diffuse")}
    assert sorted(post) == list(range(6)) and info.extra["foam_pass"]["seed"] == 9
    simulate(scene_from_dict(d), out=run, resume=True, show_progress=False)  # nothing to make
    info = RunInfo.load(run)
    assert {i: (run / rel).read_bytes() for i, rel in info.files("diffuse")} == post
    assert info.extra["foam_pass"]["seed"] == 9 and (run / "diffuse/resume.npz").is_file()
    capsys.readouterr()
    d["output"]["frames"] = 8
    simulate(scene_from_dict(d), out=run, resume=True, show_progress=False)
    info = RunInfo.load(run)
    assert sorted(dict(info.files("diffuse"))) == [6, 7, 8] and "foam_pass" not in info.extra
    assert sorted(q.name for q in (run / "diffuse").iterdir()) == [
        "counts.csv", "diffuse_00006.ply", "diffuse_00007.ply", "diffuse_00008.ply"]
    assert "the diffuse frames of `whitecap foam` (seed 9) leave the run" in capsys.readouterr().err

    def counted():  # counts.csv's frames, each with the live count its file holds
        rows = [ln.split(",") for ln in (run / "diffuse/counts.csv").read_text().splitlines()[1:]]
        for r in rows:
            assert len(io.read(run / f"diffuse/diffuse_{int(r[0]):05d}.ply")) == sum(map(int, r[2:])), r
        return [int(r[0]) for r in rows]

    assert counted() == [6, 7, 8]  # not simulate's rows of frames 0-5, whose files went with the pass's
    d["output"]["frames"] = 9
    simulate(scene_from_dict(d), out=run, resume=True, show_progress=False)  # resumed again: the same rule
    assert counted() == [6, 7, 8, 9]


def _checkpoint(run: Path) -> dict:
    with np.load(run / "checkpoint.npz") as z:
        return {k: z[k] for k in z.files}


def _stopped_after(frame: int, monkeypatch):
    """simulate's solver raises KeyboardInterrupt (Ctrl-C) when it starts the frame after ``frame``."""
    from whitecap.sim import driver

    build = driver.build_solver

    def stopping(*a, **kw):
        solver = build(*a, **kw)
        advance = solver.advance_frame

        def advance_frame(index, *b, **kb):
            if index > frame:
                raise KeyboardInterrupt
            return advance(index, *b, **kb)

        solver.advance_frame = advance_frame
        return solver

    monkeypatch.setattr(driver, "build_solver", stopping)


def test_a_checkpoint_takes_its_live_particles_from_its_frames_diffuse_file_and_resumes_the_same_bytes(
        tmp_path, monkeypatch):
    """simulate's checkpoint holds the foam's state without the live diffuse particles, and names the frame's
    diffuse file, which holds them exactly, instead; resumed from it, the frames after it are the bytes of the
    uninterrupted run."""
    d = tiny_scene_dict(output={"frames": 9}, foam=FOAM)
    full, part = tmp_path / "full", tmp_path / "part"
    simulate(scene_from_dict(d), out=full, show_progress=False)
    with monkeypatch.context() as m:
        _stopped_after(6, m)
        with pytest.raises(KeyboardInterrupt):
            simulate(scene_from_dict(d), out=part, show_progress=False)
    ck = _checkpoint(part)
    assert int(ck["frame"]) == 6 and str(ck["diffuse/live_file"]) == "diffuse/diffuse_00006.ply"
    assert not {"diffuse/positions", "diffuse/velocities", "diffuse/lifetime", "diffuse/ids"} & ck.keys()
    assert int(ck["diffuse/counts"][-1][2:].sum()) == len(diffuse(part, 6)) > 100  # particles alive to restore
    simulate(scene_from_dict(d), out=part, resume=True, show_progress=False)
    for i in range(7, 10):
        for kind in ("fluid", "diffuse"):
            rel = f"{kind}/{kind}_{i:05d}.ply"
            assert (part / rel).read_bytes() == (full / rel).read_bytes(), rel


@pytest.mark.parametrize("change", ["gone", "other particles", "outside the run"])
def test_a_resume_whose_checkpoints_diffuse_file_is_gone_or_changed_is_one_line_naming_it(tmp_path, capsys, change):
    """The checkpoint's live particles come from the diffuse file it names: where that file is gone or holds
    other particles, `simulate --resume` stops with one line naming it and changes nothing in the run; a
    checkpoint naming a file outside the run is refused with one line naming the checkpoint and its field, the
    file never read."""
    from whitecap.io.lock import LOCK_FILE

    d = tiny_scene_dict(output={"frames": 6}, foam=FOAM)
    run, toml = tmp_path / "run", tmp_path / "s.toml"
    simulate(scene_from_dict(d), out=run, frames=4, show_progress=False)
    assert len(diffuse(run, 4)) != len(diffuse(run, 3))
    toml.write_text(scene_from_dict(d).to_toml())
    f = run / "diffuse" / "diffuse_00004.ply"
    if change == "gone":
        f.unlink()
    elif change == "other particles":
        io.write(f, diffuse(run, 3))  # another frame's particles
    else:  # the checkpoint names a file outside the run (the right particles there): never read
        shutil.copy(f, tmp_path / "elsewhere.ply")
        ck = _checkpoint(run)
        ck["diffuse/live_file"] = np.asarray("../elsewhere.ply")
        np.savez(run / "checkpoint.npz", **ck)
        f = run / "checkpoint.npz"
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and p.name != LOCK_FILE}
    capsys.readouterr()
    code = main(["simulate", str(toml), "--out", str(run), "--resume"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("error")]
    assert code != 0 and len(err) == 1 and err[0].startswith(f"error: {f}: "), err
    assert "start over with `whitecap simulate --force`" in err[0]
    assert change != "outside the run" or "field 'diffuse/live_file': '../elsewhere.ply' is not" in err[0], err
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and p.name != LOCK_FILE} == before


def test_a_profile_totals_the_top_phases_once_whether_named_plainly_or_with_dots():
    """timing.top_level: simulate's phases are plain names (pbf.* and foam.* nested in them); a foam pass's are all
    dotted, and there a phase is top-level unless another is its parent; the writer's thread never counts."""
    from whitecap.timing import top_level

    sim = ["step", "diffuse", "output", "pbf.constraints", "foam.generate", "output.wait", "writer.fluid"]
    assert top_level(sim) == ["step", "diffuse", "output"]
    foam = ["foam.generate", "foam.generate.auto", "foam.generate.classify", "foam.advect", "output.wait",
            "writer.diffuse", "writer.run.json", "foam.look_ahead"]
    assert top_level(foam) == ["foam.generate", "foam.advect", "output.wait", "foam.look_ahead"]


def test_foam_profile_prints_the_passs_phases_whose_top_level_shares_make_the_whole(foam_run, tmp_path, capsys):
    """`whitecap foam --profile`: the pass's named phases, each once; the top-level ones (set-up, look-ahead, the
    frames' steps, the waits for the writer) add up to 100 % of their total, the nested and the writer's thread
    beside them."""
    capsys.readouterr()
    assert main(["foam", str(foam_run), "--out", str(tmp_path / "p"), "--seed", "4", "--profile"]) == 0
    out = capsys.readouterr().out
    rows = {ln.split()[0]: float(ln.split()[-1].rstrip("%")) for ln in out[out.index("foam profile:"):].splitlines()[2:]
            if ln.strip().endswith("%")}
    top = {"foam.setup", "foam.look_ahead", "foam.read", "foam.potentials", "foam.advect",
           "foam.generate", "foam.compact", "foam.say", "foam.records"}
    assert top <= rows.keys() and {"foam.generate.counts", "writer.diffuse"} <= rows.keys(), sorted(rows)
    assert sum(v for k, v in rows.items() if k in top or k == "output.wait") == pytest.approx(100, abs=0.5)


def test_simulate_hands_the_foam_its_frame_on_the_device_the_same_bytes(foam_run, tmp_path, monkeypatch):
    """Inside simulate the foam stage copies the solver's arrays on the device (K.copy_fluid) instead of uploading
    the frame it was handed: the same particles in the same order, so the same diffuse bytes as the upload."""
    from whitecap.diffuse import driver, kernels as K

    used = []  # per frame: whether the fluid came from host arrays
    real = K.copy_fluid
    monkeypatch.setattr(K, "copy_fluid", lambda *a: used.append(isinstance(a[1], np.ndarray)) or real(*a))
    again = tmp_path / "again"
    simulate(scene_from_dict(tiny_scene_dict(output={"frames": 12}, foam=FOAM)), out=again, show_progress=False)
    assert used == [False] * 13
    start = driver.FoamStage.start

    def host_only(self, info, solver=None):
        start(self, info, solver)
        self.gen.fluid_on_device = None

    monkeypatch.setattr(driver.FoamStage, "start", host_only)
    used.clear()
    uploaded = tmp_path / "uploaded"
    simulate(scene_from_dict(tiny_scene_dict(output={"frames": 12}, foam=FOAM)), out=uploaded, show_progress=False)
    assert used == [True] * 13
    made = 0
    for i, rel in RunInfo.load(again).files("diffuse"):
        a, b = (again / rel).read_bytes(), (uploaded / rel).read_bytes()
        assert a == b == (foam_run / rel).read_bytes(), rel
        made += len(a) > 400
    assert made >= 6


KILLED_MID_FILE = """
import sys, time
sys.path.insert(0, sys.argv[1])
import whitecap.diffuse.driver as driver
from whitecap.io.atomic import atomic_path
from whitecap.io.run import RunInfo
real = driver.write

def write(path, frame):
    if path.name == "diffuse_00006.ply":  # half a file in its temporary name, then wait for SIGKILL
        with atomic_path(path) as tmp:
            tmp.write_bytes(b"ply\\nformat binary_little_endian 1.0\\n")
            # frame 5's run.json does not wait for frame 6's file: killed once it is written (or after 30 s)
            for _ in range(3000):
                if 5 in dict(RunInfo.load(path.parents[1]).files("diffuse")):
                    break
                time.sleep(0.01)
            open(sys.argv[4], "w").close()
            time.sleep(600)
    return real(path, frame)

driver.write = write
driver.postprocess(sys.argv[2], out=sys.argv[3], show_progress=False)
"""


def test_a_pass_killed_while_writing_a_frame_resumes_into_the_same_bytes(foam_run, tmp_path):
    """kill -9 while frame 6's diffuse file is half-written, frame 5 listed (the writer lists it meanwhile): the
    pass run again sweeps the temporary file, continues after frame 5 and makes the bytes of a pass never
    stopped."""
    whole, out, sig = tmp_path / "whole", tmp_path / "killed", tmp_path / "writing"
    postprocess(foam_run, out=whole, show_progress=False)
    src = Path(__file__).resolve().parents[1] / "src"
    child = subprocess.Popen([sys.executable, "-c", KILLED_MID_FILE, str(src), str(foam_run), str(out), str(sig)],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             env={**os.environ, "WHITECAP_PROGRESS": "0"})
    kill_when(child, sig, "frame 6's write")
    assert list((out / "diffuse").glob(".diffuse_00006.*.tmp.ply"))
    assert sorted(dict(RunInfo.load(out).files("diffuse"))) == list(range(6))
    postprocess(foam_run, out=out, show_progress=False)
    names = sorted(q.relative_to(whole) for q in whole.rglob("*") if q.is_file() and q.name != ".whitecap.lock")
    assert sorted(q.relative_to(out) for q in out.rglob("*") if q.is_file() and q.name != ".whitecap.lock") == names
    assert [n for n in names if (whole / n).read_bytes() != (out / n).read_bytes()] == []


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
    s = resolve(preset="splishsplash-manual")  # FoamGenerator's --no-auto numbers
    assert (s.vo_min, s.vo_max, s.k_ta, s.k_wc, s.k_vo, s.lifetime_min, s.lifetime_max, s.buoyancy, s.drag,
            s.spray_below, s.bubble_above, s.model) == (5, 20, 4000, 50000, 4000, 2, 5, 2.0, 0.8, 6, 20, "ihmsen2012")
    a = resolve(preset="splishsplash")  # FoamGenerator's default: automatic mode, factors 1 x foamscale 1000
    assert (a.model, a.k_ta, a.k_wc, a.k_vo, a.lifetime_min, a.lifetime_max, a.spray_below, a.bubble_above) == (
        "foamgenerator", 1000, 1000, 0, 2, 5, 6, 20)
    assert set(PRESETS) >= {"ihmsen2012", "dualsphysics", "splishsplash", "splishsplash-manual", "auto"}
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
    # The run's own domain: guessed from the first frame (the water column), it would drop the
    # diffuse particles of the flow that has left it, where 'auto' finds the violence.
    common = dict(dt=1.0 / info.frame_rate, radius=info.particle_radius, preset="auto", show_progress=False,
                  domain=(info.domain["lower"], info.domain["upper"]))
    postprocess(tmp_path / "partio", out=tmp_path / "a", up="y", **common)
    postprocess(foam_run / "fluid", out=tmp_path / "b", **common)
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
    lists = (g.nb_count, g.nb, g.pad, g.max_neighbors)
    mark = ti.ndarray(ti.i32, n)
    K.mark_energetic(n, fv, -math.inf, e_k, mark, normal, surface, v_diff, vort, crest)  # every particle marked
    K.fluid_potentials(n, fx, fv, *lists, gen.h, SURFACE_FRACTION, normal, surface, v_diff, e_k, vort, mark,
                       K.ENERGETIC)
    K.wave_crest(n, fx, fv, *lists, normal, surface, gen.h, crest, mark, K.ENERGETIC)
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

    from .diffuse_reference import generate

    runtime.init(runtime.current() or "cpu")
    n = len(v_diff)
    zeros = np.zeros(n, np.float32)
    x = _nd(np.zeros((n, 3), np.float32), ti.f32, True)
    v = _nd(np.tile([[0.0, 0.0, 2.0]], (n, 1)).astype(np.float32), ti.f32, True)
    tau = _nd(np.array([*ta_range, 1, 2, 0, 1e-3, 1, 2], np.float32), ti.f32)
    ids = _nd(np.arange(n, dtype=np.uint32), ti.u32)
    ek = _nd(np.ones(n, np.float32), ti.f32)  # above ke_max: I_k = 1
    cnt, rate = ti.ndarray(ti.i32, n), ti.ndarray(ti.f32, n)
    K.birth_counts(n, ids, _nd(np.asarray(v_diff, np.float32), ti.f32), _nd(zeros, ti.f32), ek, _nd(zeros, ti.f32),
                   tau, k_ta, 0.0, 0.0, dt, 7, 3, 0, cnt, rate, 0)
    counts = cnt.to_numpy()
    total = int(counts.sum())
    offset = _nd(np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32), ti.i32)
    m = max(total, 1)
    ox, ov, ol = ti.Vector.ndarray(3, ti.f32, m), ti.Vector.ndarray(3, ti.f32, m), ti.ndarray(ti.f32, m)
    generate(n, x, v, ids, ek, tau, cnt, offset, 1.0, 2.0, 0.0, r, dt, 7, 3, ox, ov, ol)
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


def _stop_foam_at(monkeypatch, index: int) -> None:
    """Every foam pass from here on stops (as by Ctrl-C) when it reaches frame ``index``."""
    from whitecap.diffuse.generator import FoamGenerator

    step = FoamGenerator.step

    def stopped(self, fluid, i, dt, **kw):
        if i == index:
            raise KeyboardInterrupt
        return step(self, fluid, i, dt, **kw)

    monkeypatch.setattr(FoamGenerator, "step", stopped)


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
    # The count follows the violence: the gentle frame makes a sliver of what a violent one makes,
    # and whitewater builds up over the violent frames rather than saturating at once (thresholds
    # from the gentle frame would clamp every violent particle to φ = 1 from frame 2 on).
    born = np.diff(rows[:, 2:].sum(1), prepend=0)
    assert born[1] < 0.05 * born[2:].max(), born[:4]
    assert ratio[2] < 0.25 * ratio.max(), ratio[:6]
    # In the simulation (no look-ahead) the running estimate also keeps within the budget.
    postprocess(src, out=tmp_path / "s", params=_auto(budget=2.0), dt=1 / 30, radius=0.01, show_progress=False,
                look_ahead=False)
    err = capsys.readouterr().err
    ratio_s, _ = _peak(tmp_path / "s", N_BLOCK)
    assert 0.3 <= ratio_s.max() <= 3.0, ratio_s.max()
    assert "saturated" not in err, err


def test_the_budget_scales_the_count(tmp_path):
    src = _gentle_then_violent(tmp_path / "in")
    curves = []
    for b in (1.0, 2.0):
        postprocess(src, out=tmp_path / f"b{b}", params=_auto(budget=b), dt=1 / 30, radius=0.01, show_progress=False)
        curves.append(_peak(tmp_path / f"b{b}", N_BLOCK)[0])
    one, two = curves
    assert two.max() / one.max() == pytest.approx(2.0, abs=0.5), (one.max(), two.max())
    # Scaled all along, not clipped at the top: halfway up as well.
    k = int(np.argmax(two >= 0.5 * two.max()))
    assert two[k] / one[k] == pytest.approx(2.0, abs=0.5), (k, one[k], two[k])


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


# ------------------------------------------------------------------ SPlisHSPlasH FoamGenerator's automatic mode
def _block_frame(scale: float, r: float = 0.01, n: int = 8):
    """A (slightly jittered) lattice block of water with a sheared, rising velocity field, scaled by ``scale``."""
    x = _lattice(n, r) + np.random.default_rng(7).uniform(-0.05 * r, 0.05 * r, (n**3, 3)).astype(np.float32)
    z = (x[:, 2] - x[:, 2].min()) / (2 * r * (n - 1))
    v = np.stack([1.5 * z, 0.3 * np.sin(9 * x[:, 0]), 0.8 * z * z], axis=1).astype(np.float32) * scale
    return io.ParticleFrame(positions=x, velocities=v, ids=np.arange(len(x), dtype=np.uint32))


def _fg_reference(gen, frame):
    """FoamGenerator's formulas in NumPy, on whitecap's neighbour lists (main.cpp: computeDensities,
    computeNormals, determineValues): cubic spline of support h, m = 0.8 (2r)³ 1000; the k-th
    neighbour term of the trapped-air and crest sums weighted by m/ρ of row k of the frame,
    which over the arbitrary order of a neighbour list is the mean over the first N rows."""
    from whitecap.diffuse import splishsplash as SP

    n = len(frame)
    gen._prepare(frame, n)
    cnt = gen.grid.nb_count.to_numpy()[:n]
    nb = gen.grid.nb.to_numpy()[:n]
    x, v, h, m = frame.positions.astype(np.float64), frame.velocities.astype(np.float64), gen.h, SP.particle_mass(gen.r)

    def W(d):
        q = np.linalg.norm(d, axis=-1) / h
        s = 8 / (np.pi * h**3)
        return np.where(q <= 0.5, s * (6 * q**3 - 6 * q**2 + 1), np.where(q <= 1, s * 2 * (1 - q) ** 3, 0.0))

    def gradW(d):
        r_ = np.linalg.norm(d, axis=-1, keepdims=True)
        q = r_ / h
        dq = np.where(q <= 0.5, q * (3 * q - 2), -((1 - q) ** 2))
        return np.where((q <= 1) & (r_ > 0), 48 / (np.pi * h**3) * dq * d / np.maximum(r_ * h, 1e-30), 0.0)

    rho = np.array([m * W(np.zeros(3)) + m * W(x[i] - x[nb[i, : cnt[i]]]).sum() for i in range(n)])
    nrm = np.zeros((n, 3))
    for i in range(n):
        if cnt[i] <= 20:
            j = nb[i, : cnt[i]]
            g = -(m / rho[j, None] * gradW(x[i] - x[j])).sum(0)
            nrm[i] = g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else 0
    vd, kap = np.zeros(n), np.zeros(n)
    for i in range(n):
        j = nb[i, : cnt[i]]
        vol = (m / rho[: cnt[i]]).mean()  # FoamGenerator's loop weights its k-th term by row k's volume
        xij = x[i] - x[j]
        xh = xij / np.linalg.norm(xij, axis=1, keepdims=True)
        vij = v[i] - v[j]
        vl = np.linalg.norm(vij, axis=1)
        vh = np.where(vl[:, None] > 1e-6, vij / np.maximum(vl, 1e-30)[:, None], vij)
        vd[i] = (vol * vl * (1 - (vh * xh).sum(1)) * W(xij)).sum()
        behind = (xh @ nrm[i]) > 0
        kap[i] = (vol * (1 - nrm[j] @ nrm[i]) * W(xij))[behind].sum()
        sl = np.linalg.norm(v[i])
        if sl == 0 or v[i] @ nrm[i] / sl < 0.6:
            kap[i] = 0
    return vd, kap, 0.5 * m * (v**2).sum(1), cnt


def _fg_generator(r=0.01):
    from whitecap.diffuse.generator import FoamGenerator

    p = resolve(preset="splishsplash")
    from dataclasses import replace

    return FoamGenerator(replace(p, slots_per_particle=64), r, ([-1, -1, -1], [2, 2, 2]), (0, 0, -9.81), seed=3)


def test_foamgenerator_potentials_follow_its_formulas():
    # The cubic-spline potentials of FoamGenerator (SPH volumes, normals only for <= 20 neighbours,
    # crest only when moving along the normal, energy 1/2 m v^2 in joules) against a NumPy transcription.
    from whitecap.diffuse import splishsplash as SP

    gen, fr = _fg_generator(), _block_frame(1.0)
    vd, kap, e, cnt = _fg_reference(gen, fr)
    n = len(fr)
    fx, fv, _, _ = gen._prepare(fr, n)
    got = [a.to_numpy()[:n] for a in SP.frame_potentials(gen, fx, fv, n)]
    assert (kap > 0).sum() > 10 and (cnt > 20).sum() > 10  # crests exist and interior particles have no normal
    for ours, ref in zip(got, (vd, kap, e)):
        np.testing.assert_allclose(ours, ref, rtol=2e-4, atol=1e-6 * ref.max())


def test_splishsplash_box_counts_foam_near_the_domain_faces_up_as_foamgenerator_does():
    # FoamGenerator given a box (--bbsize) raises a foam particle's fluid-neighbour count N by
    # ceil(N pi a^2 (3 - a) / 3), a = 1 - d/h, per box face within h (faces x, y, z; lower, then upper;
    # stopping above 20) and calls it a bubble above 20. 'splishsplash-box' does; 'splishsplash'
    # (FoamGenerator's default, no box) does not, and neither changes anything far from the faces.
    import math

    import taichi as ti

    from whitecap.diffuse import kernels as K
    from whitecap.diffuse.generator import FoamGenerator, _nd

    r = 0.01
    fr = _block_frame(1.0, r)
    x = fr.positions.astype(np.float64)
    lo = x.min(0) - [0.5 * r, 1.0, 1.0]  # only the lower x face is near the block
    hi = x.max(0) + 1.0
    top = x[:, 2].max()
    g1 = np.linspace(x[:, 0].min(), x[:, 0].max(), 12)
    px, py, pz = np.meshgrid(g1, g1[:6], top + r * np.array([0.8, 1.2, 1.6, 2.0]), indexing="ij")
    pts = np.stack([px.ravel(), py.ravel(), pz.ravel()], 1).astype(np.float32)
    kinds = {}
    for preset in ("splishsplash", "splishsplash-box"):
        p = resolve(preset=preset)
        gen = FoamGenerator(p, r, (lo, hi), (0, 0, -9.81), seed=3)
        *_, args = gen._prepare(fr, len(fr))
        kd = ti.ndarray(ti.i32, len(pts))
        K.classify(len(pts), _nd(pts, ti.f32, True), *args, p.spray_below, p.bubble_above, ti.math.vec3(*lo),
                   ti.math.vec3(*hi), int(p.wall_correction), kd)
        kinds[preset] = kd.to_numpy()
    h = 4 * r
    n = (np.linalg.norm(pts[:, None, :] - x[None], axis=2) < h).sum(1)

    def fg_type(q, c):  # main.cpp, advectFoamParticles: the correction for particles typed as foam
        if c < 6:
            return 0
        if c > 20:
            return 2
        for j in range(3):
            for face in (lo[j], hi[j]):
                d = abs(q[j] - face)
                if d < h:
                    a = 1 - d / h
                    c += math.ceil(c * a * a * math.pi / 3 * (3 - a))
            if c > 20:
                return 2
        return 1

    want_box = np.array([fg_type(q, c) for q, c in zip(pts.astype(np.float64), n)])
    want_plain = np.where(n < 6, 0, np.where(n > 20, 2, 1))
    assert (kinds["splishsplash"] == want_plain).mean() > 0.97  # float32 distances at the support's edge
    assert (kinds["splishsplash-box"] == want_box).mean() > 0.97
    near = pts[:, 0] - lo[0] < h
    turned = (kinds["splishsplash"] == 1) & (kinds["splishsplash-box"] == 2)
    assert turned[near].sum() >= 5 and not turned[~near].any()
    assert (kinds["splishsplash"][~near] == kinds["splishsplash-box"][~near]).all()


def test_foamgenerator_limits_are_the_mean_of_per_frame_maxima_over_the_whole_sequence(tmp_path):
    # Three frames of one flow at speeds 1, 2, 3: the energy maxima scale as 1, 4, 9 and the trapped-air
    # maxima as 1, 2, 3, so FoamGenerator's limits are tau_max = 14/3 and 2 times the first frame's,
    # tau_min = 0.1 tau_max -- not the first frame's (a gentle start is not the scale).
    from whitecap.diffuse import splishsplash as SP

    gen = _fg_generator()
    first = SP.frame_maxima(gen, _block_frame(1.0))
    for k in (1, 2, 3):
        f = _block_frame(float(k))
        io.write(tmp_path / "seq" / f"frame_{k:04d}.ply", f)
    info = postprocess(tmp_path / "seq", out=tmp_path / "o", preset="splishsplash", dt=0.02, radius=0.01,
                       show_progress=False)
    tau = np.asarray(info.extra["foam_limits"], np.float64)
    assert RunInfo.load(tmp_path / "o").extra["foam_limits"] == info.extra["foam_limits"]  # recorded in run.json
    np.testing.assert_allclose(tau[[1, 5]], [2 * first[0], 14 / 3 * first[2]], rtol=1e-4)
    np.testing.assert_allclose(tau[[0, 2, 4]], 0.1 * tau[[1, 3, 5]], rtol=1e-6)
    assert tau[3] > 0


def test_foamgenerator_limits_on_a_sequence_without_crests_or_motion_stay_finite_and_generate_nothing():
    # A potential that is 0 in every frame gives limits with I = 0 (FoamGenerator would divide 0 by 0),
    # and the energy limit never falls below 1/2 m (1 m/s)^2, so a resting tank's jitter is not foam.
    from whitecap.diffuse import splishsplash as SP

    tau = SP.limits_from_maxima(np.array([[0.2, 0.0, 1e-7], [0.4, 0.0, 3e-7]]), 0.01).astype(np.float64)
    assert np.isfinite(tau).all() and tau[1] == pytest.approx(0.3) and tau[0] == pytest.approx(0.03)
    assert tau[5] == pytest.approx(0.5 * SP.particle_mass(0.01) * SP.ENTRAINMENT_SPEED**2)
    assert tau[3] > tau[2] >= 0 and (min(0.0, tau[3]) - min(0.0, tau[2])) / (tau[3] - tau[2]) == 0.0


def test_foamgenerator_generates_its_rounded_count_with_its_lifetimes():
    # n_d = floor(foamscale I_k (I_ta + I_wc) dt + 1/2) per fluid particle with >= 15 neighbours, and
    # lifetime l_min + I_k / tau_max_k X (l_max - l_min): FoamGenerator's generation, particle for particle.
    gen, fr, dt = _fg_generator(), _block_frame(2.0), 0.02
    vd, kap, e, cnt = _fg_reference(gen, fr)
    tau = np.array([0.1 * vd.max(), vd.max(), 0.1 * kap.max(), kap.max(), 0.1 * e.max(), e.max(), 1, 2], np.float32)
    gen.state.tau = tau

    def phi(i, lo, hi):
        return (np.minimum(i, hi) - np.minimum(i, lo)) / (hi - lo)

    t = tau.astype(np.float64)
    i_k = phi(e, t[4], t[5])
    nd = np.floor(1000.0 * i_k * (phi(vd, t[0], t[1]) + phi(kap, t[2], t[3])) * dt + 0.5) * (cnt >= 15)
    out = gen.step(fr, 0, dt)
    assert nd.sum() > 100 and (cnt < 15).any() and len(out) == int(nd.sum())
    # New particles come in fluid order, nd[i] each: X = (life - l_min) / ((I_k / tau_max_k)(l_max - l_min))
    # must be uniform in [0, 1); the energy limit is in joules, so small particles' foam outlives l_max.
    src = np.repeat(np.arange(len(fr)), nd.astype(int))
    x01 = (out.arrays["lifetime"] - 2.0) / (3.0 * i_k[src] / t[5])
    assert x01.min() >= -1e-5 and x01.max() < 1 + 1e-5 and abs(x01.mean() - 0.5) < 0.05
    assert out.arrays["lifetime"].max() > 5.0




@pytest.mark.parametrize("preset,keeps", [("splishsplash", True), ("ihmsen2012", False)])
def test_foam_moves_with_the_fluid_and_keeps_its_own_velocity_only_as_foamgenerator_does(preset, keeps):
    # A foam particle on a block of fluid moving at u: it moves by u dt in both models; its own
    # velocity becomes u in whitecap's, and stays what it was in FoamGenerator's (so foam that turns
    # into spray leaves with it).
    from dataclasses import replace

    from whitecap.diffuse.generator import DiffuseState, FoamGenerator

    u, dt, r = np.array([0.3, 0.0, 0.1], np.float32), 0.02, 0.01
    x = _lattice(10, r)
    fr = io.ParticleFrame(positions=x, velocities=np.tile(u, (len(x), 1)), ids=np.arange(len(x), dtype=np.uint32))
    p = replace(resolve(preset=preset), ta_min=1e3, ta_max=2e3, wc_min=1e3, wc_max=2e3)  # no generation
    gen = FoamGenerator(p, r, ([-1, -1, -1], [2, 2, 2]), (0, 0, -9.81), seed=1)
    gen.state = DiffuseState.empty()
    gen.state.tau = np.array([1e3, 2e3, 1e3, 2e3, 1e3, 2e3, 1e3, 2e3], np.float32) if keeps else None
    x0 = np.array([[0.205, 0.205, x[:, 2].max() + r]], np.float32)  # at the surface: 6 to 20 fluid neighbours
    v0 = np.array([[0.0, 0.0, 1.5]], np.float32)
    gen.state.positions, gen.state.velocities, gen.state.lifetime = x0, v0, np.array([3.0], np.float32)
    gen.state.ids = np.array([0], np.uint32)
    out = gen.step(fr, 1, dt)
    assert len(out) == 1 and out.arrays["type"][0] == 1  # still foam
    np.testing.assert_allclose(out.positions[0], x0[0] + dt * u, atol=1e-6)
    np.testing.assert_allclose(out.velocities[0], v0[0] if keeps else u, atol=1e-6)


def test_foamgenerator_mode_needs_the_whole_sequence_so_the_simulation_refuses_it(tmp_path, capsys):
    d = tiny_scene_dict(output={"frames": 2}, foam={"preset": "splishsplash"})
    with pytest.raises(InputError, match="whitecap foam RUN --preset splishsplash"):
        simulate(scene_from_dict(d), out=tmp_path, show_progress=False)


# ------------------------------------------------------------------ the DualSPHysics user's .ini (VisualSPHysics)
EXAMPLE_INI = """[TIMESTEPS]
StartingTimeStep = 200
EndingTimeStep = 550

[FOAMPARAMETERS]
MinTrappedAirThreshold = 5.
MaxTrappedAirThreshold = 20.
MinWaveCrestsThreshold = 2.
MaxWaveCrestsThreshold = 8.
MinKineticEnergyThreshold = 5.0
MaxKineticPowerThreshold = 50.0
DiffuseTrappedAirMultiplier = 40.0
DiffuseWaveCrestsMultiplier = 40.0
"""


def full_ini(inp: str = "parts", out: str = "foamout", xml: str = "case/Case.xml", custom: str = "yes",
             first: int = 12, last: int = 14, **foam) -> str:
    """Every key of the VisualSPHysics foam simulator's file."""
    fp = dict(MinTrappedAirThreshold=0.5, MaxTrappedAirThreshold=4.0, MinWaveCrestsThreshold=0.3,
              MaxWaveCrestsThreshold=3.0, MinKineticEnergyThreshold=0.0008, MaxKineticEnergyThreshold=0.016,
              DiffuseTrappedAirMultiplier=400.0, DiffuseWaveCrestsMultiplier=300.0, SprayDensity=5,
              BubblesDensity=18, LifefimeMultiplier=12, BuoyancyControl=0.7, DragControl=0.4)
    fp.update(foam)
    return (
        f"[PATHS]\nInputDataPath = {inp}\nInputFilesPrefix = PartFluid_\nZeroPadding = 4\nOutputDataPath = {out}\n"
        f"FilesOutputPrefix = Diffuse_\n# no exclusion zone\nExclusionZoneFile =\nXmlFile = {xml}\n\n"
        "[OUTPUT]\nTextFiles = no\nPlyFiles = no\nVtkFiles = yes\nVtkDiffuseData = no\nVtkFluidData = no\n\n"
        f"[TIMESTEPS]\nStartingTimeStep = {first}\nEndingTimeStep = {last}\n\n[FOAMPARAMETERS]\n"
        + "".join(f"{k} = {v}\n" for k, v in fp.items())
        + f"\n[DOMAIN]\nCustomDomain = {custom}\nDomainMinx = 0.0\nDomainMiny = 0.0\nDomainMinz = 0.0\n"
        "DomainMaxx = 0.4\nDomainMaxy = 0.7\nDomainMaxz = 0.5\n"
    )


def test_the_dualsphysics_example_ini_parses_to_its_parameters(tmp_path, capsys):
    ini = tmp_path / "example.ini"
    ini.write_text(EXAMPLE_INI)
    f = read_ini(ini)
    assert capsys.readouterr().err == ""  # every key understood
    assert f.job.first == 200 and f.job.last == 550 and f.job.input_dir is None
    m = 0.008  # kg, massfluid of the case: the energy thresholds are 1/2 m v^2 of one particle
    p = resolve(ini=ini, preset="dualsphysics", particle_mass=m)
    assert (p.ta_min, p.ta_max, p.wc_min, p.wc_max, p.k_ta, p.k_wc) == (5, 20, 2, 8, 40, 40)
    assert p.ke_min == pytest.approx(5.0 / m) and p.ke_max == pytest.approx(50.0 / m)
    with pytest.raises(InputError, match=r"MinKineticEnergyThreshold.*particle mass is unknown"):
        resolve(ini=ini)


def test_a_full_visualsphysics_ini_parses_to_every_parameter_and_the_job(tmp_path, capsys):
    ini = tmp_path / "cfg" / "full.ini"
    ini.parent.mkdir()
    ini.write_text(full_ini() + "Colour = blue\n[EXTRA]\nWind = 3\n")
    f = read_ini(ini)
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "[DOMAIN] Colour" in err and "[EXTRA] Wind" in err  # one warning line
    assert f.unknown == ("[DOMAIN] Colour", "[EXTRA] Wind")
    p = resolve(ini=f, particle_mass=0.002)
    assert (p.ta_min, p.ta_max, p.wc_min, p.wc_max, p.k_ta, p.k_wc) == (0.5, 4.0, 0.3, 3.0, 400, 300)
    assert (p.spray_below, p.bubble_above, p.lifetime_multiplier, p.buoyancy, p.drag) == (5, 18, 12, 0.7, 0.4)
    assert (p.ke_min, p.ke_max) == (pytest.approx(0.4), pytest.approx(8.0))
    j = f.job
    assert (j.input_dir, j.out, j.xml) == (ini.parent / "parts", ini.parent / "foamout", ini.parent / "case/Case.xml")
    assert (j.prefix, j.zero_padding, j.first, j.last, j.out_prefix, j.exclusion_zone) == (
        "PartFluid_", 4, 12, 14, "Diffuse_", "")
    assert j.domain == ([0, 0, 0], [0.4, 0.7, 0.5]) and j.outputs == ("VtkFiles",)
    assert j.frame_path(7).name == "PartFluid_0007.vtk"


@pytest.mark.parametrize("section,key,bad,message", [
    ("FOAMPARAMETERS", "SprayDensity", "six", "expected a number"),
    ("FOAMPARAMETERS", "DragControl", "-1", "expected a finite number >= 0"),
    ("PATHS", "ZeroPadding", "four", "expected a whole number"),
    ("TIMESTEPS", "EndingTimeStep", "3", "before StartingTimeStep"),
    ("DOMAIN", "DomainMaxx", "-1", "must be greater than DomainMinx"),
    ("DOMAIN", "CustomDomain", "perhaps", "expected yes or no"),
    ("PATHS", "ExclusionZoneFile", "zone.vtk", "exclusion zones are not supported"),
    ("PATHS", "InputDataPath", "nowhere", "no such directory"),
])
def test_bad_ini_values_are_one_line_errors_naming_file_section_and_key(tmp_path, capsys, section, key, bad, message):
    import re

    ini = tmp_path / "bad.ini"
    text = full_ini(inp=str(DATA / "dualsphysics"), xml=str(DATA / "dualsphysics" / "CaseDambreak.xml"))
    text, n = re.subn(rf"(?m)^{key} =.*$", f"{key} = {bad}", text)
    assert n == 1
    ini.write_text(text)
    assert main(["foam", "--params", str(ini)]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(ini) in err and f"[{section}] {key}" in err and message in err, err


def test_one_command_runs_the_job_the_ini_describes(tmp_path, capsys):
    # `whitecap foam --params FILE` alone: frames 13..14 of the PartFluid sequence, the case XML,
    # the output folder (relative to the file) and a custom domain that cuts the tank at x = 0.4 m.
    ini = tmp_path / "job" / "foam.ini"
    ini.parent.mkdir()
    ini.write_text(full_ini(inp=str(DATA / "dualsphysics"), out="../result",
                            xml=str(DATA / "dualsphysics" / "CaseDambreak.xml"), first=13, last=14))
    assert main(["foam", "--params", str(ini)]) == 0
    out = tmp_path / "result"
    assert str(out) in capsys.readouterr().err
    info = RunInfo.load(out)
    assert [i for i, _ in info.files("diffuse")] == [13, 14] and [i for i, _ in info.files("fluid")] == [13, 14]
    assert info.extra["case"].endswith("CaseDambreak.xml") and info.particle_radius == pytest.approx(0.01)
    assert info.domain == {"lower": [0, 0, 0], "upper": [0.4, 0.7, 0.5]}
    made = 0
    for i in (13, 14):
        d = io.read(out / f"diffuse/diffuse_{i:05d}.ply")
        made += len(d)
        assert (d.positions <= [0.4, 0.7, 0.5]).all() and (d.positions >= 0).all()
    fluid = io.read(out / "fluid/fluid_00014.ply")
    assert made > 0 and (fluid.positions[:, 0] > 0.45).any()  # the fluid reaches past the box; its foam does not


def test_an_ending_time_step_past_the_last_file_stops_there_and_says_so(tmp_path, capsys):
    # Like the VisualSPHysics simulator the run ends at the first missing frame, but not silently.
    ini = tmp_path / "foam.ini"
    ini.write_text(full_ini(inp=str(DATA / "dualsphysics"), out="o",
                            xml=str(DATA / "dualsphysics" / "CaseDambreak.xml"), custom="no", first=13, last=40))
    assert main(["foam", "--params", str(ini)]) == 0
    err = capsys.readouterr().err
    warn = [ln for ln in err.splitlines() if "EndingTimeStep" in ln]
    assert len(warn) == 1 and "PartFluid_0015.vtk" in warn[0] and "13..14" in warn[0]
    info = RunInfo.load(tmp_path / "o")
    assert [i for i, _ in info.files("diffuse")] == [13, 14]
    assert info.domain["upper"] != [0.4, 0.7, 0.5]  # CustomDomain = no: the case XML's domain


@pytest.mark.parametrize("shares", [None, [1.0, 3.0, 1.0]])
def test_each_type_peaks_at_its_share_of_the_budget(tmp_path, shares):
    """The budget splits into spray, foam and bubbles by ``shares`` (even by default): each
    type's own peak lands on budget × its share ±50 %, in post-processing and, for the
    default split, in the simulation's running estimate. Unscaled, this flow splits about
    0.6 : 1.1 : 1.0, so 1 : 3 : 1 would put bubbles 60 % over their share."""
    src = _gentle_then_violent(tmp_path / "in")
    kw = {} if shares is None else {"shares": shares}
    want = 3.0 * np.asarray(shares or [1, 1, 1]) / sum(shares or [1, 1, 1])
    modes = (True, False) if shares is None else (True,)
    for ahead in modes:
        out = tmp_path / f"o{ahead}"
        postprocess(src, out=out, params=_auto(budget=3.0, **kw), dt=1 / 30, radius=0.01, show_progress=False,
                    look_ahead=ahead)
        _, rows = _peak(out, N_BLOCK)
        got = rows[:, 2:].max(0) / N_BLOCK
        assert np.all(np.abs(got / want - 1) <= 0.5), (ahead, got, want)


def test_numpy_draws_equal_the_kernel_draws_bit_for_bit():
    """The per-type thinning and foam dissipation draw on the host (generator.uniform) what
    the kernels draw on the device (kernels.rand01); a drift between the two copies would
    silently decorrelate them, so they are compared bit for bit."""
    import taichi as ti

    from whitecap.diffuse import kernels as K
    from whitecap.diffuse.generator import uniform
    from whitecap.sim import runtime

    runtime.init("cpu")
    n = 4096
    rng = np.random.default_rng(7)
    pid = rng.integers(0, 2**32, n, dtype=np.uint32)
    slot = rng.integers(0, 2**20, n, dtype=np.uint32)
    seed, frame, draw = 0xDEADBEEF, 123456, 5
    out = ti.ndarray(ti.f32, n)
    pid_nd, slot_nd = ti.ndarray(ti.u32, n), ti.ndarray(ti.u32, n)
    pid_nd.from_numpy(pid)
    slot_nd.from_numpy(slot)

    def draws(pid, slot, out):
        for i in range(n):
            out[i] = K.rand01(ti.u32(seed), ti.u32(frame), pid[i], slot[i], ti.u32(draw))

    # annotations as objects (this module's `from __future__ import annotations` makes them strings)
    draws.__annotations__ = {k: ti.types.ndarray() for k in ("pid", "slot", "out")}
    draws = ti.kernel(draws)
    draws(pid_nd, slot_nd, out)
    host = uniform(seed, frame, pid, slot, draw)
    assert host.dtype == np.float32
    assert np.array_equal(out.to_numpy(), host)
    assert 0.45 < host.mean() < 0.55  # and they are spread over [0, 1)


def _births_and_live(out: Path, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, the new particles of each type (ids not seen before, by their type when first
    written) and the live particles of each type."""
    born, live, seen = np.zeros((frames, 3)), np.zeros((frames, 3)), -1
    for i in range(frames):
        d = diffuse(out, i)
        kind = d.arrays["type"].astype(int)
        new = d.ids.astype(np.int64) > seen
        born[i] = np.bincount(kind[new], minlength=3)[:3]
        live[i] = np.bincount(kind, minlength=3)[:3]
        seen = max(seen, int(d.ids.max())) if len(d.ids) else seen
    return born, live


@pytest.mark.parametrize("ahead", [True, False])
def test_no_type_is_born_past_its_share_of_the_budget(tmp_path, ahead):
    """A frame's new particles of a type never take that type past budget × its share: a type
    born early and living long (foam) cannot fill the room of one born later or living
    briefly (spray). Each frame's births of type t are at most the room its live count left
    after the last frame (the thinning rounds stochastically: + 3√room + 5)."""
    src = _gentle_then_violent(tmp_path / "in")
    out = tmp_path / "o"
    postprocess(src, out=out, params=_auto(budget=1.5), dt=1 / 30, radius=0.01, show_progress=False,
                look_ahead=ahead)
    born, live = _births_and_live(out, 24)
    room = np.maximum(1.5 / 3 * N_BLOCK - np.vstack([np.zeros(3), live[:-1]]), 0)
    assert born.sum() > 0.5 * N_BLOCK
    assert (born <= room + 3 * np.sqrt(room) + 5).all(), np.argwhere(born > room + 3 * np.sqrt(room) + 5)


def test_a_types_room_is_its_share_times_its_multiplier(tmp_path, monkeypatch):
    """The budget counts a type's multiplier at 1, so the room a frame's births of a type may
    fill is budget × share × multiplier less that type's live count: with spray 20 short of
    its share, a multiplier of 1 lets about 20 be born and a multiplier of 2 lets more.
    (The type scales are held at 1, so that only the room decides.)"""
    from whitecap.diffuse import budget as Bud
    from whitecap.diffuse.generator import FoamGenerator

    monkeypatch.setattr(Bud, "type_scales", lambda born, t, live, scales, *a: scales)
    _gentle_then_violent(tmp_path / "in", frames=5)
    frames = [io.read(f) for f in sorted((tmp_path / "in").glob("f_*.ply"))]
    n, budget = len(frames[0]), 30.0

    def spray_born(m: float) -> int:
        gen = FoamGenerator(_auto(budget=budget, spray_multiplier=m), radius=0.01, domain=((0, 0, 0), (1, 1, 1)),
                            gravity=(0, 0, -9.81), seed=1)
        for i, f in enumerate(frames[:4]):
            gen.step(f, i, 1 / 30)
        i, t, *_ = gen.state.counts[-1]
        gen.state.counts[-1] = (i, t, budget / 3 * n - 20, 0, 0)  # spray 20 short of its share, nothing else
        before = gen.state.next_id
        d = gen.step(frames[4], 4, 1 / 30)
        return int(((d.ids >= before) & (d.arrays["type"] == 0)).sum())

    one, two = spray_born(1.0), spray_born(2.0)
    assert one <= 20 + 3 * np.sqrt(20) + 5 and two > 2 * (20 + 3 * np.sqrt(20) + 5), (one, two)


@pytest.mark.parametrize("foam_live, aging", [(0.0, 1.0), (4.0, 2.0)])
def test_foam_past_its_share_ages_faster(tmp_path, foam_live, aging):
    """Foam fed by landing spray and surfacing bubbles keeps its birth lifetime, so fewer foam
    births cannot hold it to its share: under 'auto' foam's lifetime counts down λ times faster
    than the clock, λ moving halfway (geometrically) from 1 towards live / target. With no foam
    alive its lifetimes fall by Δt a frame; with 4 × its share alive, by √4 Δt = 2 Δt."""
    from whitecap.diffuse.generator import FoamGenerator

    _gentle_then_violent(tmp_path / "in", frames=6)
    frames = [io.read(f) for f in sorted((tmp_path / "in").glob("f_*.ply"))]
    n, budget, dt = len(frames[0]), 2.0, 1 / 30
    gen = FoamGenerator(_auto(budget=budget), radius=0.01, domain=((0, 0, 0), (1, 1, 1)), gravity=(0, 0, -9.81), seed=1)
    for i, f in enumerate(frames[:5]):
        d0 = gen.step(f, i, dt)
    i, t, *_ = gen.state.counts[-1]
    gen.state.counts[-1] = (i, t, 0, foam_live * budget / 3 * n, 0)
    gen.state.foam_aging = 1.0
    life0 = dict(zip(d0.ids.tolist(), d0.arrays["lifetime"].tolist()))
    d1 = gen.step(frames[5], 5, dt)
    old = np.isin(d1.ids, d0.ids) & (d1.arrays["type"] == 1)
    assert old.sum() > 20
    fell = np.array([life0[k] for k in d1.ids[old].tolist()]) - d1.arrays["lifetime"][old]
    assert np.allclose(fell, aging * dt, rtol=1e-3), (fell.min(), fell.max(), aging * dt)


def test_foam_aging_survives_a_checkpoint():
    """A resumed run ages its foam as the uninterrupted one would: λ is part of the checkpoint."""
    from whitecap.diffuse.generator import DiffuseState

    st = DiffuseState.empty()
    st.foam_aging = 3.5
    assert DiffuseState.from_arrays(st.to_arrays()).foam_aging == 3.5


@pytest.mark.parametrize("preset", ["splishsplash", "splishsplash-manual", "ihmsen2012"])
def test_foam_thins_out_only_in_whitecaps_own_presets_not_in_foamgenerators(preset):
    # 400 foam particles with 10 s to live on a resting block, for 1 s: FoamGenerator removes foam
    # only when its lifetime ends, so its presets keep every one; whitecap's own presets also
    # dissipate foam at FOAM_DISSIPATION = 0.5 /s, keeping about exp(-0.5) = 61 %.
    from dataclasses import replace

    from whitecap.diffuse.generator import DiffuseState, FoamGenerator
    from whitecap.diffuse.params import FOAM_DISSIPATION

    dt, r, frames = 0.04, 0.01, 25
    x = _lattice(10, r)
    fr = io.ParticleFrame(positions=x, velocities=np.zeros_like(x), ids=np.arange(len(x), dtype=np.uint32))
    p = replace(resolve(preset=preset), ta_min=1e3, ta_max=2e3, wc_min=1e3, wc_max=2e3)  # no generation
    gen = FoamGenerator(p, r, ([-1, -1, -1], [2, 2, 2]), (0, 0, -9.81), seed=1)
    gen.state = DiffuseState.empty()
    if p.model == "foamgenerator":
        gen.state.tau = np.array([1e3, 2e3, 1e3, 2e3, 1e3, 2e3, 1e3, 2e3], np.float32)
    else:
        gen.state.tau = None
    n = 400
    rng = np.random.default_rng(0)
    x0 = np.column_stack([rng.uniform(0.17, 0.21, n), rng.uniform(0.17, 0.21, n), np.full(n, x[:, 2].max() + r)])
    gen.state.positions, gen.state.velocities = x0.astype(np.float32), np.zeros((n, 3), np.float32)
    gen.state.lifetime, gen.state.ids = np.full(n, 10.0, np.float32), np.arange(n, dtype=np.uint32)
    for k in range(1, frames + 1):
        out = gen.step(fr, k, dt)
    assert (out.arrays["type"] == 1).all()  # foam throughout
    if preset.startswith("splishsplash"):
        assert p.foam_dissipation == 0.0 and len(out) == n
    else:
        expected = n * np.exp(-FOAM_DISSIPATION * frames * dt)
        assert abs(len(out) - expected) < 0.15 * n


def test_post_processing_reads_each_frame_ahead_once_and_names_a_bad_one(foam_run, tmp_path, monkeypatch):
    """`whitecap foam` reads frame k + 1 on a thread while frame k is processed: each frame once there, in order
    (frame 0 the look-ahead kept), and a frame that cannot be read stops the run with its own one-line error,
    after the frames before it were written."""
    import threading

    from whitecap.diffuse import driver

    run = tmp_path / "run"
    shutil.copytree(foam_run, run)
    reads: list[tuple[str, str]] = []
    read = driver.read
    monkeypatch.setattr(driver, "read", lambda p, *a, **kw: reads.append(
        (Path(p).name, threading.current_thread().name)) or read(p, *a, **kw))
    postprocess(run, show_progress=False)
    ahead = [name for name, thread in reads if thread.startswith("whitecap-foam-reader")]
    assert ahead == [f"fluid_{i:05d}.ply" for i in range(1, 13)]
    bad = run / "fluid" / "fluid_00006.ply"
    bad.write_bytes(bad.read_bytes()[:200])  # cut inside its rows
    for f in (run / "diffuse").glob("diffuse_*.ply"):
        f.unlink()
    with pytest.raises(InputError, match="fluid_00006.ply"):
        postprocess(run, show_progress=False)
    assert sorted(f.name for f in (run / "diffuse").glob("diffuse_*.ply")) == [
        f"diffuse_{i:05d}.ply" for i in range(6)]


def test_counts_csv_lists_every_row_so_far_each_formatted_once(monkeypatch):
    """counts.csv is rewritten after every frame; its rows are formatted once each, yet the text is always
    every row of the generator so far, a restored state's (a new list, shorter) included."""
    from types import SimpleNamespace

    from whitecap.config import Foam
    from whitecap.diffuse import driver

    stage = driver.FoamStage(resolve(Foam()), seed=0)
    state = SimpleNamespace(counts=[])
    stage.gen = SimpleNamespace(state=state)  # type: ignore[assignment]
    formatted = []
    line = driver.counts_line
    monkeypatch.setattr(driver, "counts_line", lambda r: formatted.append(r[0]) or line(r))

    def whole(rows):
        return "frame,time,spray,foam,bubbles\n" + "".join(f"{r[0]},{r[1]:.6f},{r[2]},{r[3]},{r[4]}\n" for r in rows)

    for i in range(5):
        state.counts.append((i, i / 30, 10 * i, 20 * i, 30 * i))
        assert stage._counts_csv() == whole(state.counts)
    assert formatted == [0, 1, 2, 3, 4]
    state.counts = [(0, 0.0, 0, 0, 0), (1, 1 / 30, 9, 9, 9)]  # restored from a checkpoint of frame 1
    formatted.clear()
    assert stage._counts_csv() == whole(state.counts) and formatted == [0, 1]
    state.counts.append((2, 2 / 30, 7, 7, 7))
    assert stage._counts_csv() == whole(state.counts) and formatted == [0, 1, 2]
