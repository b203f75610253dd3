"""whitecap deletes and overwrites only what it recorded as its own (issue 30, items 1-5, 8, 17).

Every test here puts something that is not whitecap's (an imported case, a converted sequence,
a user's files, a user's scene file) where a stage writes, and checks that it survives the
stage byte for byte, with a one-line error, or that `--force` replaces a run whole and nothing
of the user's.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from whitecap.cli import main
from whitecap.config import scene_from_dict
from whitecap.io import ParticleFrame, write
from whitecap.io.lock import LOCK_FILE
from whitecap.io.run import RunInfo, owned_files, remove_run, simulation_identity

from .conftest import tiny_scene_dict

SCENE = tiny_scene_dict(output={"frames": 1}, foam={"enabled": False})


def snapshot(path: Path) -> dict[str, bytes]:
    """Every file under ``path`` but the writer lock (whose holder line changes), with its bytes."""
    if not path.exists():
        return {}
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file() and p.name != LOCK_FILE}


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error:"), err
    return err


def scene_file(tmp_path: Path, d: dict = SCENE, name: str = "scene.toml") -> Path:
    p = tmp_path / name
    p.write_text(scene_from_dict(d).to_toml())
    return p


def foreign_sequence(folder: Path, frames: int = 3) -> Path:
    """Another solver's output: numbered PLY frames of a falling block of water."""
    folder.mkdir(parents=True)
    g = (np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) * 0.02
    for k in range(frames):
        pos = (g + [0.1, 0.1, 0.1 - 0.01 * k]).astype(np.float32)
        vel = np.tile(np.float32([0.5, 0.0, -1.0 * k]), (len(g), 1))
        write(folder / f"frame_{k:04d}.ply", ParticleFrame(pos, vel, np.arange(len(g), dtype=np.uint32)))
    return folder


@pytest.fixture()
def run_a(tiny_run, tmp_path) -> Path:
    out = tmp_path / "A"
    shutil.copytree(tiny_run, out)
    return out


# ----------------------------------------------------------------------------- 1. resume into a foreign run
def test_simulate_resume_and_run_refuse_an_imported_case_and_keep_it(tmp_path, capsys):
    from .test_cases_dualsphysics import synthetic_case

    case = tmp_path / "case"
    synthetic_case(case, frames=2)
    run = tmp_path / "imported"
    assert main(["import", str(case), "--out", str(run)]) == 0
    before = snapshot(run)
    scene = scene_file(tmp_path)
    capsys.readouterr()
    assert main(["simulate", str(scene), "-o", str(run), "--resume"]) == 2
    assert "another simulation (converted from" in one_line_error(capsys)
    assert main(["run", str(scene), "-o", str(run), "--until", "simulate"]) == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]  # after the stage's heading
    assert last.startswith("error:") and "another simulation" in last
    assert snapshot(run) == before


def test_simulate_resume_refuses_a_foam_converted_sequence_and_keeps_it(tmp_path, capsys):
    seq = foreign_sequence(tmp_path / "seq")
    run = tmp_path / "converted"
    assert main(["foam", str(seq), "--out", str(run), "--dt", "0.02", "--radius", "0.01"]) == 0
    assert RunInfo.load(run).files("diffuse")
    before = snapshot(run)
    capsys.readouterr()
    assert main(["simulate", str(scene_file(tmp_path)), "-o", str(run), "--resume"]) == 2
    one_line_error(capsys)
    assert snapshot(run) == before


# ----------------------------------------------------------------------------- 2. foam --out onto another run
def test_foam_out_onto_another_run_is_refused_and_force_replaces_it_whole(run_a, tmp_path, capsys):
    seq = foreign_sequence(tmp_path / "seq")
    mine = run_a / "my_notes.txt"
    mine.write_text("keep me")
    before = snapshot(run_a)
    capsys.readouterr()
    assert main(["foam", str(seq), "--out", str(run_a), "--dt", "0.02", "--radius", "0.01"]) == 2
    assert "holds another simulation" in one_line_error(capsys)
    assert snapshot(run_a) == before

    assert main(["foam", str(seq), "--out", str(run_a), "--dt", "0.02", "--radius", "0.01", "--force"]) == 0
    info = RunInfo.load(run_a)
    assert info.extra["source"] == str(seq)
    assert [i for i, _ in info.files("fluid")] == [0, 1, 2]
    # Nothing of the old simulation is left to be mixed in: no checkpoint, no scene, no old frame.
    assert not (run_a / "checkpoint.npz").exists() and not (run_a / "scene.toml").exists()
    assert not (run_a / "fluid" / "fluid_00003.ply").exists()
    assert mine.read_text() == "keep me"
    capsys.readouterr()
    assert main(["simulate", str(scene_file(tmp_path, tiny_scene_dict())), "-o", str(run_a), "--resume"]) == 2
    one_line_error(capsys)


