"""A run directory holds one simulation: nothing lost, nothing stale, one writer.

Simulation identity and the stages that redo frames of another one, `--force`
that keeps the old run until the new one starts, the writer lock (with a real
second process), resume that refuses another scene and recomputes nothing, and
a tampered run.json.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from whitecap.cli import main
from whitecap.config import scene_from_dict
from whitecap.errors import InputError, WhitecapError
from whitecap.io.lock import LOCK_FILE
from whitecap.io.run import RunInfo, simulation_identity
from whitecap.pipeline import export, mesh, simulate

from .conftest import ROOT, tiny_scene_dict

# Two scenes of the same size: another seed and another fluid block.
SCENE_A = tiny_scene_dict(output={"frames": 2}, foam={"enabled": False})
SCENE_B = tiny_scene_dict(seed=4, fluid=[{"lower": [0.0, 0.0, 0.0], "upper": [0.3, 0.2, 0.2]}], output={"frames": 2},
                          foam={"enabled": False})


def _sim(d: dict, out: Path, **kw) -> RunInfo:
    return simulate(scene_from_dict(d), out=out, show_progress=False, **kw)


def _snapshot(run: Path) -> dict[str, bytes]:
    """Every file of the run but the lock file (whose holder line changes)."""
    files = [p for p in sorted(run.rglob("*")) if p.is_file() and p.name != LOCK_FILE]
    return {str(p.relative_to(run)): p.read_bytes() for p in files}


# ----------------------------------------------------------------------------- 1. identity
def test_force_makes_mesh_and_export_redo_frames_of_the_old_simulation(tmp_path, capsys):
    run = tmp_path / "R"
    _sim(SCENE_A, run)
    assert main(["mesh", str(run), "--jobs", "1", "--smoothing-iters", "2"]) == 0
    assert main(["export", str(run)]) == 0
    old_mesh = (run / "mesh" / "fluid_00001.ply").read_bytes()
    capsys.readouterr()

    info = _sim(SCENE_B, run, force=True)
    assert info.simulation == simulation_identity(scene_from_dict(SCENE_B).to_toml()) != simulation_identity(
        scene_from_dict(SCENE_A).to_toml())
    # The old meshes are still on disk but belong to the old simulation: all are made again.
    assert main(["mesh", str(run), "--jobs", "1", "--smoothing-iters", "2"]) == 0
    assert "meshed 3 frames" in capsys.readouterr().out
    assert (run / "mesh" / "fluid_00001.ply").read_bytes() != old_mesh
    info = RunInfo.load(run)
    assert [f.made_from["mesh"] for f in info.frames] == [info.simulation] * 3
    # A rerun now skips them all.
    assert main(["mesh", str(run), "--jobs", "1", "--smoothing-iters", "2"]) == 0
    assert "meshed 0 frames" in capsys.readouterr().out

    # Export after another --force (no meshes yet): no mesh series of the old simulation is left behind.
    _sim(SCENE_A, run, force=True)
    export(run, show_progress=False)
    assert not (run / "export" / "mesh.pvd").exists() and not list((run / "export").glob("mesh/*.vtp"))
    manifest = json.loads((run / "export" / "export.json").read_text())
    assert manifest["simulation"] == RunInfo.load(run).simulation
    assert "fluid/fluid_00002.vtp" in manifest["files"]


def test_foam_records_its_identity_and_a_new_source_makes_mesh_redo(tmp_path, capsys):
    a, b = tmp_path / "A", tmp_path / "B"
    _sim(SCENE_A, a)
    _sim(SCENE_B, b)
    # On a run: the diffuse frames are stamped with the run's simulation.
    assert main(["foam", str(a)]) == 0
    info = RunInfo.load(a)
    assert [f.made_from["diffuse"] for f in info.frames] == [info.simulation] * 3
    # A foreign sequence converted into O, meshed, then another sequence into the same O.
    out = tmp_path / "O"
    for src, name in ((a, "seqA"), (b, "seqB")):
        seq = tmp_path / name
        seq.mkdir()
        for f in sorted((src / "fluid").iterdir()):
            shutil.copy(f, seq / f.name)
    assert main(["foam", str(tmp_path / "seqA"), "--out", str(out), "--radius", "0.01", "--dt", "0.0333333"]) == 0
    first = RunInfo.load(out).simulation
    assert main(["mesh", str(out), "--jobs", "1", "--smoothing-iters", "2"]) == 0
    args = ["foam", str(tmp_path / "seqB"), "--out", str(out), "--radius", "0.01", "--dt", "0.0333333"]
    assert main(args) == 2  # another simulation's run: replaced only with --force, and then whole
    assert main([*args, "--force"]) == 0
    assert RunInfo.load(out).simulation != first
    capsys.readouterr()
    assert main(["mesh", str(out), "--jobs", "1", "--smoothing-iters", "2"]) == 0
    assert "meshed 3 frames" in capsys.readouterr().out


KILLED_MESH = textwrap.dedent("""
    import os, signal, sys
    import whitecap.surface.driver as d
    from whitecap.pipeline import mesh
    real, n = d.mesh_frame, []
    def mesh_then_die(*a, **kw):
        if len(n) == 2:
            os.kill(os.getpid(), signal.SIGKILL)
        n.append(1)
        return real(*a, **kw)
    d.mesh_frame = mesh_then_die
    mesh(sys.argv[1], jobs=1, show_progress=False, mesh_smoothing_iters=2)
