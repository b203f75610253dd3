"""Blender rendering (bpy, Cycles on the CPU) and the Blender add-on.

bpy runs in child processes (as `whitecap render` does), so these tests
inspect the saved scene.blend and the written images.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from whitecap import io
from whitecap.cli import main
from whitecap.errors import MissingDependency
from whitecap.io.run import RunInfo

from .conftest import BPY_END

pytest.importorskip("bpy")
SRC = Path(__file__).resolve().parents[1] / "src"
N_FOAM = {}


def write_mesh_ply(path: Path, verts, faces, vel, normals) -> None:
    names = ("x", "y", "z", "nx", "ny", "nz", "vx", "vy", "vz")
    v = np.empty(len(verts), dtype=[(k, "f4") for k in names])
    for k, a in zip(names, np.hstack([verts, normals, vel]).T):
        v[k] = a
    f = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
    f["vertex_indices"] = faces
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(f, "face")]).write(str(path))


@pytest.fixture(scope="module")
def meshed_run(tiny_run, tmp_path_factory) -> Path:
    """The tiny run plus contract meshes (convex hull of the particles, moving with their
    mean velocity) and synthetic diffuse particles of all three types."""
    import trimesh

    run = tmp_path_factory.mktemp("render") / "run"
    shutil.copytree(tiny_run, run)
    info = RunInfo.load(run)
    rng = np.random.default_rng(0)
    for i, rel in info.files("fluid"):
        fr = io.read(run / rel)
        m = trimesh.convex.convex_hull(fr.positions)
        vel = np.tile(fr.velocities.mean(0), (len(m.vertices), 1))
        write_mesh_ply(run / f"mesh/fluid_{i:05d}.ply", np.asarray(m.vertices), np.asarray(m.faces), vel,
                       np.asarray(m.vertex_normals))
        info.set_file(i, "mesh", f"mesh/fluid_{i:05d}.ply")
        n = 400
        types = rng.integers(0, 3, n).astype(np.uint8)
        N_FOAM[i] = int((types == 1).sum())
        pos = fr.positions[rng.integers(0, len(fr), n)] + [0, 0, 0.01]
        d = io.ParticleFrame(pos, np.zeros((n, 3)), np.arange(n) + 1000 * i, arrays={
            "type": types, "lifetime": np.ones(n, np.float32), "radius": np.full(n, 0.005, np.float32)})
        io.write(run / f"diffuse/diffuse_{i:05d}.ply", d)
        info.set_file(i, "diffuse", f"diffuse/diffuse_{i:05d}.ply")
    info.save(run)
    assert main(["render", str(run), "--quality", "preview", "--frames", "0:2"]) == 0
    return run


def blender(script: str, *args) -> dict:
    out = subprocess.run([sys.executable, "-c", script + BPY_END, *map(str, args)], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(SRC)})
    assert out.returncode == 0, out.stderr[-2000:]
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    assert lines, out.stdout[-2000:] + out.stderr[-2000:]
    return json.loads(lines[-1])


INSPECT = r"""
import sys, json, bpy, numpy as np
from bpy_extras.object_utils import world_to_camera_view
bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
sc = bpy.context.scene
sc.frame_set(0)
dg = bpy.context.evaluated_depsgraph_get()
fl = bpy.data.objects["fluid"]
pts = [fl.matrix_world @ v.co for v in fl.data.vertices]
uv = np.array([tuple(world_to_camera_view(sc, sc.camera, p))[:2] for p in pts])
foam = bpy.data.objects.get("foam")
geom = foam.evaluated_get(dg).evaluated_geometry() if foam is not None else None  # keep alive while pc is read
pc = geom.pointcloud if geom is not None else None
radii = [a.value for a in pc.attributes["radius"].data] if pc is not None else []
print(json.dumps({
  "uv_min": uv.min(0).tolist(), "uv_max": uv.max(0).tolist(),
  "foam_points": len(radii), "r_min": min(radii) if radii else 0, "r_max": max(radii) if radii else 0,
  "motion_blur": sc.render.use_motion_blur, "engine": sc.render.engine,
  "velocity_attr": "velocity" in fl.data.attributes, "size": [sc.render.resolution_x, sc.render.resolution_y],
}))
"""


def test_preview_frames_show_the_fluid(meshed_run):
    import imageio.v2 as imageio

    pngs = [meshed_run / "render" / f"frame_{i:05d}.png" for i in (0, 1)]
    assert all(p.exists() for p in pngs) and not (meshed_run / "render" / "frame_00002.png").exists()
    a, b = (imageio.imread(p)[..., :3].astype(float) for p in pngs)
    assert a.shape[:2] == (240, 320)
    assert a.std() > 5, "blank image"
    assert np.abs(a - b).mean() > 0.5, "the two frames are identical"
    assert_water_where_the_fluid_is(a, meshed_run)


def assert_water_where_the_fluid_is(a: np.ndarray, run: Path) -> None:
    """The fluid mesh's screen box in image ``a`` is tinted blue beyond the rest of the frame."""
    s = blender(INSPECT, run / "render" / "scene.blend")
    h, w = a.shape[:2]
    (u0, v0), (u1, v1) = s["uv_min"], s["uv_max"]
    # Image rows run top-down, camera-view v bottom-up.
    box = (slice(int((1 - v1) * h), int((1 - v0) * h)), slice(int(u0 * w), int(u1 * w)))
    inside = np.zeros(a.shape[:2], bool)
    inside[box] = True
    blue = a[..., 2] - a[..., 0]  # water is tinted blue; ground and sky behind it are grey/pale
    assert inside.sum() > 100
    assert blue[inside].mean() > blue[~inside].mean() + 3


