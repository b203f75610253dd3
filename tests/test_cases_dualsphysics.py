"""Whole DualSPHysics cases (`whitecap import`): tank, obstacles and moving bodies from the particles.

Synthetic cases are written here as PartVTK-like legacy VTK files (vtk's own
writer), so the tests need no data; the real dam break in ../shared runs where
it exists (CI has it beside the clone) and is skipped elsewhere.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from whitecap.cases import dualsphysics as D
from whitecap.cases.rigid_fit import apply_pose, fit_pose, fit_poses
from whitecap.cli import main
from whitecap.io.run import RunInfo

from .conftest import ADDON_LOAD_SCRIPT, BPY_END

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "dualsphysics_dambreak"
SRC = Path(__file__).resolve().parents[1] / "src"
DP = 0.02


# ---------------------------------------------------------------------------- synthetic PartVTK
def write_part_vtk(path: Path, pos, arrays: dict) -> None:
    """A legacy VTK POLYDATA of points with the given point arrays (as PartVTK writes them)."""
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    pd = vtk.vtkPolyData()
    pts = vtk.vtkPoints()
    pts.SetData(numpy_to_vtk(np.ascontiguousarray(pos, np.float32), deep=True))
    pd.SetPoints(pts)
    for name, a in arrays.items():
        arr = numpy_to_vtk(np.ascontiguousarray(a), deep=True)
        arr.SetName(name)
        pd.GetPointData().AddArray(arr)
    w = vtk.vtkPolyDataWriter()
    w.SetFileName(str(path))
    w.SetInputData(pd)
    w.SetFileTypeToBinary()
    assert w.Write() == 1


def cube_shell(n: int, origin) -> np.ndarray:
    """Particles on the surface of an n×n×n lattice block of spacing DP (a hollow cube of boundary particles)."""
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    shell = g[np.any((g == 0) | (g == n - 1), axis=1)]
    return np.asarray(origin, float) + (shell + 0.5) * DP


def rotation(angles_deg) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix()


def case_xml(blocks: str) -> str:
    """A DualSPHysics case XML of spacing DP whose <particles> lists ``blocks`` (one line per mk block)."""
    return f"""<?xml version="1.0" encoding="UTF-8" ?>
<case><casedef><constantsdef><rhop0 value="1000"/><gravity x="0" y="0" z="-9.81"/></constantsdef>
<geometry><definition dp="{DP}"><pointmin x="-0.1" y="-0.1" z="-0.1"/><pointmax x="1" y="1" z="1"/></definition>
</geometry></casedef>
<execution><parameters><parameter key="TimeOut" value="0.05"/></parameters>
<particles mkboundfirst="10" mkfluidfirst="1">
{blocks.strip()}</particles></execution></case>
"""


XML = case_xml("""
<fixed mkbound="0" mk="10" begin="0" count="1"/>
<floating mkbound="40" mk="50" begin="1" count="1"/>
<moving mkbound="50" mk="60" begin="2" count="1"/>
<fluid mkfluid="0" mk="1" begin="3" count="1"/>""")
N_FRAMES = 5


def motion(k: int):
    """The floating cube's known motion at frame k: rotation R_k about its centre, then a shift."""
    return rotation([7.0 * k, -5.0 * k, 11.0 * k]), np.array([0.03, -0.01, 0.02]) * k


