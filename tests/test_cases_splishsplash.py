"""SPlisHSPlasH cases (whitecap.cases.splishsplash): fluid ordered by id, the tank as the
container, the floating sphere as a moving body whose poses reproduce the solver's own
per-frame meshes, and one-line errors for bad input.

tests/data/splishsplash_rigid is a cut of the real SPlisHSPlasH 2.16 output in
../shared/data/splishsplash_rigid (frames 1, 29, 30; 40 fluid particles; see its
make_tiny.py). The tests on the full output skip when that folder is absent.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from whitecap.cases import splishsplash
from whitecap.errors import InputError
from whitecap.geometry import pose_matrix
from whitecap.io import read, read_mesh
from whitecap.io.axes import to_z_up
from whitecap.io.record import Pose

TINY = Path(__file__).resolve().parent / "data" / "splishsplash_rigid"
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "splishsplash_rigid"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="shared SPlisHSPlasH data not present")

TOL = 1e-4  # [m] the tolerance for poses against the exported meshes
# A particle followed from frame k to k+1 moves as its velocities say: |Δx − ½(v_k + v_k+1)·Δt|
# is small. Measured on the sample: median ≤ 0.0075 m, largest 0.116 m (a splash at 9.6 m/s,
# with frames up to one 5 ms step late); rows holding different particles are off by a median of about 1.8 m.
MEDIAN_RESIDUAL = 0.015  # [m] a quarter of the particle spacing 2r = 0.06 m
MAX_RESIDUAL = 0.2  # [m]
ROW_JUMP = 0.5  # [m] median residual of rows that hold different particles (measured 1.8 m)


def write_splishsplash_vtk(path: Path, pos, ids, vel, density) -> None:
    """A particle file in SPlisHSPlasH's legacy VTK layout (binary, big-endian): POINTS,
    one VTK_VERTEX cell per particle, ``id`` as unsigned_int SCALARS, velocity and density
    as FIELD arrays."""
    pos = np.asarray(pos, ">f4").reshape(-1, 3)
    n = len(pos)
    parts = [b"# vtk DataFile Version 4.1\nSPlisHSPlasH particle data\nBINARY\nDATASET UNSTRUCTURED_GRID\n",
             f"POINTS {n} float\n".encode(), pos.tobytes(), b"\n",
             f"CELLS {n} {2 * n}\n".encode(),
             np.stack([np.ones(n), np.arange(n)], 1).astype(">i4").tobytes(), b"\n",
             f"CELL_TYPES {n}\n".encode(), np.ones(n, ">i4").tobytes(), b"\n",
             f"POINT_DATA {n}\n".encode()]
    if ids is not None:
        parts += [b"SCALARS id unsigned_int 1\nLOOKUP_TABLE id_table\n", np.asarray(ids, ">u4").tobytes(), b"\n"]
    parts += [b"FIELD FieldData 2\n", f"velocity 3 {n} float\n".encode(), np.asarray(vel, ">f4").tobytes(), b"\n",
              f"density 1 {n} float\n".encode(), np.asarray(density, ">f4").tobytes(), b"\n"]
    Path(path).write_bytes(b"".join(parts))


def _copy(tmp_path: Path, src: Path = TINY) -> Path:
    out = tmp_path / "case"
    shutil.copytree(src, out, ignore=shutil.ignore_patterns("*.py", "__pycache__"))
    return out


def _z_up(v) -> np.ndarray:
    return np.asarray(to_z_up(np.asarray(v, np.float32), None, "y")[0], np.float64)


def _posed(pose, points: np.ndarray) -> np.ndarray:
    """Rest-placement points carried by a run.json pose (a record or its dict), through the project's one transform."""
    M = pose_matrix(Pose.model_validate(pose))
    return points @ M[:3, :3].T + M[:3, 3]


def _kinematic_residual(a, b, dt: float) -> np.ndarray:
    """Per row, how far frame b's position is from frame a's carried by the mean velocity [m]."""
    return np.linalg.norm(b.positions - a.positions - 0.5 * (a.velocities + b.velocities) * dt, axis=1)