def test_run_meshed_as_obj_renders_water(tiny_run, tmp_path):
    """`[mesh] format = "obj"` meshes are read through the io mesh registry, not parsed as PLY."""
    import imageio.v2 as imageio

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    assert main(["mesh", str(run), "--format", "obj", "--jobs", "1"]) == 0
    assert RunInfo.load(run).files("mesh")[0][1].endswith(".obj")
    assert main(["render", str(run), "--quality", "preview", "--frames", "0:1"]) == 0
    a = imageio.imread(run / "render" / "frame_00000.png")[..., :3].astype(float)
    assert a.std() > 5, "blank image"
    assert_water_where_the_fluid_is(a, run)


def test_foam_spheres_and_motion_blur(meshed_run):
    s = blender(INSPECT, meshed_run / "render" / "scene.blend")
    assert s["foam_points"] == N_FOAM[0]
    r = RunInfo.load(meshed_run).particle_radius
    # Foam is many small bubbles: 0.15-0.35 of the particle radius unless [render] says otherwise.
    assert 0.15 * r - 1e-9 <= s["r_min"] <= s["r_max"] <= 0.35 * r + 1e-9
    assert s["r_max"] > s["r_min"]  # random radii
    assert s["motion_blur"] and s["engine"] == "CYCLES" and s["velocity_attr"]


def test_movie_and_rerun_skips_done_frames(meshed_run):
    import imageio.v2 as imageio

    movie = meshed_run / "render" / "movie.mp4"
    assert imageio.get_reader(str(movie), format="FFMPEG").count_frames() == 2
    before = (meshed_run / "render" / "frame_00000.png").stat().st_mtime_ns
    assert main(["render", str(meshed_run), "--frames", "0:2"]) == 0
    assert (meshed_run / "render" / "frame_00000.png").stat().st_mtime_ns == before


def test_no_meshes_says_run_mesh_first(tiny_run, capsys):
    assert main(["render", str(tiny_run)]) != 0
    err = capsys.readouterr().err
    assert "whitecap mesh" in err and str(tiny_run) in err and len(err.strip().splitlines()) == 1


