"""The typed run record (io/record.py): run.json read into models and written back byte for byte,
a bad field refused in one line naming run.json and the field, and each default in one place."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from whitecap.errors import InputError
from whitecap.geometry import obstacle_matrix, pose_matrix
from whitecap.io.record import OBSTACLE_COLOR, Frame, Obstacle, Pose
from whitecap.io.run import RunInfo

SIM = "0123456789abcdef"


def _run_json(tmp_path: Path) -> dict:
    """A run.json as a simulation with a moving body and an imported case's shape write them: ints
    and floats mixed, keys of a frame and an obstacle in their writers' orders, fields whitecap
    does not declare (friction, motion) and ones the frame lacks (no bodies, no particles)."""
    return {
        "particle_radius": 0.01, "rest_density": 1000.0, "particle_mass": 0.008, "gravity": [0, 0, -9.81],
        "domain": {"lower": [0.0, 0.0, 0.0], "upper": [0.5, 0.12, 0.3]}, "frame_rate": 30,
        "frames": [
            {"index": 0, "time": 0.0, "files": {"fluid": "fluid/fluid_00000.ply"}, "made_from": {"fluid": SIM},
             "bodies": [{"position": [0.0, 0.0, 0.0], "quaternion": [1.0, 0.0, 0.0, 0.0]}], "particles": 120},
            {"index": 1, "time": 0.0333, "files": {"fluid": "fluid/fluid_00001.ply", "mesh": "mesh/fluid_00001.ply"},
             "made_from": {"fluid": SIM, "mesh": SIM}, "mesh_settings": "aa", "render_key": "bb"},
        ],
        "obstacles": [
            {"mesh": "paddle.stl", "render_mesh": None, "translate": [0.2, 0.06, 0.15], "rotate": [0.0, 0.0, 0.0],
             "scale": 1.0, "friction": 0.2, "material": "stone", "color": [0.8, 0.78, 0.72], "texture": None,
             "motion": {"kind": "piston", "axis": [1, 0, 0]}, "dynamic": False},
            {"name": "tank", "role": "container", "source": "case.xml", "mesh": "geometry/tank.ply",
             "render_mesh": "geometry/tank.ply", "translate": [0.0, 0.0, 0.0], "rotate": [0.0, 0.0, 0.0], "scale": 1,
             "material": "glass"},
        ],
        "extra": {"name": "t", "seed": 3, "scene_dir": str(tmp_path), "kernel_support": 0.04, "blend": {"file": "x"}},
        "format": "whitecap-run", "version": 1, "up": "z", "simulation": SIM,
    }


def _write(tmp_path: Path, data: dict) -> Path:
    (tmp_path / "run.json").write_text(json.dumps(data, indent=1))
    return tmp_path / "run.json"


def test_a_run_json_round_trips_byte_for_byte(tmp_path):
    src = _write(tmp_path, _run_json(tmp_path))
    info = RunInfo.load(tmp_path)
    assert isinstance(info.frames[0], Frame) and isinstance(info.obstacles[1], Obstacle)
    assert isinstance(info.frames[0].bodies[0], Pose) and info.frames[1].bodies is None
    out = tmp_path / "again"
    out.mkdir()
    info.save(out)
    assert (out / "run.json").read_bytes() == src.read_bytes()
    # a frame recorded afterwards: the fields set, in their declared order, after the file's own
    info.set_file(2, "fluid", "fluid/fluid_00002.ply", 0.0667)
    info.frame(2).particles = 7
    info.save(out)
    assert list(json.loads((out / "run.json").read_text())["frames"][2]) == [
        "index", "time", "files", "made_from", "particles"]


def test_the_records_are_what_placement_and_pose_take(tmp_path):
    _write(tmp_path, _run_json(tmp_path))
    info = RunInfo.load(tmp_path)
    pose = Pose(position=[0.0, 0.0, 0.5], quaternion=[0.0, 0.0, 0.0, 1.0])  # half a turn about z, lifted
    info.set_bodies(1, [pose])
    assert info.body_pose(1, 0) == pose and info.body_pose(1, 1) is None and info.body_pose(5, 0) is None
    M = obstacle_matrix(info.obstacles[0], info.body_pose(1, 0))
    assert M[:3, 3] == pytest.approx([-0.2, -0.06, 0.65])
    assert pose_matrix(None) == pytest.approx(pose_matrix(Pose(position=[0, 0, 0], quaternion=[1, 0, 0, 0])))


@pytest.mark.parametrize("field,tamper", [
    ("particle_mass", lambda d: d.update(particle_mass=-1.0)),
    ("domain.upper", lambda d: d["domain"].update(upper=[1, 1])),
    ("frames[0].time", lambda d: d["frames"][0].update(time="0")),
    ("frames[0].bodies[0].quaternion", lambda d: d["frames"][0]["bodies"][0].update(quaternion=[1, 1, 0, 0])),
    ("frames[1].made_from.mesh", lambda d: d["frames"][1]["made_from"].update(mesh=3)),
    ("obstacles[1].scale", lambda d: d["obstacles"][1].update(scale=0)),
    ("obstacles[0].translate", lambda d: d["obstacles"][0].update(translate=[0, "x", 0])),
    ("extra.kernel_support", lambda d: d["extra"].update(kernel_support=True)),
    ("version", lambda d: d.update(version=1.0)),
])
def test_a_bad_field_is_one_line_naming_run_json_and_the_field(tmp_path, field, tamper):
    data = _run_json(tmp_path)
    tamper(data)
    _write(tmp_path, data)
    with pytest.raises(InputError) as err:
        RunInfo.load(tmp_path)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"{tmp_path / 'run.json'}: field '{field}': "), msg


def test_a_missing_field_is_named(tmp_path):
    data = _run_json(tmp_path)
    del data["frames"][1]["files"]
    _write(tmp_path, data)
    with pytest.raises(InputError, match=r"run.json: missing field 'frames\[1\].files'$"):
        RunInfo.load(tmp_path)


def test_defaults_come_from_the_records(tmp_path):
    # an obstacle entry with its mesh alone: placed at rest, stone, the preset's colour, no texture
    o = Obstacle.model_validate({"mesh": "m.stl"})
    assert (o.translate, o.rotate, o.scale, o.material, o.color, o.texture) == (
        [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 1.0, "stone", None, None)
    assert o.render_file == "m.stl" and o.model_dump() == {"mesh": "m.stl"}  # defaults are not written
    # the scene's own [[obstacle]] takes the same placement and look
    from whitecap.config import Obstacle as SceneObstacle

    scene = SceneObstacle(mesh="m.stl")
    assert (scene.translate, scene.rotate, scene.scale, scene.material) == (o.translate, o.rotate, o.scale, o.material)
    assert tuple(scene.color) == OBSTACLE_COLOR
    # a frame without a time is at index / frame rate
    data = _run_json(tmp_path)
    del data["frames"][1]["time"]
    _write(tmp_path, data)
    info = RunInfo.load(tmp_path)
    assert info.frames[1].time is None and info.time(1) == pytest.approx(1 / 30) and info.time(0) == 0.0


def test_the_records_load_without_pydantic_as_in_blenders_python(tmp_path):
    # The add-on's copy of io/record.py and io/run.py (the files `whitecap blender-addon` puts in
    # the extension) runs in Blender's own Python, which has no pydantic: the same records, filled
    # from the file unchecked, with the same defaults.
    from whitecap.render.driver import addon_shared_files

    _write(tmp_path, _run_json(tmp_path))
    ext = tmp_path / "extension"
    for rel, data in addon_shared_files().items():
        (ext / rel).parent.mkdir(parents=True, exist_ok=True)
        (ext / rel).write_bytes(data)
    code = f"""