def _by_role(case, role: str):
    return [s for s in case.shapes if s.role == role]


def _check_tank_and_sphere(case, n_frames: int) -> None:
    (tank,) = _by_role(case, "container")
    (sphere,) = _by_role(case, "body")
    assert len(case.shapes) == 2
    # the tank: unit box ×3.1 at (0, 1.5, 0), y up -> z up: x, y in ±1.55, z from −0.05 to 3.05
    assert tank.poses is None
    np.testing.assert_allclose(tank.vertices.min(0), [-1.55, -1.55, -0.05], atol=1e-5)
    np.testing.assert_allclose(tank.vertices.max(0), [1.55, 1.55, 3.05], atol=1e-5)
    # the sphere: radius 0.5 about (0.005, 0.99985, 0) y up at the first frame
    centre = sphere.vertices.mean(0)
    np.testing.assert_allclose(centre, [0.005, 0.0, 0.99985], atol=2e-3)
    np.testing.assert_allclose(np.linalg.norm(sphere.vertices - centre, axis=1).max(), 0.5, atol=2e-3)
    assert len(sphere.poses) == n_frames
    assert sphere.poses[0].position == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)  # at rest at the first frame
    assert sphere.poses[0].quaternion == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-9)
    assert np.linalg.norm(sphere.poses[-1].position) > 0.1  # it moved


def _check_constants(case) -> None:
    assert case.solver == "splishsplash"
    assert case.particle_radius == pytest.approx(0.03)
    assert case.frame_dt == pytest.approx(0.04)
    assert case.rest_density == pytest.approx(1000.0)
    assert case.particle_mass == pytest.approx(0.1728)  # 1000 · 0.8 · 0.06³ (the sample's README)
    np.testing.assert_allclose(case.gravity, [0.0, 0.0, -9.81], atol=1e-12)
    assert case.times == pytest.approx([(k - 1) * 0.04 for k, _ in case.fluid])


def _check_poses_reproduce_obj(case, obj_dir: Path, frames) -> float:
    """Carry frame 1's exported sphere mesh by each frame's pose; compare vertex by vertex
    with that frame's exported mesh (both turned z up). Returns the largest error."""
    (sphere,) = _by_role(case, "body")
    rest = _z_up(read_mesh(obj_dir / "rb_data_1_1.obj").vertices)
    # the case's rest mesh is frame 1's mesh (as a set: the model's vertex order differs)
    from scipy.spatial import cKDTree

    assert cKDTree(rest).query(sphere.vertices)[0].max() < TOL
    pose_of = dict(zip([k for k, _ in case.fluid], sphere.poses))
    worst = 0.0
    for k in frames:
        exported = _z_up(read_mesh(obj_dir / f"rb_data_1_{k}.obj").vertices)
        worst = max(worst, float(np.abs(_posed(pose_of[k], rest) - exported).max()))
    return worst


# ============================================================================ the committed cut
def test_tiny_case_finds_tank_as_container_and_sphere_as_moving_body():
    assert splishsplash.is_case(TINY)
    case = splishsplash.read_output(TINY)
    assert [k for k, _ in case.fluid] == [1, 29, 30]
    _check_tank_and_sphere(case, 3)
    _check_constants(case)


def test_tiny_bin_poses_reproduce_exported_obj_meshes():
    case = splishsplash.read_output(TINY)
    assert _check_poses_reproduce_obj(case, TINY / "obj", (1, 29, 30)) < TOL


def test_tiny_fluid_follows_id_across_the_solver_resort():
    """SPlisHSPlasH re-sorts its particles between frames 29 and 30: read as the case says,
    row i is the same particle in both (it moves at most v_max·Δt); in file order it is not."""
    case = splishsplash.read_output(TINY)
    files = dict(case.fluid)
    a, b = (read(files[k], up=case.up, **case.fluid_reader_options) for k in (29, 30))
    np.testing.assert_array_equal(a.ids, b.ids)
    res = _kinematic_residual(a, b, case.frame_dt)
    assert np.median(res) < MEDIAN_RESIDUAL and res.max() < MAX_RESIDUAL
    raw_a, raw_b = (read(files[k], up=case.up) for k in (29, 30))
    assert not np.array_equal(raw_a.ids, raw_b.ids)
    assert np.median(_kinematic_residual(raw_a, raw_b, case.frame_dt)) > ROW_JUMP


