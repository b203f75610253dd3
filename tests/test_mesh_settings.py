"""`mesh` settings are part of each mesh's identity, and a grid that cannot fit is refused up front
(issue 30, items 12 and 19)."""

from __future__ import annotations

import shutil

from whitecap.cli import main
from whitecap.io.run import RunInfo

FAST = ["--jobs", "1", "--smoothing-iters", "0"]


def test_new_cube_size_remakes_every_mesh_and_run_json_holds_only_applied_settings(tiny_run, tmp_path, capsys):
    run = tmp_path / "R"
    shutil.copytree(tiny_run, run)
    assert main(["mesh", str(run), *FAST]) == 0
    first = {p.name: p.read_bytes() for p in (run / "mesh").glob("*.ply")}
    assert RunInfo.load(run).extra["mesh"]["cube_size"] == 0.5
    capsys.readouterr()
    assert main(["mesh", str(run), *FAST, "--cube-size", "0.8"]) == 0
    assert "meshed 4 frames" in capsys.readouterr().out
    second = {p.name: p.read_bytes() for p in (run / "mesh").glob("*.ply")}
    assert second.keys() == first.keys() and all(second[k] != first[k] for k in first)
    assert RunInfo.load(run).extra["mesh"]["cube_size"] == 0.8
    # The same settings again: nothing to do.
    assert main(["mesh", str(run), *FAST, "--cube-size", "0.8"]) == 0
    assert "meshed 0 frames" in capsys.readouterr().out


def test_a_partly_remeshed_run_records_no_settings(tiny_run, tmp_path):
    from whitecap.surface.driver import plan, run_mesh

    run = tmp_path / "R"
    shutil.copytree(tiny_run, run)
    assert main(["mesh", str(run), *FAST]) == 0
    job = plan(run, mesh_smoothing_iters=0, cube_size=0.8)
    job.frames = job.frames[:2]  # as if interrupted after two frames
    run_mesh(job, jobs=1, show_progress=False)
    info = RunInfo.load(run)
    assert "mesh" not in info.extra  # two settings in one run: neither is "the" run's
    assert len(info.files("mesh")) == 4


def test_a_cube_size_that_cannot_fit_is_refused_before_any_frame(tiny_run, tmp_path, capsys):
    run = tmp_path / "R"
    shutil.copytree(tiny_run, run)
    assert main(["mesh", str(run), *FAST, "--cube-size", "0.00001"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "mesh.cube_size" in err and "GiB" in err, err
    assert not (run / "mesh").exists()


def _sequence(folder, frames=(3, 4)):
    from .test_surface import lattice_sphere, write_frame

    for i in frames:
        write_frame(folder / f"part_{i:04d}.ply", lattice_sphere(0.08))
    return folder


def test_mesh_outside_a_run_never_overwrites_or_skips_on_a_users_file(tmp_path, capsys):
    seq = _sequence(tmp_path / "seq")
    out = tmp_path / "mine"
    out.mkdir()
    (out / "fluid_00004.ply").write_bytes(b"the user's own mesh")
    assert main(["mesh", str(seq), "--radius", "0.01", "-o", str(out), *FAST]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "fluid_00004.ply: not written by whitecap" in err, err
    assert (out / "fluid_00004.ply").read_bytes() == b"the user's own mesh"
    for extra in ([], ["--force"]):  # not even with --force
        assert main(["mesh", str(seq), "--radius", "0.01", "-o", str(out), *FAST, *extra]) == 2
    assert (out / "fluid_00004.ply").read_bytes() == b"the user's own mesh"


def test_mesh_outside_a_run_remakes_frames_of_another_input_or_settings(tmp_path, capsys):
    import os

    seq = _sequence(tmp_path / "seq")
    assert main(["mesh", str(seq), "--radius", "0.01", *FAST]) == 0
    capsys.readouterr()
    assert main(["mesh", str(seq), "--radius", "0.01", *FAST]) == 0
    assert "meshed 0 frames" in capsys.readouterr().out
    assert main(["mesh", str(seq), "--radius", "0.01", *FAST, "--cube-size", "0.8"]) == 0
    assert "meshed 2 frames" in capsys.readouterr().out
    # A frame of the input written again (another simulation's output in the same place): made again.
    from .test_surface import lattice_sphere, write_frame

    write_frame(seq / "part_0004.ply", lattice_sphere(0.06))
    os.utime(seq / "part_0004.ply", ns=(1, 1))
    assert main(["mesh", str(seq), "--radius", "0.01", *FAST, "--cube-size", "0.8"]) == 0
    assert "meshed 1 frames" in capsys.readouterr().out


def test_mesh_during_the_first_frame_of_simulate_names_the_writer(tmp_path, capsys):
    """simulate writes run.json before its first frame: a mesh started then names the writer."""
    import json
    import subprocess
    import sys

    from whitecap.io.run import RunInfo

    run = tmp_path / "R"
    run.mkdir()
    info = RunInfo(particle_radius=0.01, rest_density=1000.0, particle_mass=0.008, gravity=[0, 0, -9.81],
                   domain={"lower": [0, 0, 0], "upper": [1, 1, 1]}, frame_rate=30.0, simulation="abc")
    info.save(run)
    assert json.loads((run / "run.json").read_text())["frames"] == []
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from whitecap.io.lock import run_lock\n"
        f"with run_lock({str(run)!r}, 'simulate'):\n    print('held', flush=True); time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert main(["mesh", str(run), *FAST]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "another whitecap process is writing" in err and "simulate" in err, err
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    assert main(["mesh", str(run), *FAST]) == 2  # nobody writing: the run simply has no frames
    assert "the run has no fluid frames" in capsys.readouterr().err


def test_mesh_never_writes_over_the_runs_own_frames(tiny_run, tmp_path, capsys):
    run = tmp_path / "R"
    shutil.copytree(tiny_run, run)
    before = (run / "fluid" / "fluid_00001.ply").read_bytes()
    assert main(["mesh", str(run), "-o", str(run / "fluid"), *FAST]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "is the run's fluid file" in err, err
    assert (run / "fluid" / "fluid_00001.ply").read_bytes() == before


def test_render_redoes_frames_whose_look_or_inputs_changed(tmp_path, capsys):
    """A frame rendered with other [render] settings, or from a mesh made again since, is rendered
    again rather than skipped beside frames of the new look (the same defect as item 12)."""
    import pytest

    pytest.importorskip("bpy")
    from whitecap.config import scene_from_dict
    from whitecap.pipeline import mesh, simulate

    from .conftest import tiny_scene_dict

    small = {"preview_resolution": [64, 48], "preview_samples": 2}
    run = tmp_path / "R"
    simulate(scene_from_dict(tiny_scene_dict(output={"frames": 1}, foam={"enabled": False}, render=small)),
             out=run, show_progress=False)
    mesh(run, jobs=1, show_progress=False, mesh_smoothing_iters=0)
    png = run / "render" / "frame_00001.png"

    def rendered() -> bool:
        before = png.stat().st_ino if png.exists() else None
        assert main(["render", str(run), "--frames", "1", "--no-movie"]) == 0
        return png.stat().st_ino != before

    assert rendered()
    assert not rendered()  # nothing changed: skipped
    scene = run / "scene.toml"
    scene.write_text(scene.read_text().replace("preview_samples = 2", "preview_samples = 3"))
    assert rendered()  # the look changed
    assert not rendered()
    mesh(run, jobs=1, show_progress=False, mesh_smoothing_iters=1)  # other settings: meshes remade
    assert rendered()
