"""`whitecap export --to usd|abc`: a whole run as one USD stage or Alembic archive, read back
with pxr alone and with Blender's own USD and Alembic importers (bpy in a child process)."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from whitecap import io as wio
from whitecap.cli import main
from whitecap.geometry import obstacle_matrix
from whitecap.io.diffuse_types import DIFFUSE_RADIUS, TYPE_NAMES
from whitecap.io.mesh import read_mesh
from whitecap.io.run import RunInfo
from whitecap.pipeline import export, mesh

from .conftest import BPY_END
from .test_surface_export import synthetic_diffuse

pxr = pytest.importorskip("pxr")
from pxr import Sdf, Usd, UsdGeom, UsdValidation  # noqa: E402

SRC = Path(__file__).resolve().parents[1] / "src"
FRAMES = (1, 3)  # the frames read back in Blender
SPRAY_RADIUS = [0.001, 0.002]  # [render] spray_radius of the test run [m]; foam and bubbles keep the defaults


def add_moving_block(run: Path) -> None:
    """A 8 cm block obstacle that turns 10° about z and rises 2 cm per frame (run.json poses)."""
    import trimesh

    trimesh.creation.box(extents=(0.08, 0.08, 0.08)).export(run / "block.obj")
    meta = json.loads((run / "run.json").read_text())
    meta["obstacles"] = [{"mesh": "block.obj", "translate": [0.45, 0.1, 0.06], "color": [0.9, 0.1, 0.1]}]
    meta["extra"]["scene_dir"] = str(run)
    for f in meta["frames"]:
        a = math.radians(10 * f["index"])
        f["bodies"] = [{"position": [0.0, 0.01 * f["index"], 0.02 * f["index"]],
                        "quaternion": [math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)]}]
    (run / "run.json").write_text(json.dumps(meta))


def set_render(run: Path, **render) -> None:
    """Change [render] keys in the run's scene.toml (what `whitecap render` and export read)."""
    import tomllib

    import tomli_w

    scene = tomllib.loads((run / "scene.toml").read_text())
    scene.setdefault("render", {}).update(render)
    (run / "scene.toml").write_text(tomli_w.dumps(scene))


@pytest.fixture(scope="module")
def scene_run(tiny_run, tmp_path_factory) -> Path:
    """The tiny dam break, meshed, with synthetic diffuse particles, a moving obstacle and a
    camera that moves (start to end, orbiting) with depth of field."""
    run = tmp_path_factory.mktemp("scene") / "run"
    shutil.copytree(tiny_run, run)
    mesh(run, jobs=1, show_progress=False)
    synthetic_diffuse(run)
    add_moving_block(run)
    set_render(run, camera_start=[0.3, -0.8, 0.5], camera_end=[0.9, -0.6, 0.4], camera_orbit=20.0, fstop=2.8,
               spray_radius=SPRAY_RADIUS)
    return run


@pytest.fixture(scope="module")
def usd_path(scene_run) -> Path:
    written = export(scene_run, to="usd", show_progress=False)
    assert "note" not in written
    return written["usd"]


def diffuse_counts(run: Path, i: int) -> dict[str, int]:
    t = wio.read(run / f"diffuse/diffuse_{i:05d}.ply").arrays["type"]
    return {name: int((t == code).sum()) for code, name in enumerate(TYPE_NAMES)}


# ---------------------------------------------------------------------------- Blender reads it back
READ_BACK = r"""
import sys, json, bpy
from pathlib import Path
path, run, fps = sys.argv[1], Path(sys.argv[2]), float(sys.argv[3])
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
sc.render.fps, sc.render.fps_base = round(fps), round(fps) / fps  # Alembic times are seconds
if path.endswith(".abc"):
    bpy.ops.wm.alembic_import(filepath=path)
else:
    bpy.ops.wm.usd_import(filepath=path)
out = {"types": {o.name: o.type for o in bpy.data.objects}, "frames": {}}
for f in map(int, sys.argv[4:]):
    sc.frame_set(f)
    dg = bpy.context.evaluated_depsgraph_get()
    fr = out["frames"][f] = {}
    for o in bpy.data.objects:
        e = o.evaluated_get(dg)
        d = fr[o.name] = {"matrix": [list(r) for r in e.matrix_world]}
        if o.type in ("MESH", "POINTCLOUD"):
            geo = e.data
            d["count"] = len(geo.vertices) if o.type == "MESH" else len(geo.points)
            if "velocity" in geo.attributes:
                v = [0.0] * (3 * d["count"])
                geo.attributes["velocity"].data.foreach_get("vector", v)
                d["velocity"] = v
        if o.type == "CAMERA":
            d["lens"], d["sensor"] = o.data.lens, o.data.sensor_width
            d["fstop"], d["focus"] = o.data.dof.aperture_fstop, o.data.dof.focus_distance
# The renderer's own camera for the same run, at the same frames.
from whitecap.io.run import RunInfo
from whitecap.render.driver import render_settings
from whitecap.render.scene import build_scene
info = RunInfo.load(run)
meshed = [i for i, _ in info.files("mesh")]
build_scene(info, render_settings(run), "final", min(meshed), max(meshed), run_dir=run)
out["render_camera"] = {}
target = bpy.data.objects["camera_target"].location
for f in map(int, sys.argv[4:]):
    bpy.context.scene.frame_set(f)
    cam = bpy.data.objects["camera"]
    out["render_camera"][f] = [list(r) for r in cam.matrix_world]
    out["render_camera"][f].append((cam.matrix_world.translation - target).length)  # focus distance
print("JSON" + json.dumps(out))
"""