def synthetic_case(folder: Path, noise: float = 0.01 * DP, frames: int = N_FRAMES, tiny_mk: bool = False,
                   drop: str | None = None) -> dict:
    """A tank floor (mk 10, fixed), a floating cube (mk 50) moved by :func:`motion` with noise
    ``noise`` per particle and frame, a still moving-type cube (mk 60) and a fluid block.
    Returns the cube's rest particles and per-frame particles."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "Case.xml").write_text(XML)
    rng = np.random.default_rng(1)
    g = np.stack(np.meshgrid(np.arange(30), np.arange(20), [0], indexing="ij"), -1).reshape(-1, 3)
    floor = (g + 0.5) * DP  # 0.6 × 0.4 m, one particle thick
    cube = cube_shell(6, [0.2, 0.15, 0.1])
    still = cube_shell(4, [0.45, 0.25, 0.02])
    if tiny_mk:
        still = still[:3]
    fluid = (np.stack(np.meshgrid(np.arange(8), np.arange(8), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
             + 0.5) * DP + [0.02, 0.02, 0.04]
    c0 = cube.mean(0)
    moved = []
    for k in range(frames):
        R, t = motion(k)
        cube_k = (cube - c0) @ R.T + c0 + t + rng.normal(0, noise, cube.shape)
        moved.append(cube_k)
        pos = np.concatenate([floor, cube_k, still, fluid])
        n = [len(floor), len(cube), len(still), len(fluid)]
        arrays = {
            "Idp": np.arange(len(pos), dtype=np.uint32),
            "Vel": np.zeros((len(pos), 3), np.float32),
            "Rhop": np.full(len(pos), 1000.0, np.float32),
            "Type": np.repeat(np.array([0, 2, 1, 3], np.uint8), n),
            "Mk": np.repeat(np.array([10, 50, 60, 1], np.uint16), n),
        }
        if drop:
            del arrays[drop]
        write_part_vtk(folder / f"PartAll_{k:04d}.vtk", pos, arrays)
        keep = arrays.get("Type", np.repeat(np.array([0, 2, 1, 3], np.uint8), n)) == 3
        write_part_vtk(folder / f"PartFluid_{k:04d}.vtk", pos[keep],
                       {"Idp": arrays["Idp"][keep], "Vel": arrays["Vel"][keep], "Rhop": arrays["Rhop"][keep]})
    return {"cube": cube, "moved": moved, "still": still, "floor": floor, "centre": c0}


def snapshot(path: Path) -> dict:
    """Every file under ``path`` with its size and modification time (missing: {})."""
    if not path.exists():
        return {}
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(path.rglob("*"))}


# ---------------------------------------------------------------------------- rigid fit
def test_fit_recovers_known_rotation_and_translation_of_a_noisy_cube():
    """Kabsch on a cube of boundary particles moved by a known rotation and translation per frame,
    with 0.01 dp of noise: the recovered poses carry the rest particles onto the frame's
    particles within 0.1 dp, and the still frame gets the identity."""
    rng = np.random.default_rng(3)
    cube = cube_shell(6, [0.2, 0.15, 0.1])
    c0 = cube.mean(0)
    frames = []
    for k in range(6):
        R, t = motion(k)
        frames.append((cube - c0) @ R.T + c0 + t + rng.normal(0, 0.01 * DP, cube.shape))
    poses = fit_poses(cube, frames)
    for k, (p, q) in enumerate(zip(poses, frames)):
        err = np.linalg.norm(apply_pose(p, cube) - q, axis=1).max()
        assert err < 0.1 * DP, (k, err / DP)
        R, _ = motion(k)
        M = apply_pose(p, np.eye(3) + c0) - apply_pose(p, np.zeros((1, 3)) + c0)  # rotation's columns
        assert np.abs(M.T - R).max() < 1e-3
    same = fit_pose(cube, cube)
    assert np.abs(np.array(same.quaternion) - [1, 0, 0, 0]).max() < 1e-9
    assert np.abs(same.position).max() < 1e-9
    # A spin past 180°: quaternion signs stay continuous from frame to frame (Blender interpolates
    # them per component, so a sign flip would swing the body the long way round between two frames).
    spin = fit_poses(cube, [(cube - c0) @ rotation([0, 0, 50 * k]).T + c0 for k in range(7)])
    qs = np.array([p.quaternion for p in spin])
    assert (np.sum(qs[1:] * qs[:-1], axis=1) > 0).all()


def test_fit_never_returns_a_reflection():
    """Points mirrored through a plane: the best orthogonal map is a reflection, the fit must
    still be a proper rotation (det +1)."""
    from whitecap.cases.rigid_fit import kabsch

    rng = np.random.default_rng(0)
    p = rng.random((50, 3))
    R, _ = kabsch(p, p * [1, 1, -1])
    assert np.linalg.det(R) == pytest.approx(1.0)


# ---------------------------------------------------------------------------- synthetic import
def test_import_fits_the_floating_cube_and_leaves_the_still_body_at_identity(tmp_path):
    """`whitecap import` of a synthetic case: the floating cube's poses in run.json reproduce its
    particles at every frame within 0.1 dp; the moving-type cube that never moves gets the
    identity; the floor is fixed (no poses) and written once under geometry/."""
    case = tmp_path / "case"
    s = synthetic_case(case)
    out = tmp_path / "run"
    assert main(["import", str(case), "--out", str(out)]) == 0
    info = RunInfo.load(out)
    names = [o.name for o in info.obstacles]
    roles = {o.name: o.role for o in info.obstacles}
    assert names[:2] == ["mk50", "mk60"] and roles["mk50"] == roles["mk60"] == "body"
    assert roles["mk10"] in ("obstacle", "container")
    for o in info.obstacles:
        assert not Path(o.mesh).is_absolute() and (out / o.mesh).is_file()
    assert len(info.files("fluid")) == N_FRAMES
    for k, f in enumerate(info.frames):
        assert f.time == pytest.approx(0.05 * k)
        cube_pose, still_pose = f.bodies
        err = np.linalg.norm(apply_pose(cube_pose, s["cube"]) - s["moved"][k], axis=1).max()
        assert err < 0.1 * DP, (k, err / DP)
        assert np.abs(np.array(still_pose.quaternion) - [1, 0, 0, 0]).max() < 1e-9
        assert np.abs(still_pose.position).max() < 1e-9
        assert len(f.bodies) == 2  # fixed shapes carry no pose


def test_floating_csv_places_the_body(tmp_path):
    """A FloatingInfo motion CSV (time, centre, roll/pitch/yaw) replaces the fit: the poses it gives
    carry the rest particles onto the frames' particles (no noise: within 1e-4 dp)."""
    case = tmp_path / "case"
    s = synthetic_case(case, noise=0.0)
    from scipy.spatial.transform import Rotation

    rows = ["time [s];fvel.x [m/s];center.x [m];center.y [m];center.z [m];roll [deg];pitch [deg];yaw [deg]"]
    for k in range(N_FRAMES):
        R, t = motion(k)
        roll, pitch, yaw = Rotation.from_matrix(R).as_euler("ZYX", degrees=True)[::-1]  # R = Rz(yaw)Ry(pitch)Rx(roll)
        c = s["centre"] + t
        rows.append(f"{0.05 * k:.6f};0;{c[0]:.9f};{c[1]:.9f};{c[2]:.9f};{roll:.9f};{pitch:.9f};{yaw:.9f}")
    csv = tmp_path / "FloatingMotion_mk50.csv"
    csv.write_text("\n".join(rows) + "\n")
    c = D.read_output(case, floating_csv=csv)
    body = next(x for x in c.shapes if x.name == "mk50")
    for k, p in enumerate(body.poses):
        assert np.abs(apply_pose(p, s["cube"]) - s["moved"][k]).max() < 1e-4 * DP