# ----------------------------------------------------------------------------- 3. the user's files
def test_simulate_refuses_a_folder_of_user_files_even_with_force(tmp_path, capsys):
    d = tmp_path / "D"
    (d / "fluid").mkdir(parents=True)
    (d / "diffuse").mkdir()
    (d / "fluid" / "fluid_00000.ply").write_bytes(b"my own data")
    (d / "diffuse" / "notes.txt").write_text("my notes")
    before = snapshot(d)
    scene = scene_file(tmp_path)
    for extra in ([], ["--force"], ["--resume"]):
        capsys.readouterr()
        assert main(["simulate", str(scene), "-o", str(d), *extra]) == 2
        assert "files whitecap did not write" in one_line_error(capsys)
        assert snapshot(d) == before


def test_force_removes_only_what_the_run_recorded(run_a, tmp_path, capsys):
    notes = [run_a / "fluid" / "notes.txt", run_a / "diffuse" / "mine.csv", run_a / "README.txt"]
    for p in notes:
        p.parent.mkdir(exist_ok=True)
        p.write_text("user's")
    assert main(["simulate", str(scene_file(tmp_path)), "-o", str(run_a), "--force"]) == 0
    assert all(p.read_text() == "user's" for p in notes)
    info = RunInfo.load(run_a)
    assert info.simulation == simulation_identity(scene_from_dict(SCENE).to_toml())
    # The old run had frames 0..3; the new one has 0..1 and no file of the old is left over.
    assert sorted(p.name for p in (run_a / "fluid").glob("*.ply")) == ["fluid_00000.ply", "fluid_00001.ply"]