def read_back(path: Path, run: Path) -> dict:
    info = RunInfo.load(run)
    res = subprocess.run([sys.executable, "-c", READ_BACK + BPY_END, str(path), str(run), str(info.frame_rate),
                          *map(str, FRAMES)], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(SRC)})
    assert res.returncode == 0, res.stderr[-3000:]
    got = json.loads([ln for ln in res.stdout.splitlines() if ln.startswith("JSON")][-1][4:])
    got["frames"] = {int(k): v for k, v in got["frames"].items()}
    got["render_camera"] = {int(k): v for k, v in got["render_camera"].items()}
    return got


def check_read_back(got: dict, run: Path, points_type: str) -> None:
    """What Blender imported, at two frames, against the run's own files."""
    info = RunInfo.load(run)
    assert got["types"]["fluid"] == "MESH"
    for f in FRAMES:
        fr = got["frames"][f]
        m = read_mesh(run / f"mesh/fluid_{f:05d}.ply")
        assert fr["fluid"]["count"] == len(m.vertices) > 0
        # the velocities the meshing stage interpolated onto the surface, vertex for vertex
        v = np.array(fr["fluid"]["velocity"]).reshape(-1, 3)
        np.testing.assert_allclose(v, m.arrays["velocity"], atol=1e-6)
        assert np.abs(v).max() > 0
        for name, n in diffuse_counts(run, f).items():
            assert got["types"][name] == points_type
            assert fr[name]["count"] == n > 0, (f, name)
            assert len(fr[name]["velocity"]) == 3 * n
        # the moving body where run.json puts it
        want = obstacle_matrix(info.obstacles[0], info.body_pose(f, 0))
        np.testing.assert_allclose(fr["obstacle_0"]["matrix"], want, atol=1e-5)
        # the camera where the renderer puts it, focused where the renderer focuses
        matrix = got["render_camera"][f][:4]
        np.testing.assert_allclose(fr["camera"]["matrix"], matrix, atol=1e-5)
        assert fr["camera"]["lens"] == pytest.approx(32.0) and fr["camera"]["sensor"] == pytest.approx(36.0)
        assert fr["camera"]["fstop"] == pytest.approx(2.8, rel=1e-6)
    for name in ("obstacle_0", "camera"):  # both move
        assert not np.allclose(got["frames"][1][name]["matrix"], got["frames"][3][name]["matrix"], atol=1e-3)


def test_usd_read_back_in_blender(scene_run, usd_path):
    pytest.importorskip("bpy")
    got = read_back(usd_path, scene_run)
    check_read_back(got, scene_run, "POINTCLOUD")
    # Blender's USD importer reads a camera's focus distance at one time only: the stage's
    # own samples are checked against the renderer's focus (on its camera target) per frame.
    stage = Usd.Stage.Open(str(usd_path))
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/camera"))
    for f in FRAMES:
        assert cam.GetFocusDistanceAttr().Get(f) == pytest.approx(got["render_camera"][f][4], rel=1e-5)
    assert cam.GetFStopAttr().Get() == pytest.approx(2.8, rel=1e-6)


def test_alembic_read_back_in_blender(scene_run, tmp_path):
    pytest.importorskip("bpy")
    assert main(["export", str(scene_run), "--to", "abc", "--out", str(tmp_path / "abc")]) == 0
    path = tmp_path / "abc" / "scene.abc"
    assert sorted(p.name for p in path.parent.iterdir()) == ["export.json", "scene.abc"]  # no temporary USD left
    # Alembic has no point clouds in Blender's exporter: each type is a mesh of vertices only
    check_read_back(read_back(path, scene_run), scene_run, "MESH")