# ---------------------------------------------------------------------------- bad input
def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error:"), err
    return err


@pytest.mark.parametrize("missing", ["Type", "Mk"])
def test_missing_type_or_mk_array_is_one_line_error_and_writes_nothing(tmp_path, capsys, missing):
    case = tmp_path / "case"
    synthetic_case(case, frames=2, drop=missing)
    out = tmp_path / "run"
    assert main(["import", str(case), "--out", str(out)]) != 0
    err = one_line_error(capsys)
    assert "PartAll_0000.vtk" in err and f"'{missing}'" in err
    assert not out.exists()


def test_mk_with_fewer_than_4_particles_is_one_line_error_and_writes_nothing(tmp_path, capsys):
    case = tmp_path / "case"
    synthetic_case(case, frames=2, tiny_mk=True)
    out = tmp_path / "run"
    out.mkdir()
    (out / "keep.txt").write_text("earlier output")
    before = snapshot(out)
    assert main(["import", str(case), "--out", str(out)]) != 0
    err = one_line_error(capsys)
    assert "PartAll_0000.vtk" in err and "mk 60" in err and "3 particle" in err
    assert snapshot(out) == before


def test_floating_csv_with_other_times_is_one_line_error_and_writes_nothing(tmp_path, capsys):
    case = tmp_path / "case"
    synthetic_case(case, frames=3)
    csv = tmp_path / "FloatingMotion_mk50.csv"
    csv.write_text("time [s];center.x [m];center.y [m];center.z [m];roll [deg];pitch [deg];yaw [deg]\n"
                   + "".join(f"{0.07 * k};0.26;0.21;0.16;0;0;0\n" for k in range(3)))
    out = tmp_path / "run"
    assert main(["import", str(case), "--out", str(out), "--floating-csv", str(csv)]) != 0
    err = one_line_error(capsys)
    assert str(csv) in err and "time" in err
    assert not out.exists()