def test_remove_run_follows_no_recorded_path_out_of_the_run(run_a, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("outside")
    data = json.loads((run_a / "run.json").read_text())
    data["frames"][0]["files"]["mesh"] = "../victim.txt"
    data["obstacles"] = [{"mesh": str(victim), "render_mesh": "../victim.txt"}]
    data["extra"].pop("scene_dir")  # as an imported case: its obstacle meshes lie in the run
    (run_a / "run.json").write_text(json.dumps(data))
    assert victim not in owned_files(run_a)
    remove_run(run_a)
    assert victim.read_text() == "outside"
    assert not (run_a / "run.json").exists() and not (run_a / "fluid").exists()


# ----------------------------------------------------------------------------- 4. the user's scene file
def test_simulate_never_overwrites_a_scene_file_it_did_not_write(tmp_path, capsys):
    d = tmp_path / "D"
    d.mkdir()
    scene = d / "scene.toml"
    text = "# my dam break, with comments\n" + scene_from_dict(SCENE).to_toml()
    scene.write_text(text)
    for extra in ([], ["--force"]):
        capsys.readouterr()
        assert main(["simulate", str(scene), "-o", str(d), *extra]) == 2
        one_line_error(capsys)
        assert scene.read_text() == text and sorted(p.name for p in d.iterdir()) == ["scene.toml"]


def test_an_edited_run_scene_is_neither_overwritten_nor_resumed(run_a, tmp_path, capsys):
    """Item 8: the check is against run.json's identity, not against the (edited) scene.toml."""
    scene = run_a / "scene.toml"
    edited = scene.read_text().replace("seed = 3", "seed = 9")
    assert edited != scene.read_text()
    scene.write_text(edited)
    before = snapshot(run_a)
    capsys.readouterr()
    assert main(["simulate", str(scene), "-o", str(run_a), "--resume", "--frames", "4"]) == 2
    assert "another" in one_line_error(capsys)
    assert snapshot(run_a) == before
    # Only comments added: the same simulation, but whitecap would lose them: refused too.
    scene.write_text("# mine\n" + before["scene.toml"].decode().replace("seed = 9", "seed = 3"))
    original = scene_file(tmp_path, tiny_scene_dict())
    assert main(["simulate", str(original), "-o", str(run_a), "--resume", "--frames", "4"]) == 2
    assert "scene.toml: not the scene whitecap wrote" in one_line_error(capsys)


def test_an_unedited_run_scene_is_rewritten_when_a_run_is_extended(run_a, tmp_path):
    longer = scene_file(tmp_path, tiny_scene_dict(output={"frames": 4}))
    assert main(["simulate", str(longer), "-o", str(run_a), "--resume"]) == 0
    assert "frames = 4" in (run_a / "scene.toml").read_text()
    assert len(RunInfo.load(run_a).files("fluid")) == 5


# ----------------------------------------------------------------------------- 5. the scene name
@pytest.mark.parametrize("name", ["../escaped", "/tmp/whitecap-escaped", "", "a/b", ".."])
def test_a_scene_name_that_is_not_one_folder_name_is_refused(tmp_path, monkeypatch, capsys, name):
    monkeypatch.chdir(tmp_path)
    scene = scene_file(tmp_path, {**SCENE, "name": "x"})
    scene.write_text(scene.read_text().replace('name = "x"', f"name = {json.dumps(name)}"))
    (tmp_path / "escaped").mkdir()
    (tmp_path / "escaped" / "keep.txt").write_text("mine")
    for extra in ([], ["--force"]):
        assert main(["simulate", str(scene), *extra]) == 2
        assert "name: must be one folder name" in one_line_error(capsys)
    assert not (tmp_path / "out").exists() and not Path("/tmp/whitecap-escaped").exists()
    assert (tmp_path / "escaped" / "keep.txt").read_text() == "mine"


# ----------------------------------------------------------------------------- inputs and messages
def test_a_scene_that_is_not_utf8_is_one_line(tmp_path, capsys, tiny_run):
    bad = tmp_path / "latin1.toml"
    bad.write_bytes('name = "caf\xe9"\n'.encode("latin-1"))
    assert main(["simulate", str(bad), "-o", str(tmp_path / "R")]) == 2
    assert "not UTF-8" in one_line_error(capsys)
    assert main(["mesh", str(tiny_run), "--config", str(bad), "-o", str(tmp_path / "M")]) == 2
    assert "not UTF-8" in one_line_error(capsys)


def test_a_directory_given_as_the_scene_says_so(tmp_path, capsys):
    assert main(["simulate", str(tmp_path)]) == 2
    assert "is a directory" in one_line_error(capsys)


@pytest.mark.parametrize("opt", ["--dt", "--radius"])
def test_foam_zero_dt_or_radius_names_the_option(tmp_path, capsys, opt):
    seq = foreign_sequence(tmp_path / "seq", frames=2)
    args = {"--dt": "0.02", "--radius": "0.01", opt: "0"}
    assert main(["foam", str(seq), "--out", str(tmp_path / "F"), *sum(map(list, args.items()), [])]) == 2
    assert f"{opt}: must be a positive number" in one_line_error(capsys)


def test_an_import_that_fails_half_way_leaves_nothing(tmp_path, monkeypatch, capsys):
    from whitecap.cases import run_dir
    from whitecap.errors import InputError

    from .test_cases_dualsphysics import synthetic_case

    case = tmp_path / "case"
    synthetic_case(case, frames=3)
    real, calls = run_dir.read, []

    def read_then_fail(path, **kw):
        calls.append(path)
        if len(calls) == 3:
            raise InputError(f"{path}: truncated")
        return real(path, **kw)

    monkeypatch.setattr(run_dir, "read", read_then_fail)
    out = tmp_path / "run"
    assert main(["import", str(case), "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].endswith("PartFluid_0002.vtk: truncated")
    assert len(calls) == 3 and not out.exists()
    # Into an existing empty folder: the folder stays, empty.
    out.mkdir()
    calls.clear()
    assert main(["import", str(case), "--out", str(out)]) == 2
    assert list(out.iterdir()) == []


def test_resume_without_a_checkpoint_never_replaces_frames(run_a, tmp_path, capsys):
    """A run of this very scene with frames but no checkpoint (a `foam --out` copy of a run, or a
    removed checkpoint) is not started over by --resume or `run` without --force."""
    copy = tmp_path / "C"
    assert main(["foam", str(run_a), "--out", str(copy)]) == 0
    assert not (copy / "checkpoint.npz").exists()
    before = snapshot(copy)
    scene = scene_file(tmp_path, tiny_scene_dict())
    capsys.readouterr()
    assert main(["simulate", str(scene), "-o", str(copy), "--resume"]) == 2
    assert "no checkpoint.npz to resume from" in one_line_error(capsys)
    assert main(["run", str(scene), "-o", str(copy), "--until", "simulate"]) == 2
    assert snapshot(copy) == before
    # A simulate stopped before its first checkpoint (frame 0 only) starts over as before.
    (run_a / "checkpoint.npz").unlink()
    data = json.loads((run_a / "run.json").read_text())
    data["frames"] = data["frames"][:1]
    (run_a / "run.json").write_text(json.dumps(data))
    assert main(["simulate", str(scene), "-o", str(run_a), "--resume"]) == 0
    assert len(RunInfo.load(run_a).files("fluid")) == 4