# ---------------------------------------------------------------------------- pxr alone
def test_usd_stage_content_and_validation(scene_run, usd_path, tmp_path):
    stage = Usd.Stage.Open(str(usd_path))
    info = RunInfo.load(scene_run)
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert stage.GetTimeCodesPerSecond() == info.frame_rate == 30.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 3)
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")

    fluid = UsdGeom.Mesh(stage.GetPrimAtPath("/World/fluid"))
    quantile_by_id: dict[int, float] = {}
    for f in range(4):
        m = read_mesh(scene_run / f"mesh/fluid_{f:05d}.ply")
        np.testing.assert_array_equal(np.array(fluid.GetPointsAttr().Get(f)), m.vertices)
        np.testing.assert_array_equal(np.array(fluid.GetFaceVertexIndicesAttr().Get(f)).reshape(-1, 3), m.faces)
        assert set(fluid.GetFaceVertexCountsAttr().Get(f)) == {3}
        np.testing.assert_array_equal(np.array(fluid.GetNormalsAttr().Get(f)), m.normals)
        np.testing.assert_array_equal(np.array(fluid.GetVelocitiesAttr().Get(f)), m.arrays["velocity"])
        d = wio.read(scene_run / f"diffuse/diffuse_{f:05d}.ply")
        for code, name in enumerate(TYPE_NAMES):
            p = UsdGeom.Points(stage.GetPrimAtPath(f"/World/diffuse/{name}"))
            keep = d.arrays["type"] == code
            np.testing.assert_array_equal(np.array(p.GetPointsAttr().Get(f)), d.positions[keep].astype(np.float32))
            np.testing.assert_array_equal(np.array(p.GetIdsAttr().Get(f)), d.ids[keep])
            np.testing.assert_allclose(np.array(p.GetVelocitiesAttr().Get(f)), d.velocities[keep], rtol=1e-6)
            # widths: the render radius range of the type ([render] spray_radius, or the default in
            # multiples of r), at a quantile fixed per particle
            w = np.array(p.GetWidthsAttr().Get(f))
            lo, hi = (2 * k for k in SPRAY_RADIUS) if name == "spray" else \
                (2 * k * info.particle_radius for k in DIFFUSE_RADIUS[code])
            assert len(w) == keep.sum() and ((w >= lo - 1e-7) & (w <= hi + 1e-7)).all()
            for i, q in zip(d.ids[keep], (w - lo) / (hi - lo)):  # a particle keeps its size, even across types
                assert quantile_by_id.setdefault(int(i), float(q)) == pytest.approx(float(q), abs=1e-5)
    q = np.array(list(quantile_by_id.values()))
    assert len(q) > 50 and q.min() < 0.1 and q.max() > 0.9  # spread over the range, not one size
    # The moving body: its pose of run.json at every frame, and half way between two frames
    # (what motion blur samples) turned half as far, still a rotation (no shrink as a blend of matrices gives).
    body = UsdGeom.Xformable(stage.GetPrimAtPath("/World/obstacles/obstacle_0"))
    for f in range(4):
        np.testing.assert_allclose(np.array(body.ComputeLocalToWorldTransform(f)).T,
                                   obstacle_matrix(info.obstacles[0], info.body_pose(f, 0)), atol=1e-9)
    half = np.array(body.ComputeLocalToWorldTransform(1.5)).T[:3, :3]
    np.testing.assert_allclose(half @ half.T, np.eye(3), atol=1e-9)
    assert math.degrees(math.atan2(half[1, 0], half[0, 0])) == pytest.approx(15.0)
    # Between frames a clip holds its frame (topology changes): motion blur comes from the velocities.
    assert len(fluid.GetPointsAttr().Get(1.5)) == len(fluid.GetPointsAttr().Get(1))

    # USD's own validators (usd-core 26 replaced UsdUtils.ComplianceChecker with UsdValidation) report nothing...
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    assert [e.GetMessage() for e in errors] == []
    # ...and do catch a stage without its units (so the check above can fail).
    shutil.copytree(usd_path.parent, tmp_path / "usd")
    broken = Usd.Stage.Open(str(tmp_path / "usd" / usd_path.name))
    assert not UsdValidation.ValidationContext(validators).Validate(broken)
    broken.GetRootLayer().ClearDefaultPrim()
    broken.GetRootLayer().pseudoRoot.ClearInfo("metersPerUnit")
    assert UsdValidation.ValidationContext(validators).Validate(broken)


def test_usd_opens_with_pxr_alone_after_moving_it(scene_run, tmp_path):
    """A fresh interpreter with nothing but pxr resolves the stage and its per-frame layers,
    also after the export directory moved (the stage names its layers by relative paths)."""
    export(scene_run, to="usd", out=tmp_path / "usd", show_progress=False)
    shutil.move(tmp_path / "usd", tmp_path / "moved")
    code = ("import sys; from pxr import Usd, UsdGeom; s = Usd.Stage.Open(sys.argv[1]); "
            "print(len(UsdGeom.Mesh(s.GetPrimAtPath('/World/fluid')).GetPointsAttr().Get(2) or []), "
            "'whitecap' in sys.modules)")
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path / "moved" / "scene.usd")], capture_output=True,
                         text=True, env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"}, cwd="/")
    assert res.returncode == 0, res.stderr
    n, imported = res.stdout.split()
    assert int(n) == len(read_mesh(scene_run / "mesh/fluid_00002.ply").vertices) and imported == "False"