def test_tiny_obj_export_alone_gives_the_bin_motion(tmp_path):
    """Without the BIN, the per-frame OBJ meshes are read and each pose is fitted (Kabsch)."""
    d = _copy(tmp_path)
    shutil.rmtree(d / "rigid_bodies")
    case = splishsplash.read_output(d)
    _check_tank_and_sphere(case, 3)
    (sphere,) = _by_role(case, "body")
    assert "obj" in sphere.source
    # OBJ text keeps 6 digits, so the fit is as good as the file
    assert _check_poses_reproduce_obj(case, d / "obj", (1, 29, 30)) < TOL
    ref = _by_role(splishsplash.read_output(TINY), "body")[0]
    for p, q in zip(sphere.poses, ref.poses):
        assert np.abs(_posed(p, sphere.vertices) - _posed(q, sphere.vertices)).max() < TOL


def test_scene_json_alone_gives_the_static_boundaries_with_their_placement(tmp_path):
    d = _copy(tmp_path)
    shutil.rmtree(d / "rigid_bodies")
    shutil.rmtree(d / "obj")
    with pytest.warns(UserWarning, match=r"RigidBodies\[1\] is dynamic"):
        case = splishsplash.read_output(d)
    (tank,) = case.shapes  # the dynamic sphere's motion is unknown: left out
    assert tank.role == "container" and tank.poses is None
    np.testing.assert_allclose(tank.vertices.min(0), [-1.55, -1.55, -0.05], atol=1e-6)
    np.testing.assert_allclose(tank.vertices.max(0), [1.55, 1.55, 3.05], atol=1e-6)
    # scale, then a quarter turn about x, then translation; y up -> z up
    scene_file = d / "Scenes" / "WC_RigidSample.json"
    scene = json.loads(scene_file.read_text())
    scene["RigidBodies"][0].update(scale=[1, 2, 3], rotationAxis=[1, 0, 0], rotationAngle=np.pi / 2,
                                   translation=[0, 5, 0], isWall=False)
    scene["RigidBodies"].pop()
    scene_file.write_text(json.dumps(scene))
    (box,) = splishsplash.read_output(d).shapes
    assert box.role == "obstacle"
    # y up: x ±0.5, y ±1.5 (was z), z ±1 (was y), then +5 in y; z up: (x, −z, y)
    np.testing.assert_allclose(box.vertices.min(0), [-0.5, -1.0, 3.5], atol=1e-6)
    np.testing.assert_allclose(box.vertices.max(0), [0.5, 1.0, 6.5], atol=1e-6)


# ============================================================================ bad input
def _truncate(path: Path, n: int) -> None:
    path.write_bytes(path.read_bytes()[:n])


def _json_edit(fn):
    def edit(d: Path) -> None:
        p = d / "Scenes" / "WC_RigidSample.json"
        scene = json.loads(p.read_text())
        fn(scene)
        p.write_text(json.dumps(scene))
    return edit


def _bad_rotation(d: Path) -> None:
    p = d / "rigid_bodies" / "rb_data_29.bin"
    a = np.frombuffer(p.read_bytes(), "<f4").copy()
    a[12 + 3:12 + 12] = 2.0  # body 1's rotation: all entries 2
    p.write_bytes(a.tobytes())


def _no_ids(d: Path) -> None:
    p = d / "vtk" / "ParticleData_Fluid_29.vtk"
    f = read(p)
    write_splishsplash_vtk(p, f.positions, None, f.velocities, f.density)


