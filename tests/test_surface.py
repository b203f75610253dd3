"""Surface reconstruction (`whitecap mesh`): geometry, attributes, parallel runs, errors."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from whitecap import io as wio
from whitecap.cli import main
from whitecap.errors import InputError
from whitecap.io.frame import ParticleFrame
from whitecap.io.mesh import read_mesh
from whitecap.io.run import RunInfo
from whitecap.pipeline import mesh
from whitecap.surface import MeshParams, mesh_frame

R_SIM = 0.01  # simulation particle radius r [m]; spacing 2r


def lattice_sphere(radius: float, centre=(0.0, 0.0, 0.0), r: float = R_SIM) -> np.ndarray:
    s = 2 * r
    ax = np.arange(-radius, radius + s / 2, s)
    g = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    return g[np.linalg.norm(g, axis=1) <= radius] + np.asarray(centre)


def write_frame(path: Path, pos: np.ndarray, vel: np.ndarray | None = None) -> Path:
    vel = np.zeros_like(pos) if vel is None else vel
    wio.write(path, ParticleFrame(positions=pos, velocities=vel, density=np.full(len(pos), 1000.0)))
    return path


def load_tm(path: Path) -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray]:
    m = read_mesh(path)
    return trimesh.Trimesh(m.vertices, m.faces, process=False), m.normals, m.arrays["velocity"]


def test_sphere_is_watertight_single_component_right_volume_outward_normals(tmp_path):
    R, c = 0.2, np.array([0.3, -0.1, 0.5])
    src = write_frame(tmp_path / "fluid_00000.ply", lattice_sphere(R, c))
    stats = mesh_frame(src, tmp_path / "mesh.ply", MeshParams(particle_radius=R_SIM).check())
    tm, normals, _ = load_tm(tmp_path / "mesh.ply")
    assert stats["faces"] == len(tm.faces) > 1000
    # An independent PLY reader sees the same mesh.
    other = trimesh.load(tmp_path / "mesh.ply", process=False)
    np.testing.assert_array_equal(other.faces, tm.faces)
    np.testing.assert_allclose(other.vertices, tm.vertices)
    assert tm.is_watertight
    assert len(tm.split(only_watertight=False)) == 1
    # Faces are wound outward (positive signed volume) and the volume is the sphere's.
    assert tm.volume == pytest.approx(4 / 3 * np.pi * R**3, rel=0.05)
    radial = tm.vertices - c
    outward = np.einsum("ij,ij->i", normals, radial) > 0
    assert outward.mean() > 0.99
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-3)
    # And the surface is a sphere, not a blob: radii within a few per cent of R.
    assert np.abs(np.linalg.norm(radial, axis=1) / R - 1).max() < 0.08


def test_uniform_motion_is_interpolated_onto_vertices(tmp_path):
    pos = lattice_sphere(0.12)
    u = np.array([1.5, -0.5, 2.0], np.float32)
    src = write_frame(tmp_path / "blob_00007.ply", pos, np.tile(u, (len(pos), 1)))
    mesh_frame(src, tmp_path / "blob.ply", MeshParams(particle_radius=R_SIM))
    tm, _, vel = load_tm(tmp_path / "blob.ply")
    assert len(vel) == len(tm.vertices) > 100
    np.testing.assert_allclose(vel, np.tile(u, (len(vel), 1)), rtol=0, atol=1e-4)


def test_linear_velocity_field_is_interpolated_not_copied(tmp_path):
    # v = (z, 0, 0): every vertex should carry roughly its own height, which a
    # nearest-particle lookup or a constant would not give.
    pos = lattice_sphere(0.12, centre=(0, 0, 0.5))
    vel = np.zeros_like(pos)
    vel[:, 0] = pos[:, 2]
    src = write_frame(tmp_path / "shear_00000.ply", pos, vel)
    mesh_frame(src, tmp_path / "shear.ply", MeshParams(particle_radius=R_SIM))
    tm, _, v = load_tm(tmp_path / "shear.ply")
    err = np.abs(v[:, 0] - tm.vertices[:, 2])
    assert np.median(err) < 0.01 and err.max() < 0.05
    assert np.abs(v[:, 1:]).max() < 1e-4


def test_empty_frame_gives_empty_mesh(tmp_path):
    src = write_frame(tmp_path / "fluid_00000.ply", np.zeros((0, 3)))
    stats = mesh_frame(src, tmp_path / "empty.ply", MeshParams(particle_radius=R_SIM))
    assert stats["vertices"] == stats["faces"] == 0
    m = read_mesh(tmp_path / "empty.ply")
    assert len(m.vertices) == 0 and len(m.faces) == 0
    # ... which exports to VTK as an empty dataset
    from whitecap.io.vtk_xml import read_vtp, write_vtp

    write_vtp(tmp_path / "empty.vtp", m.vertices, {"velocity": m.arrays["velocity"]}, triangles=m.faces)
    pts, arrays, tris = read_vtp(tmp_path / "empty.vtp")
    assert len(pts) == len(tris) == 0
    # OBJ too: a file that our reader and an independent one (trimesh) parse as an empty mesh,
    # with no vertex or face statement in it.
    mesh_frame(src, tmp_path / "empty.obj", MeshParams(particle_radius=R_SIM))
    m = read_mesh(tmp_path / "empty.obj")
    assert m.vertices.shape == (0, 3) and m.faces.shape == (0, 3)
    statements = [ln.split()[0] for ln in (tmp_path / "empty.obj").read_text().splitlines() if ln.strip()]
    assert all(st == "#" or st.startswith("#") for st in statements), statements
    other = trimesh.load(tmp_path / "empty.obj", file_type="obj", process=False, force="mesh")
    assert len(other.vertices) == 0 and len(other.faces) == 0


@pytest.fixture
def run_copy(tiny_run, tmp_path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(tiny_run, dst)
    return dst


def test_jobs_2_matches_jobs_1_and_reruns_skip(run_copy, tmp_path):
    s1 = mesh(run_copy, out=tmp_path / "j1", jobs=1, show_progress=False)
    assert RunInfo.load(run_copy).files("mesh") == []  # meshes outside the run are not recorded
    s2 = mesh(run_copy, jobs=2, show_progress=False)
    assert len(s1) == len(s2) == 4 and all(s["faces"] > 0 for s in s1)
    for i in range(4):
        pa, pb = tmp_path / "j1" / f"fluid_{i:05d}.ply", run_copy / "mesh" / f"fluid_{i:05d}.ply"
        if pa.read_bytes() != pb.read_bytes():
            ma, mb = read_mesh(pa), read_mesh(pb)
            diff = [k for k, x, y in (("vertices", ma.vertices, mb.vertices), ("faces", ma.faces, mb.faces),
                                      ("normals", ma.normals, mb.normals),
                                      ("velocity", ma.arrays["velocity"], mb.arrays["velocity"]))
                    if x.shape != y.shape or not np.array_equal(x, y)]
            pytest.fail(f"frame {i} differs between --jobs 1 and --jobs 2 in {diff}")
    info = RunInfo.load(run_copy)
    assert [rel for _, rel in info.files("mesh")] == [f"mesh/fluid_{i:05d}.ply" for i in range(4)]
    assert info.extra["mesh"]["particle_radius"] == info.particle_radius
    # A rerun skips everything; --force redoes it.
    before = (run_copy / "mesh" / "fluid_00002.ply").stat().st_mtime_ns
    again = mesh(run_copy, jobs=1, show_progress=False)
    assert all(s["skipped"] for s in again)
    assert (run_copy / "mesh" / "fluid_00002.ply").stat().st_mtime_ns == before
    (run_copy / "mesh" / "fluid_00002.ply").unlink()
    partial = mesh(run_copy, jobs=1, show_progress=False)
    assert [s["skipped"] for s in partial] == [True, True, False, True]
    forced = mesh(run_copy, jobs=1, force=True, show_progress=False)
    assert not any(s["skipped"] for s in forced)


def test_cli_overrides_config_and_obj_format(run_copy, capsys):
    # The run's [mesh] section is used, and the command line wins over it.
    import tomllib

    import tomli_w

    scene = tomllib.loads((run_copy / "scene.toml").read_text())
    scene.setdefault("mesh", {}).update(cube_size=0.75, mesh_smoothing_iters=3)
    (run_copy / "scene.toml").write_text(tomli_w.dumps(scene))
    assert main(["mesh", str(run_copy), "--jobs", "1", "--smoothing-iters", "5", "--format", "obj"]) == 0
    p = json.loads((run_copy / "run.json").read_text())["extra"]["mesh"]
    assert p["cube_size"] == 0.75 and p["mesh_smoothing_iters"] == 5
    obj = trimesh.load(run_copy / "mesh" / "fluid_00000.obj", process=False, force="mesh")
    assert len(obj.faces) > 0 and obj.vertex_normals.shape == obj.vertices.shape
    assert RunInfo.load(run_copy).files("mesh")[0][1] == "mesh/fluid_00000.obj"


def test_cube_size_above_one_warns():
    with pytest.warns(UserWarning, match="cube_size"):
        MeshParams(particle_radius=R_SIM, cube_size=1.5).check()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        MeshParams(particle_radius=R_SIM, cube_size=0.75).check()


def test_sequence_input_needs_radius_and_writes_beside_it(tmp_path, capsys):
    seq = tmp_path / "seq"
    for i in (3, 4):
        write_frame(seq / f"part_{i:04d}.ply", lattice_sphere(0.08))
    assert main(["mesh", str(seq), "--jobs", "1"]) == 2
    assert "--radius" in capsys.readouterr().err
    assert main(["mesh", str(tmp_path / "seq" / "part_*.ply"), "--radius", "0.01", "--jobs", "1"]) == 0
    assert sorted(p.name for p in (seq / "mesh").iterdir()) == ["fluid_00003.ply", "fluid_00004.ply", "mesh.json"]


@pytest.mark.parametrize("radius", ["0", "-0.01"])
def test_non_positive_radius_is_an_error(tmp_path, capsys, radius):
    write_frame(tmp_path / "seq" / "fluid_00000.ply", lattice_sphere(0.05))
    assert main(["mesh", str(tmp_path / "seq"), f"--radius={radius}"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "radius must be a positive" in err and err.count("\n") == 1


def test_missing_directory_is_an_error(tmp_path, capsys):
    assert main(["mesh", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert "nope: no such run directory" in err and err.count("\n") == 1


def test_unparsable_frame_is_named(tmp_path, capsys):
    seq = tmp_path / "seq"
    write_frame(seq / "fluid_00000.ply", lattice_sphere(0.05))
    (seq / "fluid_00001.ply").write_bytes(b"ply\nformat garbage\n\x00\x01")
    assert main(["mesh", str(seq), "--radius", "0.01", "--jobs", "2"]) == 2
    err = capsys.readouterr().err
    assert "fluid_00001.ply" in err and "not a readable PLY" in err and err.count("\n") == 1
    with pytest.raises(InputError, match="fluid_00001.ply"):
        mesh(seq, radius=0.01, jobs=1, force=True, show_progress=False)
    # The good frame was still written.
    assert (seq / "mesh" / "fluid_00000.ply").is_file()


def test_bad_override_is_an_error(run_copy, capsys):
    assert main(["mesh", str(run_copy), "--cube-size", "-1"]) == 2
    assert "mesh.cube_size" in capsys.readouterr().err


def test_canonical_order_ignores_vertex_and_face_order():
    # splashsurf's threads permute vertices and triangles; the written order must not change.
    from whitecap.surface.reconstruct import SNAP, canonical_order

    rng = np.random.default_rng(1)
    v = np.round(rng.uniform(-1, 1, (500, 3)) / SNAP) * SNAP
    v[10:20, :2] = v[0, :2]  # ties on (x, y) are broken by z
    n = rng.normal(size=(500, 3))
    f = rng.integers(0, 500, (900, 3))
    o1, f1 = canonical_order(v, n, f)
    perm = rng.permutation(500)
    inv = np.argsort(perm)
    f2_in = np.roll(inv[f][rng.permutation(900)], 1, axis=1)  # same triangles, other order and rotation
    o2, f2 = canonical_order(v[perm], n[perm], f2_in)
    np.testing.assert_array_equal(v[o1], v[perm][o2])
    np.testing.assert_array_equal(f1, f2)
    # winding kept: each output triangle is a rotation of an input one
    def rotations(t):
        return {tuple(np.roll(t, -k)) for k in range(3)}

    tri = set().union(*(rotations(t) for t in np.argsort(o1)[f]))
    assert all(tuple(t) in tri for t in f1)
    assert sorted(min(rotations(t)) for t in np.argsort(o1)[f]) == [tuple(t) for t in f1]


def test_api_checks_jobs_and_profiles_like_the_cli(run_copy, capsys):
    with pytest.raises(InputError, match="--jobs must be at least 1"):
        mesh(run_copy, jobs=0, show_progress=False)
    assert not (run_copy / "mesh").exists()
    stats = mesh(run_copy, jobs=1, profile=True, show_progress=False)
    out = capsys.readouterr().out
    assert len(stats) == 4 and "mesh profile" in out and "mesh.splashsurf" in out


def settled_tank_run(root: Path, extra: dict) -> tuple[Path, np.ndarray, np.ndarray]:
    """A run holding one frame of water at rest in the corner of a tank: a lattice of spacing 2r
    with centres r from the walls, as the solver leaves them (it confines centres to r inside)."""
    lo, hi = np.zeros(3), np.array([0.3, 0.2, 0.4])
    g = [np.arange(lo[i] + R_SIM, hi[i] - R_SIM + 1e-9, 2 * R_SIM) for i in range(2)]
    g.append(np.arange(R_SIM, 0.15, 2 * R_SIM))
    pos = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
    run = root / "run"
    run.mkdir()
    info = RunInfo(particle_radius=R_SIM, rest_density=1000.0, particle_mass=0.008, gravity=[0, 0, -9.81],
                   domain={"lower": lo.tolist(), "upper": hi.tolist()}, frame_rate=30.0, extra=extra)
    write_frame(run / "fluid/fluid_00000.ply", pos)
    info.set_file(0, "fluid", "fluid/fluid_00000.ply")
    info.save(run)
    return run, lo, hi


def wall_gaps(run: Path, lo, hi) -> dict:
    """For each wall the water touches: the largest distance [r] from the wall plane of the
    vertices that face it (normal within 45° of the wall's outward normal, within 3 r of it)."""
    m = read_mesh(run / "mesh/fluid_00000.ply")
    v, n = m.vertices.astype(float), m.normals.astype(float)
    gaps = {}
    for name, axis, side, coord in (("x-", 0, -1, lo[0]), ("x+", 0, 1, hi[0]), ("y-", 1, -1, lo[1]),
                                    ("y+", 1, 1, hi[1]), ("z-", 2, -1, lo[2])):
        d = (coord - v[:, axis]) * side
        sel = (n[:, axis] * side > 0.7) & (d < 3 * R_SIM)
        assert sel.sum() > 100, name
        gaps[name] = float(np.abs(d[sel]).max() / R_SIM)
    return gaps


def test_settled_tank_surface_meets_the_solid_walls(tmp_path):
    """splashsurf ends the surface about where the particles end, half a radius or more inside
    a wall; for the walls a whitecap run says are solid, the vertices facing them are on them."""
    run, lo, hi = settled_tank_run(tmp_path, {"solid_walls": ["x-", "x+", "y-", "y+", "z-", "z+"]})
    assert main(["mesh", str(run), "--jobs", "1"]) == 0
    gaps = wall_gaps(run, lo, hi)
    assert max(gaps.values()) <= 0.25, gaps
    m = read_mesh(run / "mesh/fluid_00000.ply")
    assert (m.vertices >= lo - 1e-6).all() and (m.vertices <= hi + 1e-6).all()  # nothing pushed through a wall
    # The water fills its share of the tank: the volume of N lattice cells (2r)³, within 3 %.
    n = len(wio.read(run / "fluid/fluid_00000.ply"))
    volume = trimesh.Trimesh(m.vertices, m.faces, process=False).volume
    assert volume == pytest.approx(n * (2 * R_SIM) ** 3, rel=0.03)


def test_a_foreign_sequence_box_is_not_a_wall(tmp_path):
    """A converted foreign sequence's domain is only a bound: its surface is left where splashsurf put it."""
    run, lo, hi = settled_tank_run(tmp_path, {"source": "elsewhere/PartFluid_*.vtk"})
    assert RunInfo.load(run).solid_walls() == []
    assert main(["mesh", str(run), "--jobs", "1"]) == 0
    assert min(wall_gaps(run, lo, hi).values()) > 0.4


def test_smoothing_weight_normalization_reaches_splashsurf_and_smooths_a_thin_film(tmp_path):
    """A film one particle thick, jittered up and down by a third of r: its distance-weighted neighbour
    count (about 5 at the surface with the default kernel) is under splashsurf's normalization 13, so
    its vertices get partial smoothing weights and keep the beads. With the normalization lowered to
    the film's own count they are smoothed fully: the top comes out flatter."""
    rng = np.random.default_rng(32)
    s = 2 * R_SIM
    ax = np.arange(0.0, 0.4, s)
    g = np.stack(np.meshgrid(ax, ax, indexing="ij"), -1).reshape(-1, 2)
    pos = np.column_stack([g, rng.uniform(-R_SIM / 3, R_SIM / 3, len(g))])
    src = write_frame(tmp_path / "fluid_00000.ply", pos)

    def top_roughness(**kw) -> float:
        out = tmp_path / f"mesh_{len(kw)}.ply"
        mesh_frame(src, out, MeshParams(particle_radius=R_SIM, **kw).check())
        m = read_mesh(out)
        inner = np.all((m.vertices[:, :2] > 4 * s) & (m.vertices[:, :2] < 0.4 - 5 * s), axis=1)
        top = inner & (m.normals[:, 2] > 0.5)
        assert top.sum() > 500
        return float(np.degrees(np.arccos(np.clip(m.normals[top, 2], -1, 1))).mean())

    default = top_roughness()
    assert MeshParams(particle_radius=R_SIM).splashsurf_kwargs()["mesh_smoothing_weights_normalization"] == 13.0
    lowered = top_roughness(mesh_smoothing_weights_normalization=4.0)
    print(f"film top: mean normal tilt {default:.2f} deg at 13, {lowered:.2f} deg at 4")
    assert lowered < 0.8 * default, (default, lowered)
    with pytest.raises(ValueError, match="mesh_smoothing_weights_normalization"):
        MeshParams(particle_radius=R_SIM, mesh_smoothing_weights_normalization=0.0)