def test_folder_of_neither_solver_is_one_line_error(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("x")
    assert main(["import", str(tmp_path), "--out", str(tmp_path / "run")]) != 0
    err = one_line_error(capsys)
    assert "DualSPHysics" in err and str(tmp_path) in err
    assert not (tmp_path / "run").exists()


# ---------------------------------------------------------------------------- the shared dam break
needs_shared = pytest.mark.skipif(not (SHARED / "PartAll_0000.vtk").is_file(), reason=f"{SHARED} not present")


def subset(tmp_path: Path, frames=(0, 1, 2)) -> Path:
    """A folder of links to a few frames of the shared dam break (its PartAll_0000 and XML)."""
    d = tmp_path / "dambreak"
    d.mkdir()
    for name in ["CaseDambreak.xml", "PartAll_0000.vtk"] + [f"PartFluid_{i:04d}.vtk" for i in frames]:
        os.symlink(SHARED / name, d / name)
    return d


@pytest.fixture(scope="module")
def dambreak_run(tmp_path_factory) -> Path:
    if not (SHARED / "PartAll_0000.vtk").is_file():
        pytest.skip(f"{SHARED} not present")
    tmp = tmp_path_factory.mktemp("dsph")
    out = tmp / "run"
    assert main(["import", str(subset(tmp)), "--out", str(out)]) == 0
    return out


def _mesh(run: Path, name: str):
    import trimesh

    info = RunInfo.load(run)
    o = next(o for o in info.obstacles if o.name == name)
    return o, trimesh.load(run / o.mesh, force="mesh", process=False)


@needs_shared
def test_dambreak_tank_and_building_are_separate_obstacles(dambreak_run):
    """Mk 10 is the tank (the container); mk 11 and mk 20, one shape in the XML, are the building."""
    info = RunInfo.load(dambreak_run)
    got = {o.name: (o.role, o.source) for o in info.obstacles}
    assert got == {"Box": ("container", "mk 10"), "Building": ("obstacle", "mk 11,20")}
    assert all(f.bodies is None for f in info.frames)  # nothing moves


@needs_shared
def test_dambreak_building_matches_the_xml_box_within_one_dp(dambreak_run):
    """The XML's building is the box 0.12 × 0.12 × 0.45 m at (0.9, 0.24, 0): each of its six faces
    lies within one dp of the mesh's, and the mesh is closed."""
    _, m = _mesh(dambreak_run, "Building")
    lo, hi = np.array([0.9, 0.24, 0.0]), np.array([0.9 + 0.12, 0.24 + 0.12, 0.45])
    assert np.abs(m.bounds[0] - lo).max() <= DP * (1 + 1e-5), m.bounds
    assert np.abs(m.bounds[1] - hi).max() <= DP * (1 + 1e-5), m.bounds
    assert m.is_watertight
    # the faces are flat: every vertex lies on one of the box's six face planes or inside (no blob)
    assert m.volume == pytest.approx(628 * DP**3, rel=1e-6)  # the 628 particles' cells


def _hits_above(m, x: float, y: float, z: float) -> int:
    """Triangles of ``m`` a vertical ray up from (x, y, z) passes through."""
    t = m.triangles
    a, b, c = t[:, 0, :2], t[:, 1, :2], t[:, 2, :2]
    p = np.array([x, y])

    def cross(u, v):
        return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]

    d1, d2, d3 = cross(b - a, p - a), cross(c - b, p - b), cross(a - c, p - c)
    inside = ((d1 >= 0) & (d2 >= 0) & (d3 >= 0)) | ((d1 <= 0) & (d2 <= 0) & (d3 <= 0))
    return int((inside & (t[:, :, 2].max(1) > z) & (np.abs(cross(b - a, c - a)) > 0)).sum())


@needs_shared
def test_dambreak_tank_is_open_at_the_top_and_closed_below(dambreak_run):
    """A ray up from inside the tank meets nothing; one down meets the floor slab (two faces: its
    top and bottom), and the walls rise to the XML's height 0.4 m within one dp."""
    _, m = _mesh(dambreak_run, "Box")
    for x, y in ((0.3113, 0.2971), (0.8137, 0.1071), (1.4093, 0.6031)):  # off the cell lattice
        assert _hits_above(m, x, y, 0.1) == 0
        m2 = m.copy()
        m2.vertices[:, 2] *= -1  # a ray down = a ray up in the mirrored mesh
        assert _hits_above(m2, x, y, -0.1) == 2
    tol = DP * (1 + 1e-5)  # the mesh is stored in float32
    assert abs(m.bounds[1][2] - 0.4) <= tol and m.is_watertight
    assert np.abs(m.bounds[1][:2] - [1.6, 0.67]).max() <= tol and np.abs(m.bounds[0]).max() <= tol