BAD = {
    "truncated header": (lambda d: _truncate(d / "rigid_bodies" / "rb_data_1.bin", 30),
                         r"rb_data_1\.bin: body 0 (mesh name|scale|isWall|colour)|rb_data_1\.bin: number of bodies"),
    "short pose block": (lambda d: _truncate(d / "rigid_bodies" / "rb_data_30.bin", 90),
                         r"rb_data_30\.bin: pose block: 90 bytes, 96 expected"),
    "first BIN missing": (lambda d: (d / "rigid_bodies" / "rb_data_1.bin").unlink(),
                          r"rb_data_1\.bin: missing"),
    "BIN frames != fluid frames": (lambda d: (d / "rigid_bodies" / "rb_data_29.bin").unlink(),
                                   r"rigid_bodies: rigid-body poses .*2 frames but the fluid has 3 "
                                   r"\(missing frames 29\)"),
    "dynamic body without poses": (lambda d: [(d / "rigid_bodies" / f"rb_data_{k}.bin").unlink() for k in (29, 30)],
                                   r"rigid_bodies: only rb_data_1\.bin, but .*RigidBodies\[1\]\.isDynamic is true"),
    "not a rotation": (_bad_rotation, r"rb_data_29\.bin: body 1 rotation: not a rotation matrix"),
    "OBJ frames != fluid frames": (lambda d: (shutil.rmtree(d / "rigid_bodies"),
                                              (d / "obj" / "rb_data_1_29.obj").unlink()),
                                   r"obj: body 1 meshes .*2 frames but the fluid has 3"),
    "misspelt field": (_json_edit(lambda s: s["RigidBodies"][0].update(
                           translaton=s["RigidBodies"][0].pop("translation"))),
                       r"WC_RigidSample\.json: RigidBodies\[0\]\.translaton: unknown field "
                       r"\(did you mean 'translation'\?\)"),
    "misspelt config field": (_json_edit(lambda s: s["Configuration"].update(
                                  ParticleRadius=s["Configuration"].pop("particleRadius"))),
                              r"WC_RigidSample\.json: Configuration\.ParticleRadius: unknown field"),
    "malformed field": (_json_edit(lambda s: s["RigidBodies"][0].update(scale="big")),
                        r"WC_RigidSample\.json: RigidBodies\[0\]\.scale: expected 3 numbers"),
    "bad radius": (_json_edit(lambda s: s["Configuration"].update(particleRadius=-1)),
                   r"WC_RigidSample\.json: Configuration\.particleRadius: expected a positive number"),
    "body count": (_json_edit(lambda s: s["RigidBodies"].pop()),
                   r"rb_data_1\.bin: 2 rigid bodies, but .*WC_RigidSample\.json: RigidBodies lists 1"),
    "not JSON": (lambda d: (d / "Scenes" / "WC_RigidSample.json").write_text("{\"Configuration\": {,}}"),
                 r"WC_RigidSample\.json: not valid JSON \(line 1"),
}


@pytest.mark.parametrize("name", list(BAD))
def test_bad_input_is_one_line_naming_file_and_field(tmp_path, name):
    spoil, message = BAD[name]
    d = _copy(tmp_path)
    spoil(d)
    with pytest.raises(InputError, match=message) as err:
        splishsplash.read_output(d)
    assert "\n" not in str(err.value)


def test_fluid_without_ids_is_refused_when_read_for_the_case(tmp_path):
    d = _copy(tmp_path)
    _no_ids(d)
    case = splishsplash.read_output(d)
    path = dict(case.fluid)[29]
    with pytest.raises(InputError, match=r"ParticleData_Fluid_29\.vtk: missing array 'id'") as err:
        read(path, up=case.up, **case.fluid_reader_options)
    assert "\n" not in str(err.value)


def test_duplicate_ids_are_refused(tmp_path):
    p = tmp_path / "ParticleData_Fluid_1.vtk"
    write_splishsplash_vtk(p, np.zeros((3, 3)), [4, 7, 4], np.zeros((3, 3)), np.ones(3))
    with pytest.raises(InputError, match=r"ParticleData_Fluid_1\.vtk: id: 1 ids appear more than once \(e\.g\. 4\)"):
        read(p, by_id=True)