# ---------------------------------------------------------------------------- points only, reruns, errors
def test_run_without_meshes_exports_points_only_and_says_so(tiny_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    assert not RunInfo.load(run).files("mesh")
    assert main(["export", str(run), "--to", "usd"]) == 0
    assert "points only" in capsys.readouterr().out
    stage = Usd.Stage.Open(str(run / "export/usd/scene.usd"))
    assert not stage.GetPrimAtPath("/World/fluid")
    p = UsdGeom.Points(stage.GetPrimAtPath("/World/fluid_particles"))
    for f in (0, 2):
        fr = wio.read(run / f"fluid/fluid_{f:05d}.ply")
        np.testing.assert_array_equal(np.array(p.GetPointsAttr().Get(f)), fr.positions)
        np.testing.assert_array_equal(np.array(p.GetVelocitiesAttr().Get(f)), fr.velocities)
        np.testing.assert_allclose(np.array(p.GetWidthsAttr().Get(f)), 2 * RunInfo.load(run).particle_radius)


def test_rerun_keeps_unchanged_frames_and_never_mixes_simulations(scene_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(scene_run, run, ignore=shutil.ignore_patterns("export"))
    first = export(run, to="usd", show_progress=False)["usd"]
    frames_dir = first.parent / "scene_frames"
    before = {p.name: p.stat().st_mtime_ns for p in frames_dir.iterdir()}
    assert len(before) == 4
    # frame 2's diffuse particles change: only its layer is made again, and the old one goes
    d = wio.read(run / "diffuse/diffuse_00002.ply")
    d.positions[:] += 0.01
    wio.write(run / "diffuse/diffuse_00002.ply", d)
    manifest = first.parent / "export.json"  # an interrupted export listed its layer before writing it
    m = json.loads(manifest.read_text())
    m["files"]["scene_frames/frame_00009_0123456789ab.usdc"] = None
    manifest.write_text(json.dumps(m))
    (frames_dir / "frame_00009_0123456789ab.usdc").write_bytes(b"left by an interrupted export")
    (frames_dir / "notes.txt").write_text("mine")
    export(run, to="usd", show_progress=False)
    assert (frames_dir / "notes.txt").read_text() == "mine"
    after = {p.name: p.stat().st_mtime_ns for p in frames_dir.iterdir() if p.name != "notes.txt"}
    assert len(after) == 4
    assert [n for n in after if n not in before] == [n for n in after if n.startswith("frame_00002_")]
    assert all(after[n] == before[n] for n in after if not n.startswith("frame_00002_"))
    stage = Usd.Stage.Open(str(first))
    spray = UsdGeom.Points(stage.GetPrimAtPath("/World/diffuse/spray")).GetPointsAttr().Get(2)
    np.testing.assert_array_equal(np.array(spray), d.positions[d.arrays["type"] == 0].astype(np.float32))


def test_export_scene_errors(tmp_path, scene_run, capsys):
    assert main(["export", str(tmp_path / "missing"), "--to", "usd"]) == 2
    err = capsys.readouterr().err
    assert "missing: no such run directory" in err and err.count("\n") == 1
    assert main(["export", str(scene_run), "--to", "fbx"]) == 2
    err = capsys.readouterr().err
    assert err == "error: export: unknown target 'fbx' (choose from vtk, ply, usd, abc)\n"
    run = tmp_path / "run"
    shutil.copytree(scene_run, run, ignore=shutil.ignore_patterns("export"))
    (run / "diffuse" / "diffuse_00002.ply").write_bytes(b"not a ply")  # found while writing frames
    assert main(["export", str(run), "--to", "usd"]) == 2
    err = capsys.readouterr().err
    assert "diffuse_00002.ply" in err and err.count("\n") == 1
    assert not (run / "export/usd/scene.usd").exists()  # no stage naming a half-made run


def test_missing_usd_core_says_how_to_install(scene_run, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "pxr", None)  # import pxr now raises ImportError
    assert main(["export", str(scene_run), "--to", "usd", "--out", str(scene_run / "nowhere")]) == 4
    err = capsys.readouterr().err
    assert "pip install 'whitecap[usd]'" in err and err.count("\n") == 1
    assert not (scene_run / "nowhere" / "scene.usd").exists()