@needs_shared
def test_foam_continues_from_an_imported_run(dambreak_run, tmp_path):
    """`whitecap foam RUN` on an imported run writes diffuse frames into it, made from the same simulation."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(dambreak_run, run)
    assert main(["foam", str(run)]) == 0
    info = RunInfo.load(run)
    assert [i for i, _ in info.files("diffuse")] == [i for i, _ in info.files("fluid")] == [0, 1, 2]
    assert len(info.obstacles) == 2


def test_import_resumes_and_refuses_another_simulation(tmp_path, capsys):
    """A second import of the same case converts nothing again; a different case into the same
    directory is refused with one line and leaves it as it was."""
    case = tmp_path / "case"
    synthetic_case(case, frames=2)
    out = tmp_path / "run"
    assert main(["import", str(case), "--out", str(out)]) == 0
    before = snapshot(out / "fluid")
    assert main(["import", str(case), "--out", str(out)]) == 0
    assert snapshot(out / "fluid") == before
    other = tmp_path / "other"
    synthetic_case(other, frames=3)
    whole = snapshot(out)
    capsys.readouterr()
    assert main(["import", str(other), "--out", str(out)]) != 0
    assert "another simulation" in one_line_error(capsys)
    assert snapshot(out) == whole


# ---------------------------------------------------------------------------- render
RENDER = r"""
import sys, json, bpy, numpy as np
from pathlib import Path
from mathutils import Vector
from bpy_extras.object_utils import world_to_camera_view
from whitecap.config import Render
from whitecap.io.run import RunInfo
from whitecap.render.scene import build_scene, load_frame
run, out = Path(sys.argv[1]), Path(sys.argv[2])
info = RunInfo.load(run)
# [render] container = "glass" asks for whitecap's own tank: the imported one must win
cfg = Render(preview_resolution=[160, 120], preview_samples=8, device="cpu", glare=0.0, motion_blur=False,
             container="glass")
res = {}
for name in ("with", "without"):
    h = build_scene(info, cfg, "preview", 0, 0, run_dir=run)
    load_frame(h, run, info, 0)
    sc = bpy.context.scene
    objs = {o.name: o for o in sc.objects if o.name.startswith("obstacle_")}
    k = next(k for k, o in enumerate(info.obstacles) if o.name == "Building")
    b = objs.get(f"obstacle_{k}")
    res[name] = {"objects": sorted(objs), "container": bpy.data.objects.get("container") is not None}
    if b is not None:
        res[name]["uv"] = [list(world_to_camera_view(sc, sc.camera, b.matrix_world @ Vector(c)))[:2]
                           for c in b.bound_box]
        corners = [b.matrix_world @ Vector(c) for c in b.bound_box]
        top = max(c.z for c in corners)
        roof = sum((c for c in corners if c.z == top), Vector()) / 4  # the roof's centre: seen over the tank's wall
        res[name]["centre_uv"] = list(world_to_camera_view(sc, sc.camera, roof))[:2]
        b.hide_render = name == "without"
    sc.render.filepath = str(out / f"{name}.png")
    bpy.ops.render.render(write_still=True)