# ============================================================================ the full shared output
@needs_real
def test_real_case_finds_tank_as_container_and_sphere_as_moving_body():
    assert splishsplash.is_case(REAL)
    case = splishsplash.read_output(REAL)
    assert [k for k, _ in case.fluid] == list(range(1, 52))
    assert case.times[-1] == pytest.approx(2.0)
    _check_tank_and_sphere(case, 51)
    _check_constants(case)
    # the README's frame-26 pose, y up: the sphere's centre is the mesh origin carried by the pose
    (sphere,) = _by_role(case, "body")
    origin_1 = _z_up([[0.0050, 0.99985, 0.0]])[0]
    np.testing.assert_allclose(_posed(sphere.poses[25], origin_1[None])[0],
                               _z_up([[0.5423, 0.5713, -0.3079]])[0], atol=1e-3)


@needs_real
def test_real_bin_poses_reproduce_every_exported_obj_mesh():
    case = splishsplash.read_output(REAL)
    assert _check_poses_reproduce_obj(case, REAL / "obj", range(1, 52)) < TOL


@needs_real
def test_real_fluid_follows_id_in_every_frame():
    case = splishsplash.read_output(REAL)
    frames = [read(p, up=case.up, **case.fluid_reader_options) for _, p in case.fluid]
    raw = [read(p, up=case.up) for _, p in case.fluid]
    resorted = 0
    for k in range(len(frames) - 1):
        np.testing.assert_array_equal(frames[k].ids, frames[k + 1].ids)
        res = _kinematic_residual(frames[k], frames[k + 1], case.frame_dt)
        assert np.median(res) < MEDIAN_RESIDUAL and res.max() < MAX_RESIDUAL, f"frame {k + 1} -> {k + 2}"
        resorted += bool(np.median(_kinematic_residual(raw[k], raw[k + 1], case.frame_dt)) > ROW_JUMP)
    assert resorted >= 1  # the solver did re-sort: in file order, rows jump


@needs_real
@pytest.mark.parametrize("form", ["vtk", "ply", "obj"])
def test_real_per_frame_mesh_forms_give_the_bin_motion(tmp_path, form):
    d = tmp_path / form
    (d / "vtk").mkdir(parents=True)
    for name in ("Scenes", "models", form) if form != "vtk" else ("Scenes", "models"):
        (d / name).symlink_to(REAL / name)
    for p in (REAL / "vtk").iterdir():
        if p.name.startswith("ParticleData_") or form == "vtk":
            (d / "vtk" / p.name).symlink_to(p)
    case = splishsplash.read_output(d)
    _check_tank_and_sphere(case, 51)
    (sphere,) = _by_role(case, "body")
    assert f"{form}/rb_data_1_<k>.{form}" in sphere.source
    ref = _by_role(splishsplash.read_output(REAL), "body")[0]
    worst = max(np.abs(_posed(p, sphere.vertices) - _posed(q, sphere.vertices)).max()
                for p, q in zip(sphere.poses, ref.poses))
    assert worst < TOL


# ============================================================================ whitecap import (end to end)
def test_import_writes_a_run_with_the_glass_tank_the_moving_sphere_and_the_fluid_by_id(tmp_path):
    from whitecap.io.run import RunInfo
    from whitecap.pipeline import import_case

    out = tmp_path / "run"
    import_case(TINY, out, show_progress=False)
    info = RunInfo.load(out)
    roles = {o.role: o for o in info.obstacles}
    assert set(roles) == {"container", "body"}
    # the closed wall box would hide the water if drawn opaque: it is a glass pane
    assert roles["container"].material == "glass" and roles["body"].material != "glass"
    tank = read_mesh(out / roles["container"].mesh)
    np.testing.assert_allclose(tank.vertices.min(0), [-1.55, -1.55, -0.05], atol=1e-5)
    # the sphere's poses in run.json carry frame 1's exported mesh onto frame 30's
    k_body = info.obstacles.index(roles["body"])
    rest = _z_up(read_mesh(TINY / "obj" / "rb_data_1_1.obj").vertices)
    pose_30 = info.frame(30).bodies[k_body]
    exported_30 = _z_up(read_mesh(TINY / "obj" / "rb_data_1_30.obj").vertices)
    assert np.abs(_posed(pose_30, rest) - exported_30).max() < TOL
    # the fluid files are in id order: across the solver's re-sort each row moves as its velocity says
    a, b = (read(out / info.frame(k).files["fluid"]) for k in (29, 30))
    np.testing.assert_array_equal(a.ids, b.ids)
    assert np.median(_kinematic_residual(a, b, 0.04)) < MEDIAN_RESIDUAL