def test_render_workers_die_with_a_killed_parent(meshed_run, tmp_path):
    import signal
    import time

    from .test_errors import _alive, _children

    run = tmp_path / "run"
    shutil.copytree(meshed_run, run)
    # A final-quality frame takes minutes, so within the test the worker writes nothing to the
    # stdout pipe of its dead parent (which would end it by SIGPIPE anyway). Killed, the processes cannot remove
    # the temporary folders Blender made for them: TMPDIR puts those in the test's own folder.
    parent = subprocess.Popen([sys.executable, "-m", "whitecap.cli", "render", str(run), "--force", "--no-movie",
                               "--quality", "final"],
                              env={**os.environ, "PYTHONPATH": str(SRC), "TMPDIR": str(tmp_path)},
                              stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and parent.poll() is None and not workers:
            workers = [p for p in _children(parent.pid)
                       if b"whitecap.render.worker" in Path(f"/proc/{p}/cmdline").read_bytes()]
            time.sleep(0.1)
        time.sleep(2)  # let Blender start up and begin rendering
        assert parent.poll() is None and workers, "the render worker never started, or rendering ended too soon"
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and any(map(_alive, workers)):
            time.sleep(0.1)
        assert not any(map(_alive, workers)), "a Blender worker outlived its killed parent"
    finally:
        for p in [parent.pid, *workers]:
            try:
                os.kill(p, signal.SIGKILL)
            except OSError:
                pass


def test_missing_bpy_says_how_to_install(monkeypatch):
    import builtins

    from whitecap.render import require_bpy

    real = builtins.__import__

    def fake(name, *a, **k):
        if name == "bpy":
            raise ImportError("No module named 'bpy'")
        return real(name, *a, **k)

    monkeypatch.setitem(sys.modules, "bpy", None)
    monkeypatch.setattr(builtins, "__import__", fake)
    with pytest.raises(MissingDependency, match="pip install bpy==5.0.1"):
        require_bpy()


ADDON = r"""
import sys, json, zipfile, importlib.util, bpy, os
zip_path, tmp, seq_ply, seq_vtk = sys.argv[1:5]
zipfile.ZipFile(zip_path).extractall(os.path.join(tmp, "whitecap_sequences"))
sys.path.insert(0, tmp)
import whitecap_sequences as addon
bpy.ops.wm.read_factory_settings(use_empty=True)
addon.register()
res = {}
for key, path in (("ply", seq_ply), ("vtk", seq_vtk)):
    bpy.ops.whitecap.load(filepath=path)
    obj = [o for o in bpy.context.scene.objects if o.whitecap_seq.enabled][-1]
    sc = bpy.context.scene
    sc.frame_set(sc.frame_start)
    a = [tuple(v.co) for v in obj.data.vertices][:5]; na = len(obj.data.vertices)
    sc.frame_set(sc.frame_start + 1)
    b = [tuple(v.co) for v in obj.data.vertices][:5]
    res[key] = {"n": na, "changed": a != b, "velocity": "velocity" in obj.data.attributes}
print(json.dumps(res))
"""


def test_blender_addon_loads_sequences_and_follows_frames(tmp_path, meshed_run):
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    zip_path = tmp_path / "addon.zip"
    assert main(["blender-addon", "--out", str(zip_path)]) == 0
    names = zipfile.ZipFile(zip_path).namelist()
    assert "blender_manifest.toml" in names and "__init__.py" in names
    # A DualSPHysics-like PartVTK sequence: legacy binary POLYDATA points with a Vel array.
    vdir = tmp_path / "vtk"
    vdir.mkdir()
    for k in range(2):
        pts = np.random.default_rng(k).random((50, 3))
        poly = vtk.vtkPolyData()
        p = vtk.vtkPoints()
        p.SetData(numpy_to_vtk(pts))
        poly.SetPoints(p)
        vel = numpy_to_vtk(np.full((50, 3), float(k)))
        vel.SetName("Vel")
        poly.GetPointData().AddArray(vel)
        w = vtk.vtkPolyDataWriter()
        w.SetFileName(str(vdir / f"PartFluid_{k:04d}.vtk"))
        w.SetInputData(poly)
        w.SetFileTypeToBinary()
        w.Write()
    s = blender(ADDON, zip_path, tmp_path, meshed_run / "mesh" / "fluid_00000.ply", vdir / "PartFluid_0000.vtk")
    assert s["ply"]["n"] >= 8 and s["ply"]["changed"] and s["ply"]["velocity"]
    assert s["vtk"]["n"] == 50 and s["vtk"]["changed"] and s["vtk"]["velocity"]


def test_bad_frame_range(meshed_run, capsys):
    assert main(["render", str(meshed_run), "--frames", "x:y"]) != 0
    assert "--frames" in capsys.readouterr().err


DEVICE = ("import json; from whitecap.render.scene import cycles_device; "
          "print(json.dumps({'device': cycles_device('auto')}))")


def _has_gpu() -> bool:
    return blender(DEVICE)["device"] == "GPU"


@pytest.mark.gpu
def test_gpu_render_matches_the_cpu_frame(meshed_run, tmp_path):
    """Where Blender finds a GPU, `--device gpu` renders the frame the CPU renders (up to noise)."""
    import imageio.v2 as imageio

    if not _has_gpu():
        pytest.skip("Cycles finds no GPU here")
    run = tmp_path / "run"
    shutil.copytree(meshed_run, run)
    assert main(["render", str(run), "--frames", "0:1", "--force", "--device", "gpu", "--no-movie"]) == 0
    gpu = imageio.imread(run / "render" / "frame_00000.png")[..., :3].astype(float)
    cpu = imageio.imread(meshed_run / "render" / "frame_00000.png")[..., :3].astype(float)
    assert gpu.std() > 5, "blank image"
    assert np.abs(gpu - cpu).mean() < 8, "GPU and CPU frames differ beyond sampling noise"


def test_gpu_asked_for_without_one_is_one_line_error(meshed_run, capsys):
    if _has_gpu():
        pytest.skip("this machine has a GPU")
    assert main(["render", str(meshed_run), "--frames", "0:1", "--device", "gpu"]) != 0
    err = capsys.readouterr().err.strip()
    assert "render.device" in err and "no GPU" in err and len(err.splitlines()) == 1


BLUR = r"""
import sys, json, bpy, numpy as np
bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
sc = bpy.context.scene
sc.frame_set(0)
for name in ("spray", "foam", "bubbles"):
    bpy.data.objects[name].hide_render = True
me = bpy.data.objects["fluid"].data
n = len(me.vertices)
out = {}
for label, speed, blur in (("still", 0.0, True), ("moving", 3.0, True), ("moving_no_blur", 3.0, False)):
    me.attributes["velocity"].data.foreach_set("vector", np.tile([speed, 0.0, 0.0], n).astype(np.float32))
    me.update()
    sc.render.use_motion_blur = blur
    sc.render.filepath = sys.argv[2] + f"/{label}.png"
    bpy.ops.render.render(write_still=True)
    px = bpy.data.images.load(sc.render.filepath)
    out[label] = np.array(px.pixels[:]).reshape(-1, 4)[:, :3].tolist()
a, b, c = (np.array(out[k]) for k in ("still", "moving", "moving_no_blur"))
print(json.dumps({"blurred": float(np.abs(a - b).mean()), "unblurred": float(np.abs(a - c).mean())}))
"""


def test_motion_blur_follows_the_vertex_velocity_attribute(meshed_run, tmp_path):
    """Fluid meshes change topology every frame, so blur must come from the per-vertex
    `velocity` attribute: a fast mesh renders smeared, and only while motion blur is on."""
    s = blender(BLUR, meshed_run / "render" / "scene.blend", tmp_path)
    # measured: blurred 3.5e-3, unblurred 6e-6 (mean absolute change of linear RGB)
    assert s["blurred"] > 1e-3 and s["blurred"] > 50 * s["unblurred"], s


COPIES = r"""
import sys, json, bpy, numpy as np
from whitecap.render.scene import fill_mesh
from whitecap.blender.looks import sphere_nodes
obj = bpy.data.objects.new("d", bpy.data.meshes.new("d"))
bpy.context.scene.collection.objects.link(obj)
mod = obj.modifiers.new("n", "NODES")
mod.node_group = sphere_nodes("s", 0.001, 0.002, bpy.data.materials.new("m"), seed=2, copies=3, jitter=0.01)
rng = np.random.default_rng(0)
x, ids = rng.random((50, 3)), np.arange(50) + 7
out = {}
for label, order, shift in (("a", np.arange(50), 0.0), ("b", rng.permutation(50), 0.5)):
    fill_mesh(obj.data, x[order] + shift, np.zeros((0, 3), np.int32), None, ids=ids[order])
    dg = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    geom = ev.evaluated_geometry()
    pc = geom.pointcloud
    out[label] = [list(a.vector) for a in pc.attributes["position"].data]
out["x"] = x.tolist()
print(json.dumps(out))
"""


def test_render_copies_are_jittered_and_keep_their_place():
    """[render] diffuse_copies: k copies per diffuse particle near it, seeded by its id, so a
    particle's copies move with it from frame to frame whatever order the file lists it in."""
    s = blender(COPIES)
    a, b, x = (np.array(s[k]) for k in ("a", "b", "x"))
    assert len(a) == len(b) == 3 * len(x)
    d = np.linalg.norm(a[:, None] - x[None], axis=2).min(1)
    assert (d <= 0.01 * np.sqrt(3) + 1e-6).all() and (d > 1e-4).sum() == 2 * len(x)  # 2 jittered copies each
    # Frame b: every particle moved by 0.5 and listed in another order; its copies went along.

    def key(p):
        return p[np.lexsort(np.round(p, 6).T)]

    assert np.allclose(key(b - 0.5), key(a), atol=1e-5)


# ---------------------------------------------------------------------------- the stage
VARIANTS = r"""
import sys, json, bpy, numpy as np
from pathlib import Path
from bpy_extras.object_utils import world_to_camera_view
from whitecap.config import Render
from whitecap.io.run import RunInfo
from whitecap.render import stage
from whitecap.render.scene import build_scene, load_frame
run, out, variants = Path(sys.argv[1]), Path(sys.argv[2]), json.loads(sys.argv[3])
info = RunInfo.load(run)
first = min(i for i, _ in (info.files("mesh") or info.files("fluid")))
res = {}
for name, over in variants.items():
    render = over.pop("_render", True)
    cfg = Render(**{"preview_resolution": [160, 120], "preview_samples": 8, "device": "cpu", "glare": 0.0,
                    "motion_blur": False, **over})
    h = build_scene(info, cfg, "preview", first, first, run_dir=run)
    if info.files("mesh"):
        load_frame(h, run, info, first)
    sc = bpy.context.scene
    sc.frame_set(first)
    def uv(points):
        return [list(world_to_camera_view(sc, sc.camera, __import__("mathutils").Vector(p)))[:2] for p in points]
    lo, hi = stage.fluid_bounds(run, info)
    corners = [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    r = {"fluid_box_uv": uv(corners)}
    box = bpy.data.objects.get("container")
    if box is not None:
        v = np.array([list(box.matrix_world @ p.co) for p in box.data.vertices])
        r["container_vertices"] = v.tolist()
        # points along the four outer vertical edges (the outer shell's bottom and top rings)
        lo_o, hi_o = v.min(0), v.max(0)
        pts = [[x, y, lo_o[2] + t * (hi_o[2] - lo_o[2])] for x in (lo_o[0], hi_o[0]) for y in (lo_o[1], hi_o[1])
               for t in np.linspace(0.1, 0.9, 9)]
        r["edge_uv"] = uv(pts)
    dof = sc.camera.data.dof
    r["dof"] = {"use": dof.use_dof, "fstop": dof.aperture_fstop,
                "focus": list(dof.focus_object.matrix_world.translation) if dof.focus_object else None}
    r["view"] = [sc.view_settings.view_transform, sc.view_settings.exposure]
    obst = bpy.data.objects.get("obstacle_0")
    if obst is not None:
        r["obstacle_uv"] = uv([obst.matrix_world @ __import__("mathutils").Vector(c) for c in obst.bound_box])
    if render:
        sc.render.filepath = str(out / f"{name}.png")
        bpy.ops.render.render(write_still=True)
    res[name] = r
print(json.dumps(res))
"""


def variants(run: Path, out: Path, **named) -> dict:
    """Build the scene of ``run``'s first frame once per named set of [render] keys, render
    each to ``out/NAME.png`` (160×120, 8 samples; ``_render=False`` skips the render) and
    return what the script measured per variant."""
    out.mkdir(parents=True, exist_ok=True)
    return blender(VARIANTS, run, out, json.dumps(named))


def image(path: Path) -> np.ndarray:
    import imageio.v2 as imageio

    return imageio.imread(path)[..., :3].astype(float)


def test_glass_container_draws_the_walls(meshed_run, tmp_path):
    """A whitecap run's walls held the fluid, so its default container is a glass tank; its
    outer vertical edges change the pixels they project onto, compared with no container."""
    s = variants(meshed_run, tmp_path, default={}, glass={"container": "glass"}, none={"container": "none"})
    assert "container_vertices" in s["default"] and "container_vertices" not in s["none"]
    lo, hi = (np.array(RunInfo.load(meshed_run).domain[k]) for k in ("lower", "upper"))
    v = np.array(s["glass"]["container_vertices"])
    assert (v.min(0) < lo - 1e-6).all() and (v.max(0)[:2] > hi[:2] + 1e-6).all()  # walls of real thickness
    assert v.max(0)[2] == pytest.approx(hi[2])  # open at the top of the domain
    glass, none = image(tmp_path / "glass.png"), image(tmp_path / "none.png")
    assert np.abs(image(tmp_path / "default.png") - glass).mean() < 1e-9  # default = glass
    # Pixels along the four outer vertical edges of the tank, projected with the camera.
    h, w = glass.shape[:2]
    diffs = []
    for u, vv in s["glass"]["edge_uv"]:
        if 0.02 < u < 0.98 and 0.02 < vv < 0.98:
            y, x = int((1 - vv) * h), int(u * w)
            diffs.append(np.abs(glass[y - 1:y + 2, x - 1:x + 2] - none[y - 1:y + 2, x - 1:x + 2]).mean())
    assert len(diffs) >= 9
    # measured: median 30 (8-bit levels, AgX); 1.3 with the container hidden (the ground under it moves)
    assert np.median(diffs) > 15, diffs


WRITE_HDR = r"""
import sys, bpy
path, value = sys.argv[1], float(sys.argv[2])
img = bpy.data.images.new("env", 16, 8, float_buffer=True)
img.pixels[:] = [value, value, value, 1.0] * (16 * 8)
img.filepath_raw = path
img.file_format = "HDR"
img.save()
print("{}")
"""


def test_sky_and_hdri_light_the_scene(meshed_run, tmp_path):
    """The default physical sky (with its sun) and a user's HDRI both light the scene: the frame
    is much brighter than under a black world, and an HDRI of zeros gives the black frame."""
    for name, value in (("white.hdr", 1.0), ("black.hdr", 0.0)):
        blender(WRITE_HDR, tmp_path / name, value)
    s = variants(meshed_run, tmp_path, sky={}, sky_only={"sun_strength": 0.0},
                 hdri={"environment": str(tmp_path / "white.hdr")},
                 hdri_black={"environment": str(tmp_path / "black.hdr")},
                 black={"world_strength": 0.0, "sun_strength": 0.0})
    mean = {k: image(tmp_path / f"{k}.png").mean() for k in s}
    # measured (8-bit mean, AgX): sky 134, sky without the lamp 123, hdri 124, black 6.9 (the foam's own
    # glow), hdri_black 6.9; with the sky unlinked from the world: sky 67, sky without the lamp 10
    assert mean["sky"] > mean["black"] + 40, mean
    assert mean["sky_only"] > mean["black"] + 20, mean  # the sky's own light, without the sun lamp
    assert mean["hdri"] > mean["black"] + 40, mean
    assert mean["hdri_black"] < mean["black"] + 2, mean


def test_missing_hdri_is_a_one_line_error(meshed_run, tmp_path, capsys):
    import tomllib

    import tomli_w

    run = tmp_path / "run"
    shutil.copytree(meshed_run, run)
    scene = tomllib.loads((run / "scene.toml").read_text())
    scene.setdefault("render", {})["environment"] = "nowhere/studio.hdr"
    (run / "scene.toml").write_text(tomli_w.dumps(scene))
    assert main(["render", str(run), "--frames", "0:1", "--force", "--no-movie"]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "render.environment" in err and "studio.hdr" in err, err


def _box_width(uv) -> float:
    u = np.array(uv)[:, 0]
    return float(u.max() - u.min())


@pytest.mark.parametrize("source", ["whitecap run", "DualSPHysics sequence"])
def test_default_camera_frames_the_fluid(source, meshed_run, tmp_path):
    """With no camera keys the camera frames the fluid's bounds over the run (not the domain):
    projected with the camera at the first frame, they span at least half the image width
    and stay inside it."""
    if source == "whitecap run":
        run = meshed_run
    else:
        from whitecap.diffuse.driver import postprocess

        run = tmp_path / "dsph"
        postprocess(Path(__file__).parent / "data" / "dualsphysics", out=run, preset="auto", show_progress=False)
        assert main(["mesh", str(run), "--jobs", "1"]) == 0
        assert RunInfo.load(run).solid_walls() == []  # its box is only a bound: no glass by default
    s = variants(run, tmp_path / "img", default={"_render": False})["default"]
    uv = np.array(s["fluid_box_uv"])
    assert _box_width(uv) >= 0.5, uv
    assert (uv > -1e-6).all() and (uv < 1 + 1e-6).all(), uv
    assert source == "whitecap run" or "container_vertices" not in s


def cube_obj(path: Path) -> None:
    """A unit cube whose every face maps the whole texture (24 vertices, UVs per face)."""
    lines, faces = [], []
    quads = {0: [(0, 0, 0), (0, 1, 0), (0, 1, 1), (0, 0, 1)], 1: [(1, 0, 0), (1, 0, 1), (1, 1, 1), (1, 1, 0)],
             2: [(0, 0, 0), (0, 0, 1), (1, 0, 1), (1, 0, 0)], 3: [(0, 1, 0), (1, 1, 0), (1, 1, 1), (0, 1, 1)],
             4: [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], 5: [(0, 0, 1), (0, 1, 1), (1, 1, 1), (1, 0, 1)]}
    for f, corners in quads.items():
        for c in corners:
            lines.append("v %g %g %g" % tuple(np.subtract(c, 0.5)))
        b = 4 * f + 1
        faces += [(b, b + 1, b + 2), (b, b + 2, b + 3)]
    lines += ["vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1"]
    for f in range(6):
        b = 4 * f + 1
        lines += [f"f {b}/1 {b + 1}/2 {b + 2}/3", f"f {b}/1 {b + 2}/3 {b + 3}/4"]
    path.write_text("\n".join(lines) + "\n")


def test_red_texture_shows_on_the_cube(meshed_run, tmp_path):
    """An obstacle's `texture` is mapped by its mesh's UVs: a red image on a cube makes the
    pixels where the cube projects red (the preset colour is a pale grey)."""
    import imageio.v2 as imageio

    run = tmp_path / "run"
    shutil.copytree(meshed_run, run)
    cube_obj(tmp_path / "cube.obj")
    imageio.imwrite(tmp_path / "red.png", np.tile(np.array([230, 10, 10], np.uint8), (8, 8, 1)))
    info = RunInfo.load(run)
    info.obstacles = [{"mesh": str(tmp_path / "cube.obj"), "translate": [0.42, 0.1, 0.06], "scale": 0.1,
                       "material": "plastic", "texture": str(tmp_path / "red.png")}]
    info.save(run)
    s = variants(run, tmp_path / "img", textured={"container": "none"})["textured"]
    img = image(tmp_path / "img" / "textured.png")
    h, w = img.shape[:2]
    u, v = np.array(s["obstacle_uv"]).mean(0)  # the cube's centre, projected
    assert 0.1 < u < 0.9 and 0.1 < v < 0.9
    y, x = int((1 - v) * h), int(u * w)
    r, g, b = img[y - 2:y + 3, x - 2:x + 3].reshape(-1, 3).mean(0)
    assert r > g + 60 and r > b + 60, (r, g, b)


def test_exposure_and_depth_of_field(meshed_run, tmp_path):
    """`exposure` brightens the AgX image by that many stops; `fstop` turns depth of field on,
    focused on `focus_target`."""
    s = variants(meshed_run, tmp_path, base={}, bright={"exposure": 1.5},
                 dof={"_render": False, "fstop": 2.8, "focus_target": [0.1, 0.1, 0.1]})
    assert s["base"]["view"] == ["AgX", 0.0] and not s["base"]["dof"]["use"]
    assert image(tmp_path / "bright.png").mean() > image(tmp_path / "base.png").mean() + 15
    assert s["dof"]["dof"]["use"] and s["dof"]["dof"]["fstop"] == pytest.approx(2.8)
    assert s["dof"]["dof"]["focus"] == pytest.approx([0.1, 0.1, 0.1])


def test_small_fluid_pieces_are_found_by_their_volume():
    """[render] droplet_particles: a fluid mesh of a 0.2 m box of water and two 1 cm cubes (lone
    particles' blobs): only the cubes' faces are marked, and a threshold below a cube's volume
    marks none."""
    from whitecap.render.scene import small_pieces

    def cube(lo, size):
        c = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * size + lo
        q = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        return c, np.array([t for a, b, c_, d in q for t in ((a, b, c_), (a, c_, d))])

    parts = [cube([0, 0, 0], 0.2), cube([0.5, 0, 0], 0.01), cube([0.7, 0.1, 0.3], 0.01)]
    verts, faces, off = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + off)
        off += len(v)
    verts, faces = np.vstack(verts), np.vstack(faces)
    small = small_pieces(verts, faces, 8 * 1e-6)  # eight particles of 1e-6 m³
    assert not small[:12].any() and small[12:].all()
    assert not small_pieces(verts, faces, 0.5e-6).any()
