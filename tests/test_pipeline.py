"""End to end: `whitecap run` from a scene file to a movie, with interrupt and resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
from plyfile import PlyData

from whitecap.cli import main
from whitecap.io.run import RunInfo

pytest.importorskip("bpy")

SCENE = """
name = "e2e"
seed = 5
[domain]
upper = [0.6, 0.2, 0.4]
[solver]
particle_radius = 0.01
[[fluid]]
lower = [0.0, 0.0, 0.0]
upper = [0.2, 0.2, 0.3]
[render]
preview_resolution = [160, 120]
preview_samples = 8
[output]
frames = 3
"""


class Interrupt(Exception):
    pass


def test_run_all_stages_with_interrupt_and_resume(tmp_path, monkeypatch, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    out = tmp_path / "run"

    # 1. Interrupt the simulation after frame 2 has been written.
    import whitecap.sim.driver as driver

    real = driver._save_checkpoint

    def crash_after_2(o, index, solver, hooks, host=None):
        real(o, index, solver, hooks, host)
        if index == 2:
            raise Interrupt

    monkeypatch.setattr(driver, "_save_checkpoint", crash_after_2)
    with pytest.raises(Interrupt):
        main(["run", str(scene), "--out", str(out), "--preview"])
    assert (out / "fluid" / "fluid_00002.ply").exists() and not (out / "fluid" / "fluid_00003.ply").exists()
    frame2 = (out / "fluid" / "fluid_00002.ply").read_bytes()
    monkeypatch.setattr(driver, "_save_checkpoint", real)

    # 2. Stop after meshing, then 3. finish: every stage resumes where it was.
    assert main(["run", str(scene), "--out", str(out), "--preview", "--until", "mesh"]) == 0
    assert not (out / "render").exists()
    # The time of each stage run is printed and recorded (profile.json holds the last run's stages).
    assert "time per stage: simulate" in capsys.readouterr().out
    assert list(json.loads((out / "profile.json").read_text())["stage_seconds"]) == ["simulate", "mesh"]
    assert main(["run", str(scene), "--out", str(out), "--preview"]) == 0
    printed = capsys.readouterr().out
    assert "movie:" in printed and "blend:" in printed
    prof = json.loads((out / "profile.json").read_text())
    assert list(prof["stage_seconds"]) == ["simulate", "mesh", "render"]
    assert prof["total_seconds"] == pytest.approx(sum(prof["stage_seconds"].values()), abs=0.01)
    assert (out / "fluid" / "fluid_00002.ply").read_bytes() == frame2  # finished frames are not redone

    # The output contract, stage by stage.
    info = RunInfo.load(out)
    assert [f.index for f in info.frames] == [0, 1, 2, 3]
    for f in info.frames:
        assert {"fluid", "diffuse", "mesh", "render"} <= set(f.files)
        fluid = PlyData.read(str(out / f.files["fluid"]))["vertex"].data
        assert fluid.dtype.names[:6] == ("x", "y", "z", "vx", "vy", "vz")
        assert fluid["id"].dtype == np.uint32 and fluid["density"].dtype == np.float32
        mesh = PlyData.read(str(out / f.files["mesh"]))
        assert {"nx", "vx"} <= set(mesh["vertex"].data.dtype.names) and len(mesh["face"].data) > 100
        assert (out / f.files["render"]).stat().st_size > 1000
    assert json.loads((out / "run.json").read_text())["particle_radius"] == 0.01
    import imageio.v2 as imageio

    assert imageio.get_reader(str(out / "render" / "movie.mp4"), format="FFMPEG").count_frames() == 4
    assert (out / "render" / "scene.blend").stat().st_size > 10_000


def test_run_rejects_unknown_stage(tmp_path, capsys):
    from whitecap import pipeline
    from whitecap.errors import InputError

    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    out = tmp_path / "out"
    try:
        code = main(["run", str(scene), "--out", str(out), "--until", "paint"])
    except SystemExit as exc:  # argparse's choices
        code = exc.code
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert code == 2
    assert "--until" in last and "paint" in last and all(s in last for s in ("simulate", "mesh", "render")), last
    assert not out.exists()
    # The API says the same, before touching the output directory.
    with pytest.raises(InputError) as e:
        pipeline.run(str(scene), out=out, until="paint", show_progress=False)
    assert "--until" in str(e.value) and "'paint'" in str(e.value) and "simulate, mesh, render" in str(e.value)
    assert not out.exists()