def test_import_command_takes_the_scene_file_and_reports_bad_input_on_one_line(tmp_path, capsys):
    from whitecap.cli import main

    d = _copy(tmp_path)
    scene = tmp_path / "elsewhere.json"
    (d / "Scenes" / "WC_RigidSample.json").rename(scene)
    assert main(["import", str(d), "--out", str(tmp_path / "no_scene")]) != 0
    assert "no scene JSON" in capsys.readouterr().err
    assert not (tmp_path / "no_scene" / "run.json").exists()
    data = json.loads(scene.read_text())
    data["Configuration"]["particleRadius"] = 0.015
    scene.write_text(json.dumps(data))
    assert main(["import", str(d), "--out", str(tmp_path / "run"), "--scene", str(scene)]) == 0
    capsys.readouterr()
    from whitecap.io.run import RunInfo

    assert RunInfo.load(tmp_path / "run").particle_radius == pytest.approx(0.015)
    _truncate(d / "rigid_bodies" / "rb_data_30.bin", 90)
    assert main(["import", str(d), "--out", str(tmp_path / "bad"), "--scene", str(scene)]) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "rb_data_30.bin: pose block" in err and "\n" not in err
    assert not (tmp_path / "bad" / "run.json").exists()


def test_render_shows_the_sphere_through_the_closed_tank(tmp_path):
    """SPlisHSPlasH's tank is a closed box around the fluid. Drawn as a thin glass pane, the
    floating sphere inside shows in its paint colour where it projects; the same box drawn
    opaque (stone) hides it."""
    pytest.importorskip("bpy")
    from tests.test_render import image, variants
    from whitecap.io.run import RunInfo
    from whitecap.pipeline import import_case

    run = tmp_path / "run"
    import_case(TINY, run, show_progress=False)
    stone = tmp_path / "stone"
    shutil.copytree(run, stone)
    info = RunInfo.load(stone)
    info.obstacles = [o.model_copy(update={"material": "stone"}) if o.role == "container" else o
                      for o in info.obstacles]
    info.save(stone)
    colours = {}
    for name, d in (("glass", run), ("stone", stone)):
        s = variants(d, tmp_path / name, shot={})["shot"]
        img = image(tmp_path / name / "shot.png")
        h, w = img.shape[:2]
        u, v = np.array(s["obstacle_uv"]).mean(0)  # obstacle 0 is the moving sphere: its centre, projected
        assert 0.1 < u < 0.9 and 0.1 < v < 0.9
        y, x = int((1 - v) * h), int(u * w)
        colours[name] = img[y - 2:y + 3, x - 2:x + 3].reshape(-1, 3).mean(0)
    # measured (8-bit, AgX, preview): red − blue 33 through glass (the sphere's orange, paled by the
    # pane's reflection of the sky), −10 on the stone wall (grey under a blue sky)
    r, g, b = colours["glass"]
    assert r > b + 20, colours
    r, g, b = colours["stone"]
    assert r < b + 5, colours


def test_viewer_leaves_out_the_glass_tank_and_keeps_the_body(tmp_path):
    """Drawn opaque, the closed tank would hide the water in the viewer too; the body keeps its
    obstacle index (its poses in run.json are found by it)."""
    from whitecap.io.run import RunInfo
    from whitecap.pipeline import import_case
    from whitecap.view.geometry import load_obstacle_meshes

    import_case(TINY, tmp_path / "run", show_progress=False)
    info = RunInfo.load(tmp_path / "run")
    drawn = load_obstacle_meshes(info.obstacles, [tmp_path / "run"])
    assert [k for *_, k in drawn] == [i for i, o in enumerate(info.obstacles) if o.role == "body"]