""")


def test_mesh_killed_by_sigkill_resumes_after_its_last_frame(tmp_path, capsys):
    """Each mesh is recorded as it finishes, so identity checks do not cost a killed run its finished frames."""
    run = tmp_path / "R"
    _sim(SCENE_A, run)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    p = subprocess.run([sys.executable, "-c", KILLED_MESH, str(run)], env=env, capture_output=True, timeout=300)
    assert p.returncode == -9
    assert [i for i, _ in RunInfo.load(run).files("mesh")] == [0, 1]
    capsys.readouterr()
    assert main(["mesh", str(run), "--jobs", "1", "--smoothing-iters", "2"]) == 0
    assert "meshed 1 frames" in capsys.readouterr().out


def test_stale_entries_in_run_json_are_not_current(tmp_path):
    """An entry made from another simulation reads as missing, so every reader redoes or ignores it."""
    run = tmp_path / "R"
    _sim(SCENE_A, run, frames=1)
    data = json.loads((run / "run.json").read_text())
    data["frames"][1]["files"]["mesh"] = "mesh/fluid_00001.ply"
    data["frames"][1]["made_from"]["mesh"] = "0123456789abcdef"
    (run / "run.json").write_text(json.dumps(data))
    info = RunInfo.load(run)
    assert info.files("mesh") == [] and len(info.files("fluid")) == 2


def test_render_redoes_frames_of_the_old_simulation(tmp_path, capsys):
    pytest.importorskip("bpy")
    small = {"preview_resolution": [64, 48], "preview_samples": 2}
    a = tiny_scene_dict(output={"frames": 1}, foam={"enabled": False}, render=small)
    b = {**SCENE_B, "output": {"frames": 1}, "render": small}
    run = tmp_path / "R"
    _sim(a, run)
    mesh(run, jobs=1, show_progress=False, mesh_smoothing_iters=2)
    assert main(["render", str(run), "--frames", "1", "--no-movie"]) == 0
    png, blend = run / "render" / "frame_00001.png", run / "render" / "scene.blend"
    before = png.stat().st_mtime_ns, png.stat().st_ino
    blend_before = blend.stat().st_mtime_ns, blend.stat().st_ino
    _sim(b, run, force=True)
    mesh(run, jobs=1, show_progress=False, mesh_smoothing_iters=2)
    assert main(["render", str(run), "--frames", "1", "--no-movie"]) == 0
    assert (png.stat().st_mtime_ns, png.stat().st_ino) != before  # rendered again
    # and the scene saved again (the inode alone can be the old file's, freed when the new simulation
    # removed it and handed out again), recorded as the new simulation's
    assert (blend.stat().st_mtime_ns, blend.stat().st_ino) != blend_before
    info = RunInfo.load(run)
    assert info.extra["blend"]["made_from"] == info.simulation
    assert info.frame(1).made_from["render"] == info.simulation
    after, blend_after = (png.stat().st_mtime_ns, png.stat().st_ino), blend.stat().st_ino
    assert main(["render", str(run), "--frames", "1", "--no-movie"]) == 0
    assert (png.stat().st_mtime_ns, png.stat().st_ino) == after  # and now it is current
    assert blend.stat().st_ino == blend_after


# ----------------------------------------------------------------------------- 2. --force keeps the old run
@pytest.mark.parametrize("bad", ["no fluid", "too many particles", "obstacle"])
def test_force_with_a_failing_setup_keeps_the_old_run(tmp_path, monkeypatch, bad):
    run = tmp_path / "R"
    _sim(SCENE_A, run)
    before = _snapshot(run)
    if bad == "no fluid":  # a block thinner than one particle spacing
        d = tiny_scene_dict(fluid=[{"lower": [0, 0, 0], "upper": [0.2, 0.2, 0.005]}], foam={"enabled": False})
        match = "holds no particle"
    elif bad == "too many particles":
        import whitecap.sim.pbf as pbf

        monkeypatch.setattr(pbf, "available_memory", lambda: 1000)
        d, match = SCENE_B, "more than this machine has free"
    else:
        d = tiny_scene_dict(obstacle=[{"mesh": str(tmp_path / "missing.obj")}], foam={"enabled": False})
        match = "missing.obj"
    with pytest.raises(WhitecapError, match=match):
        _sim(d, run, force=True)
    assert _snapshot(run) == before


def test_failing_setup_in_a_new_directory_leaves_nothing(tmp_path):
    d = tiny_scene_dict(fluid=[{"lower": [0, 0, 0], "upper": [0.2, 0.2, 0.005]}], foam={"enabled": False})
    with pytest.raises(WhitecapError, match="holds no particle"):
        _sim(d, tmp_path / "new")
    assert not (tmp_path / "new").exists()


# ----------------------------------------------------------------------------- 3. one writer per run
HOLD = textwrap.dedent("""
    import sys
    from whitecap.io.lock import run_lock
    with run_lock(sys.argv[1], "simulate"):
        print("locked", flush=True)
        sys.stdin.read()