print(json.dumps(res))
"""


@needs_shared
def test_preview_shows_the_building_where_it_projects(dambreak_run, tmp_path):
    """A preview frame of the imported dam break, rendered with and without the building: the
    pixels where the building's box projects change (the building is drawn there, in front of
    the water and the tank), the imported tank replaces the drawn glass container even where
    [render] asks for glass, and both obstacles are in."""
    import shutil

    import imageio.v2 as imageio
    import trimesh

    run = tmp_path / "run"
    shutil.copytree(dambreak_run, run)
    info = RunInfo.load(run)
    fr = __import__("whitecap.io", fromlist=["read"]).read(run / info.files("fluid")[0][1])
    hull = trimesh.convex.convex_hull(fr.positions)  # a stand-in for the water surface
    from whitecap.io import write_mesh
    from whitecap.io.mesh import SurfaceMesh

    write_mesh(run / "mesh/fluid_00000.ply", SurfaceMesh(hull.vertices, hull.faces))
    info.set_file(0, "mesh", "mesh/fluid_00000.ply")
    info.save(run)
    p = subprocess.run([sys.executable, "-c", RENDER + BPY_END, str(run), str(tmp_path)], capture_output=True,
                       text=True, env={**os.environ, "PYTHONPATH": str(SRC)})
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads([ln for ln in p.stdout.splitlines() if ln.startswith("{")][-1])
    assert res["with"]["objects"] == ["obstacle_0", "obstacle_1"] and not res["with"]["container"]
    a = imageio.imread(tmp_path / "with.png")[..., :3].astype(float)
    b = imageio.imread(tmp_path / "without.png")[..., :3].astype(float)
    h, w = a.shape[:2]
    u, v = res["with"]["centre_uv"]
    assert 0.05 < u < 0.95 and 0.05 < v < 0.95, res
    y, x = int((1 - v) * h), int(u * w)
    inside = np.abs(a[y - 1:y + 2, x - 1:x + 2] - b[y - 1:y + 2, x - 1:x + 2]).mean()
    uv = np.array(res["with"]["uv"])
    x0, x1 = int(uv[:, 0].min() * w) - 3, int(uv[:, 0].max() * w) + 3
    y0, y1 = int((1 - uv[:, 1].max()) * h) - 3, int((1 - uv[:, 1].min()) * h) + 3
    diff = np.abs(a - b).mean(2)
    sl = (slice(max(y0, 0), y1), slice(max(x0, 0), x1))
    outside = diff.copy()
    outside[sl] = 0
    # terracotta (the obstacle's clay colour, R > B after AgX) where the building projects; the bluish-grey tank
    # and water have none
    red_with = int(((a[sl][..., 0] - a[sl][..., 2]) > 8).sum())
    red_without = int(((b[sl][..., 0] - b[sl][..., 2]) > 8).sum())
    # measured (160×120, 8 samples): roof 17.7 levels, projected box 23.0, outside it 1.1; 208 reddish pixels, 0 without
    assert inside > 8, inside  # 8-bit levels at the roof's centre
    assert diff[sl].mean() > 10 and diff[sl].mean() > 5 * outside.mean(), (diff[sl].mean(), outside.mean())
    assert red_with >= 15 and red_without == 0, (red_with, red_without)


ADDON = ADDON_LOAD_SCRIPT + r"""
res = {}
for o in sc.objects:
    if o.name.startswith("obstacle_"):
        keys = {}
        for f in range(sc.frame_start, sc.frame_end + 1):
            sc.frame_set(f)
            keys[f] = [list(o.matrix_world @ v.co) for v in o.data.vertices[:4]]
        res[o.name] = {"n": len(o.data.vertices), "keys": keys}
print(json.dumps(res))
"""


def test_blender_addon_shows_imported_shapes_and_moves_the_body(tmp_path):
    """The Blender add-on loads an imported run (mesh paths relative to the run, which has been
    moved since the import): every shape is there, and the floating cube's vertices follow the
    poses of run.json, frame by frame."""
    import shutil

    import trimesh

    pytest.importorskip("bpy")
    case = tmp_path / "case"
    synthetic_case(case, frames=3)
    assert main(["import", str(case), "--out", str(tmp_path / "run")]) == 0
    run = tmp_path / "moved"
    shutil.move(tmp_path / "run", run)  # a run directory stays valid when moved
    info = RunInfo.load(run)
    addon = SRC / "whitecap" / "render" / "addon" / "__init__.py"
    p = subprocess.run([sys.executable, "-c", ADDON + BPY_END, str(addon), str(run)], capture_output=True, text=True,
                       timeout=300, env={**os.environ, "PYTHONPATH": str(SRC)})
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads([ln for ln in p.stdout.splitlines() if ln.startswith("{")][-1])
    assert sorted(res) == [f"obstacle_{k}" for k in range(len(info.obstacles))]
    for k, o in enumerate(info.obstacles):
        m = trimesh.load(run / o.mesh, force="mesh", process=False)
        assert res[f"obstacle_{k}"]["n"] == len(m.vertices)
    cube = trimesh.load(run / info.obstacles[0].mesh, force="mesh", process=False)
    for i, f in enumerate(info.frames):
        want = apply_pose(f.bodies[0], np.asarray(cube.vertices[:4], float))
        got = np.array(res["obstacle_0"]["keys"][str(f.index)])
        assert np.abs(got - want).max() < 1e-5, (i, got, want)


@pytest.mark.parametrize("old, new", [('key="TimeOut" value="0.05"', 'key="TimeOut"'),
                                      ('<gravity x="0"', '<gravity x="down"')])
def test_case_xml_number_missing_or_not_a_number_is_one_line_error(tmp_path, old, new):
    from whitecap.cases.dualsphysics_xml import read_xml
    from whitecap.errors import InputError

    path = tmp_path / "case.xml"
    path.write_text(XML.replace(old, new))
    with pytest.raises(InputError) as err:
        read_xml(path)
    assert str(path) in str(err.value) and "expected a number" in str(err.value)
    assert len(str(err.value).splitlines()) == 1