def test_an_open_wall_keeps_the_container_look(tmp_path):
    """Only a wall that closes around the fluid is drawn as glass; an open-topped tank (the
    camera sees in over its rim) keeps the container's default look."""
    d = _copy(tmp_path)
    shutil.rmtree(d / "rigid_bodies")
    shutil.rmtree(d / "obj")
    box = read_mesh(d / "models" / "UnitBox.obj")
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    lid = (v[f][:, :, 1] > 0.49).all(axis=1)  # y up: the two triangles at the top
    assert lid.sum() == 2
    lines = [f"v {x} {y} {z}" for x, y, z in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f[~lid]]
    (d / "models" / "OpenBox.obj").write_text("\n".join(lines) + "\n")
    scene_file = d / "Scenes" / "WC_RigidSample.json"
    scene = json.loads(scene_file.read_text())
    scene["RigidBodies"][0]["geometryFile"] = "../models/OpenBox.obj"
    scene["RigidBodies"].pop()
    scene_file.write_text(json.dumps(scene))
    (tank,) = splishsplash.read_output(d).shapes
    assert tank.role == "container" and tank.look is None
    (closed,) = _by_role(splishsplash.read_output(TINY), "container")
    assert closed.look["material"] == "glass"


ADDON_LOAD = r"""
run = sys.argv[3]
bpy.ops.whitecap.load(filepath=run)
res = {}
for o in sc.objects:
    if o.name.startswith("obstacle_") and o.data.materials:
        res[o.name] = sorted(n.bl_idname for n in o.data.materials[0].node_tree.nodes)
print(json.dumps(res))
"""


def test_blender_addon_draws_the_closed_tank_as_glass(tmp_path):
    """The add-on (which ships without whitecap) gives the glass tank the same see-through pane."""
    pytest.importorskip("bpy")
    from tests.test_addon import run_blender
    from whitecap.cli import main

    zp = tmp_path / "addon.zip"
    assert main(["blender-addon", "--out", str(zp)]) == 0
    from whitecap.pipeline import import_case

    import_case(TINY, tmp_path / "run", show_progress=False)
    res = run_blender(ADDON_LOAD, zp, tmp_path, tmp_path / "run")
    res.pop("stdout")
    sphere, tank = res["obstacle_0"], res["obstacle_1"]  # moving bodies come first
    assert "ShaderNodeBsdfTransparent" in tank and "ShaderNodeBsdfTransparent" not in sphere, res


def test_partio_export_alone_is_read_in_id_order_too(tmp_path):
    """With only the partio export (enablePartioExport), the fluid comes from partio/*.bgeo,
    followed by id in the same way."""
    from tests.conftest import write_partio_bgeo

    d = _copy(tmp_path)
    (d / "partio").mkdir()
    for p in sorted((d / "vtk").glob("ParticleData_*.vtk")):
        f = read(p)  # file order, file axes
        write_partio_bgeo(d / "partio" / p.with_suffix(".bgeo").name, f.positions,
                          {"id": f.ids.astype(np.int32), "velocity": f.velocities, "density": f.density})
        p.unlink()
    case = splishsplash.read_output(d)
    assert [p.suffix for _, p in case.fluid] == [".bgeo"] * 3
    files = dict(case.fluid)
    a, b = (read(files[k], up=case.up, **case.fluid_reader_options) for k in (29, 30))
    np.testing.assert_array_equal(a.ids, b.ids)
    assert np.median(_kinematic_residual(a, b, case.frame_dt)) < MEDIAN_RESIDUAL
    raw_a, raw_b = (read(files[k], up=case.up) for k in (29, 30))
    assert np.median(_kinematic_residual(raw_a, raw_b, case.frame_dt)) > ROW_JUMP


def test_several_fluid_models_need_a_choice(tmp_path):
    d = _copy(tmp_path)
    for p in sorted((d / "vtk").glob("ParticleData_Fluid_*.vtk")):
        shutil.copyfile(p, p.with_name(p.name.replace("_Fluid_", "_Oil_")))
    with pytest.raises(InputError, match=r"vtk: several fluid models \(Fluid, Oil\); choose one"):
        splishsplash.read_output(d)
    case = splishsplash.read_output(d, model="Oil")
    assert [p.name for _, p in case.fluid] == [f"ParticleData_Oil_{k}.vtk" for k in (1, 29, 30)]
    with pytest.raises(InputError, match=r"vtk: no fluid model 'Water' \(found Fluid, Oil\)"):
        splishsplash.read_output(d, model="Water")