""")


def test_a_second_writer_gets_one_line_naming_the_first(tmp_path, capsys):
    run = tmp_path / "R"
    _sim(SCENE_A, run)
    scene = tmp_path / "a.toml"
    scene.write_text(scene_from_dict(SCENE_A).to_toml())
    before = _snapshot(run)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(run)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True, env=env)
    try:
        assert holder.stdout.readline().strip() == "locked"
        for argv in (["simulate", str(scene), "-o", str(run), "--force"], ["foam", str(run)],
                     ["mesh", str(run), "--jobs", "1"], ["export", str(run)], ["render", str(run)]):
            capsys.readouterr()
            assert main(argv) == 2, argv
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and err.startswith("error: "), err
            assert f"pid {holder.pid}: simulate" in err and "another whitecap process" in err, err
        assert _snapshot(run) == before  # nobody wrote
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)
        holder.stdout.close()
    # The lock goes with its holder.
    assert main(["mesh", str(run), "--jobs", "1", "--smoothing-iters", "2"]) == 0


def test_the_lock_stops_a_writer_in_another_process(tmp_path):
    """The reverse: this process holds the lock, a `whitecap export` process is refused and names it."""
    from whitecap.io.lock import run_lock

    run = tmp_path / "R"
    _sim(SCENE_A, run, frames=1)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    with run_lock(run, "mesh"):
        p = subprocess.run([sys.executable, "-m", "whitecap.cli", "export", str(run)], capture_output=True,
                           text=True, env=env, timeout=120)
    assert p.returncode == 2
    assert f"pid {os.getpid()}: mesh" in p.stderr and p.stderr.count("\n") == 1, p.stderr
    assert not (run / "export").exists()


# ----------------------------------------------------------------------------- 4-6. resume
def test_resume_with_another_scene_is_refused_listing_the_changed_keys(tmp_path, capsys):
    run = tmp_path / "R"
    base = tiny_scene_dict(output={"frames": 3}, foam={"enabled": False})
    _sim(base, run, frames=1)
    before = _snapshot(run)
    bigger = tiny_scene_dict(output={"frames": 3}, foam={"enabled": False}, solver={"particle_radius": 0.012})
    with pytest.raises(InputError, match=r"run.json: .*changed: solver\.particle_radius\)"):
        _sim(bigger, run, resume=True)
    tweaked = tiny_scene_dict(seed=9, output={"frames": 3}, foam={"enabled": False},
                              solver={"particle_radius": 0.01, "iterations": 5})
    scene = tmp_path / "t.toml"
    scene.write_text(scene_from_dict(tweaked).to_toml())
    capsys.readouterr()
    assert main(["simulate", str(scene), "-o", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "changed: seed, solver.iterations)" in err, err
    assert main(["run", str(scene), "-o", str(run), "--until", "simulate"]) == 2  # `run` resumes: same check
    assert _snapshot(run) == before  # scene.toml still describes the frames
    # The frame count may change (extending a run); --force starts over with the new scene.
    more = tiny_scene_dict(output={"frames": 4}, foam={"enabled": False})
    assert len(_sim(more, run, resume=True).frames) == 5
    info = _sim(bigger, run, resume=True, force=True)
    assert info.particle_radius == 0.012 and len(info.frames) == 4


def test_resume_recomputes_no_finished_frame(tmp_path, monkeypatch):
    from whitecap.sim.pbf import PBFSolver

    sc = scene_from_dict(tiny_scene_dict(output={"frames": 4}, foam={"enabled": False}))
    run = tmp_path / "R"
    simulate(sc, out=run, frames=2, show_progress=False, foam=False)
    done = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in (run / "fluid").iterdir()}
    assert len(done) == 3
    advanced = []
    real = PBFSolver.advance_frame

    def counting(self, index):
        advanced.append(index)
        return real(self, index)

    monkeypatch.setattr(PBFSolver, "advance_frame", counting)
    simulate(sc, out=run, resume=True, show_progress=False, foam=False)
    assert advanced == [3, 4]  # only the frames after the checkpoint are simulated
    assert {n: (run / "fluid" / n).stat().st_ino for n in done} == {n: v[0] for n, v in done.items()}
    assert {n: (run / "fluid" / n).stat().st_mtime_ns for n in done} == {n: v[1] for n, v in done.items()}


class Interrupt(Exception):
    pass


def test_resume_from_checkpoint_0_is_byte_identical(tmp_path, monkeypatch):
    import whitecap.sim.driver as driver

    d = tiny_scene_dict(output={"frames": 2}, foam={"preset": "auto", "k_ta": 400.0, "k_wc": 5000.0})
    full, part = tmp_path / "full", tmp_path / "part"
    _sim(d, full)
    real = driver._save_checkpoint

    def crash_after_0(o, index, solver, hooks, host=None):
        real(o, index, solver, hooks, host)
        if index == 0:
            raise Interrupt

    monkeypatch.setattr(driver, "_save_checkpoint", crash_after_0)
    with pytest.raises(Interrupt):
        _sim(d, part)
    monkeypatch.setattr(driver, "_save_checkpoint", real)
    _sim(d, part, resume=True)
    counts = (part / "diffuse" / "counts.csv").read_text()
    assert [line.split(",")[0] for line in counts.splitlines()[1:]] == ["0", "1", "2"]
    for name in ("diffuse/counts.csv", "diffuse/diffuse_00002.ply", "fluid/fluid_00002.ply"):
        assert (part / name).read_bytes() == (full / name).read_bytes(), name


# ----------------------------------------------------------------------------- 7. tampered run.json
@pytest.mark.parametrize("field,tamper", [
    ("particle_radius", lambda d: d.update(particle_radius="0.01")),
    ("frame_rate", lambda d: d.update(frame_rate=None)),
    ("gravity", lambda d: d.update(gravity=[0, 0])),
    ("frames", lambda d: d.update(frames={"0": 1})),
    ("frames[1].index", lambda d: d["frames"][1].update(index="1")),
    ("frames[1].files", lambda d: d["frames"][1].update(files=["fluid/fluid_00001.ply"])),
    ("frames[0].files.fluid", lambda d: d["frames"][0]["files"].update(fluid="/etc/passwd")),
    ("frames[1].files.fluid", lambda d: d["frames"][1]["files"].update(fluid="../../outside.ply")),
    ("frames[1].files.fluid", lambda d: d["frames"][1]["files"].update(fluid="fluid/../../outside.ply")),
    ("extra.seed", lambda d: d["extra"].update(seed="three")),
])
def test_tampered_run_json_is_one_line_naming_the_field(tmp_path, capsys, field, tamper):
    run = tmp_path / "R"
    _sim(SCENE_A, run, frames=1)
    data = json.loads((run / "run.json").read_text())
    tamper(data)
    (run / "run.json").write_text(json.dumps(data))
    for argv in (["mesh", str(run), "--jobs", "1"], ["export", str(run)], ["render", str(run)], ["foam", str(run)]):
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"run.json: field '{field}'" in err, (argv, err)
    assert not (run / "mesh").exists() and not (run / "export").exists()


def test_recording_a_path_outside_the_run_is_refused(tmp_path):
    info = RunInfo(particle_radius=0.01, rest_density=1000.0, particle_mass=0.008, gravity=[0, 0, -9.81],
                   domain={"lower": [0, 0, 0], "upper": [1, 1, 1]}, frame_rate=30.0)
    for bad in ("/tmp/x.ply", "../x.ply", "mesh/../../x.ply"):
        with pytest.raises(InputError, match="not a relative path inside the run"):
            info.set_file(0, "mesh", bad)
    info.set_file(0, "mesh", "mesh/fluid_00000.ply")
    assert info.files("mesh") == [(0, "mesh/fluid_00000.ply")]


def test_frame_entries_are_found_by_index_with_gaps_and_out_of_order_files(tmp_path):
    # run.json's frames looked up by index (a body's pose, a frame's time) whether the indices are
    # contiguous, have gaps, or were written out of order; a new frame goes in index order.
    from whitecap.io.run import RunInfo

    info = RunInfo(particle_radius=0.01, rest_density=1000.0, particle_mass=0.008, frame_rate=10.0,
                   gravity=[0, 0, -9.81], domain={"lower": [0, 0, 0], "upper": [1, 1, 1]})
    for i in (7, 2, 5, 0):
        info.frame(i).bodies = [{"position": [i, 0, 0], "quaternion": [1, 0, 0, 0]}]
    assert [f.index for f in info.frames] == [0, 2, 5, 7]
    assert [info.body_pose(i, 0).position[0] for i in (0, 2, 5, 7)] == [0, 2, 5, 7]
    assert info.body_pose(3, 0) is None and info.body_pose(8, 0) is None and info.body_pose(5, 1) is None
    assert info.frame(3).time == pytest.approx(0.3) and [f.index for f in info.frames] == [0, 2, 3, 5, 7]
    info.save(tmp_path)
    data = json.loads((tmp_path / "run.json").read_text())
    data["frames"].reverse()  # another writer's order
    (tmp_path / "run.json").write_text(json.dumps(data))
    back = RunInfo.load(tmp_path)
    assert [info.body_pose(i, 0) for i in range(9)] == [back.body_pose(i, 0) for i in range(9)]


def test_foam_into_another_folder_stopped_half_way_is_continued_by_the_same_command(tmp_path, monkeypatch):
    """`foam RUN --out DIR` stopped at a frame (an error, Ctrl-C) leaves DIR a run whose run.json lists
    exactly the frames whose files are complete, nothing else in it; the same command again is not
    refused (its files are whitecap's, recorded) and makes what an uninterrupted one makes, byte for byte."""
    from whitecap.diffuse import driver

    run = tmp_path / "R"
    _sim(tiny_scene_dict(output={"frames": 5}, foam={"enabled": False}), run)
    step = driver.FoamStage.on_frame

    def stop_at_3(self, fr, index, *a, **k):
        if index == 3:
            raise KeyboardInterrupt
        return step(self, fr, index, *a, **k)

    monkeypatch.setattr(driver.FoamStage, "on_frame", stop_at_3)
    with pytest.raises(KeyboardInterrupt):
        driver.postprocess(run, out=tmp_path / "O", show_progress=False)
    info = RunInfo.load(tmp_path / "O")
    assert info.files("fluid") == [(i, f"fluid/fluid_{i:05d}.ply") for i in range(3)]
    assert info.files("diffuse") == [(i, f"diffuse/diffuse_{i:05d}.ply") for i in range(3)]
    on_disk = {str(p.relative_to(tmp_path / "O")) for p in (tmp_path / "O").rglob("*") if p.is_file()}
    assert on_disk == {rel for f in info.frames for rel in f.files.values()} | {
        "run.json", "diffuse/counts.csv", "diffuse/resume.npz", LOCK_FILE}
    monkeypatch.setattr(driver.FoamStage, "on_frame", step)
    driver.postprocess(run, out=tmp_path / "O", show_progress=False)
    driver.postprocess(run, out=tmp_path / "whole", show_progress=False)
    again, whole = RunInfo.load(tmp_path / "O"), RunInfo.load(tmp_path / "whole")
    assert again.files("diffuse") == whole.files("diffuse") and len(whole.files("diffuse")) == 6
    for rel in [r for _, r in whole.files("fluid") + whole.files("diffuse")] + ["diffuse/counts.csv"]:
        assert (tmp_path / "O" / rel).read_bytes() == (tmp_path / "whole" / rel).read_bytes(), rel


def test_foam_again_into_a_copy_keeps_the_copys_own_meshes_recorded(tmp_path):
    """`foam RUN --out DIR`, `mesh DIR`, then `foam RUN --out DIR` again: DIR's meshes (its own files, of
    the same simulation) stay recorded, and every file in DIR is one run.json records."""
    from whitecap.diffuse import driver
    from whitecap.io.run import owned_files

    run, out = tmp_path / "R", tmp_path / "O"
    _sim(SCENE_A, run)
    mesh(run, jobs=1, show_progress=False, mesh_smoothing_iters=0)  # the source's meshes: not the copy's
    driver.postprocess(run, out=out, show_progress=False)
    assert RunInfo.load(out).files("mesh") == []
    mesh(out, jobs=1, show_progress=False, mesh_smoothing_iters=0)
    meshed = RunInfo.load(out).files("mesh")
    assert len(meshed) == 3
    driver.postprocess(run, out=out, show_progress=False)
    info = RunInfo.load(out)
    assert info.files("mesh") == meshed and "mesh" in info.extra and len(info.files("diffuse")) == 3
    on_disk = {p for p in out.rglob("*") if p.is_file() and p.name != LOCK_FILE}
    assert on_disk == set(owned_files(out)) | {out / "diffuse" / "counts.csv"}