import sys
sys.path.insert(0, {str(ext)!r})
class NoPydantic:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("pydantic", "pydantic_core"):
            raise ImportError("no pydantic here")
sys.meta_path.insert(0, NoPydantic())
from whitecap.io import record
from whitecap.io.run import RunInfo
from whitecap import geometry
assert not record.HAVE_PYDANTIC and record.__file__.startswith({str(ext)!r})
info = RunInfo.load({str(tmp_path)!r})
f = info.frames[1]
assert f.index == 1 and f.bodies is None and f.files["mesh"] == "mesh/fluid_00001.ply"
assert info.frames[0].bodies[0].quaternion == [1.0, 0.0, 0.0, 0.0]
tank = info.obstacles[1]
assert (tank.render_file, tank.material, tank.color, tank.role, tank.source) == (
    "geometry/tank.ply", "glass", None, "container", "case.xml")
assert info.obstacles[0].friction == 0.2 and info.files("mesh") == [(1, "mesh/fluid_00001.ply")]
assert info.domain["upper"] == [0.5, 0.12, 0.3] and info.time(1) == 0.0333
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_saving_after_each_frame_dumps_only_the_entries_that_changed(tmp_path, monkeypatch):
    """Stages save run.json after every frame: the text is that of a whole dump, byte for byte, whatever
    changed (a field assigned, a file or poses set, frames dropped), yet each save dumps only the new or
    changed entries, so that a long run's saves do not grow with the frames before them."""
    _write(tmp_path, _run_json(tmp_path))
    info = RunInfo.load(tmp_path)
    whole = lambda: json.dumps(info.model_dump(), indent=1)  # noqa: E731
    dumped = []
    frame_dump = Frame.model_dump
    monkeypatch.setattr(Frame, "model_dump", lambda self, **kw: dumped.append(self.index) or frame_dump(self, **kw))
    assert info.dumps() == json.dumps(_run_json(tmp_path), indent=1) and dumped == [0, 1]
    for i in range(2, 40):
        dumped.clear()
        info.set_file(i, "fluid", f"fluid/fluid_{i:05d}.ply", i / 30)
        info.set_bodies(i, [{"position": [0.01 * i, 0.0, 0.0], "quaternion": [1.0, 0.0, 0.0, 0.0]}])
        info.frame(i).particles = 120 + i
        assert info.dumps() == whole()
        assert dumped == [i]  # the new entry only (a whole dump does not call Frame.model_dump)
    changes = [(lambda: setattr(info.frame(7), "time", 0.5), [7]),
               (lambda: info.set_file(3, "mesh", "m/3.ply"), [3]),
               (lambda: setattr(info.frame(9), "render_key", "cc"), [9]),
               (lambda: info.extra.update(k="\0frames\0"), [])]
    for change, entries in changes:
        change()
        dumped.clear()
        assert info.dumps() == whole() and dumped == entries
    info.set_file(45, "fluid", "fluid/fluid_00045.ply")
    info.set_file(41, "fluid", "fluid/fluid_00041.ply")  # a frame between others: kept in index order
    assert [f.index for f in info.frames][-3:] == [39, 41, 45] and info.dumps() == whole()
    info.truncate(20)
    assert info.dumps() == whole()
    info.save(tmp_path)
    assert RunInfo.load(tmp_path).dumps() == (tmp_path / "run.json").read_text() == whole()