def test_the_camera_looks_at_a_glass_tank_from_the_side_and_over_an_opaque_one(tmp_path):
    """Over an opaque tank's wall the camera must look down from high up; through a glass one it
    keeps the usual side view, which shows the water's profile."""
    from whitecap.config import Render
    from whitecap.io.run import RunInfo
    from whitecap.pipeline import import_case
    from whitecap.render.stage import camera_path

    import_case(TINY, tmp_path / "run", show_progress=False)
    info = RunInfo.load(tmp_path / "run")
    bounds = ([-1.55, -1.55, -0.05], [1.55, 1.55, 3.05])

    def elevation(obstacles) -> float:
        info.obstacles = obstacles
        start, _, target = camera_path(Render(), info, bounds)
        d = np.subtract(start, target)
        return float(np.degrees(np.arctan2(d[2], np.linalg.norm(d[:2]))))

    glass = elevation(info.obstacles)
    stone = elevation([o.model_copy(update={"material": "stone"}) for o in info.obstacles])
    assert glass < 35 < 60 < stone, (glass, stone)


def write_splishsplash_mesh_vtk(path: Path, vertices, faces) -> None:
    """A triangle mesh in the layout of SPlisHSPlasH's rigid-body VTK export (binary,
    big-endian UNSTRUCTURED_GRID: POINTS, CELLS of (3, a, b, c), CELL_TYPES 5)."""
    v = np.asarray(vertices, ">f4").reshape(-1, 3)
    f = np.asarray(faces).reshape(-1, 3)
    cells = np.hstack([np.full((len(f), 1), 3), f]).astype(">i4")
    Path(path).write_bytes(b"".join([
        b"# vtk DataFile Version 4.2\nSPlisHSPlasH mesh data\nBINARY\nDATASET UNSTRUCTURED_GRID\n",
        f"POINTS {len(v)} float\n".encode(), v.tobytes(), b"\n",
        f"CELLS {len(f)} {4 * len(f)}\n".encode(), cells.tobytes(), b"\n",
        f"CELL_TYPES {len(f)}\n".encode(), np.full(len(f), 5, ">i4").tobytes(), b"\n"]))


def test_legacy_vtk_triangle_meshes_read_through_the_registry(tmp_path):
    """The rigid-body VTK export is a mesh format of the one registry: vertices and triangles as
    written; a particle file (one-point cells) is refused with its name."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    write_splishsplash_mesh_vtk(tmp_path / "rb_data_1_1.vtk", v, f)
    m = read_mesh(tmp_path / "rb_data_1_1.vtk")
    np.testing.assert_array_equal(m.vertices, v)
    np.testing.assert_array_equal(m.faces, f)
    with pytest.raises(InputError, match=r"ParticleData_Fluid_1\.vtk: cell 0 has 1 points; only triangle meshes"):
        read_mesh(TINY / "vtk" / "ParticleData_Fluid_1.vtk")


def test_a_scene_of_static_bodies_writes_the_first_bin_alone(tmp_path):
    """SPlisHSPlasH writes only rb_data_1.bin when no body moves: every body is fixed there."""
    d = _copy(tmp_path)
    for k in (29, 30):
        (d / "rigid_bodies" / f"rb_data_{k}.bin").unlink()
    _json_edit(lambda s: s["RigidBodies"][1].update(isDynamic=False))(d)
    case = splishsplash.read_output(d)
    assert [(s.name, s.role, s.poses) for s in case.shapes] == [("UnitBox", "container", None),
                                                                  ("sphere", "obstacle", None)]
    centre = case.shapes[1].vertices.mean(0)
    np.testing.assert_allclose(centre, [0.005, 0.0, 0.99985], atol=2e-3)
