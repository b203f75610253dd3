"""`whitecap foam` on an imported case: the diffuse particles meet the case's own obstacles
(run.json ``obstacles``: tank, building, moving bodies posed per frame), as they meet the
obstacles of a whitecap scene.

The DualSPHysics case is synthetic (tests/test_cases_dualsphysics.py writes its PartVTK
files): a cloud of fast, churning fluid around and through a solid building and a floating
cube, so that diffuse particles are born and thrown everywhere, inside the solids too unless
the obstacles remove or push them out. The SPlisHSPlasH case is the cut of real output in
tests/data/splishsplash_rigid, whose tank is a closed box around the fluid.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from whitecap.geometry import obstacle_matrix
from whitecap.io import read, read_mesh
from whitecap.io.run import RunInfo
from whitecap.sim.obstacles import compute_sdf

from .test_cases_dualsphysics import DP, case_xml, motion, write_part_vtk

TINY_SPLISHSPLASH = Path(__file__).resolve().parent / "data" / "splishsplash_rigid"
R = DP / 2
# A particle counts as inside a solid when the exact distance (libigl, to the mesh itself, not
# the SDF grid) puts it deeper than this: the grid's trilinear values may differ from the exact
# ones by a fraction of a cell (r) at edges and corners, where particles pushed out are put.
INSIDE_DEPTH = 0.3 * R

XML = case_xml("""
<fixed mkbound="0" mk="10" begin="0" count="1"/>
<fixed mkbound="1" mk="11" begin="1" count="1"/>
<floating mkbound="40" mk="50" begin="2" count="1"/>
<fluid mkfluid="0" mk="1" begin="3" count="1"/>""")
FRAMES = 4


def block(n, origin) -> np.ndarray:
    """A solid block of n[0]×n[1]×n[2] boundary particles of spacing DP (cells from ``origin``)."""
    g = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    return np.asarray(origin, float) + (g + 0.5) * DP


def churning_case(folder: Path) -> None:
    """A floor (mk 10), a solid building (mk 11, 0.1 × 0.1 × 0.2 m), a solid floating cube (mk 50)
    moved by ``motion`` and a fluid cloud through all of them, at 2 m/s with 1.5 m/s of churn."""
    folder.mkdir(parents=True)
    (folder / "Case.xml").write_text(XML)
    rng = np.random.default_rng(5)
    floor = block((40, 20, 1), [0.0, 0.0, 0.0])
    building = block((5, 5, 10), [0.4, 0.15, 0.02])
    cube = block((4, 4, 4), [0.2, 0.12, 0.1])
    c0 = cube.mean(0)
    cloud = block((28, 10, 12), [0.1, 0.1, 0.04])
    for k in range(FRAMES):
        Rk, t = motion(k)
        fluid = cloud + rng.normal(0, 0.2 * DP, cloud.shape)
        pos = np.concatenate([floor, building, (cube - c0) @ Rk.T + c0 + t, fluid])
        n = [len(floor), len(building), len(cube), len(fluid)]
        vel = np.zeros((len(pos), 3), np.float32)
        vel[-len(fluid):] = [2.0, 0.0, 1.0] + rng.normal(0, 1.5, fluid.shape)
        arrays = {"Idp": np.arange(len(pos), dtype=np.uint32), "Vel": vel,
                  "Rhop": np.full(len(pos), 1000.0, np.float32),
                  "Type": np.repeat(np.array([0, 0, 2, 3], np.uint8), n),
                  "Mk": np.repeat(np.array([10, 11, 50, 1], np.uint16), n)}
        write_part_vtk(folder / f"PartAll_{k:04d}.vtk", pos, arrays)
        keep = arrays["Type"] == 3
        write_part_vtk(folder / f"PartFluid_{k:04d}.vtk", pos[keep],
                       {"Idp": arrays["Idp"][keep], "Vel": vel[keep], "Rhop": arrays["Rhop"][keep]})


def inside_counts(run: Path, names: tuple[str, ...]) -> dict[str, int]:
    """Diffuse particles of every frame deeper than INSIDE_DEPTH inside the named obstacles, each
    at its pose of that frame (run.json), by the exact signed distance to its mesh."""
    info = RunInfo.load(run)
    counts = {}
    for name in names:
        k = next(i for i, o in enumerate(info.obstacles) if o.name == name)
        o = info.obstacles[k]
        mesh = read_mesh(run / o.mesh)
        total = 0
        for index, rel in info.files("diffuse"):
            x = read(run / rel).positions
            if not len(x):
                continue
            M = obstacle_matrix(o, info.body_pose(index, k))
            v = np.asarray(mesh.vertices, np.float64) @ M[:3, :3].T + M[:3, 3]
            total += int((compute_sdf(v, np.asarray(mesh.faces), x) < -INSIDE_DEPTH).sum())
        counts[name] = total
    return counts


@pytest.fixture(scope="module")
def imported(tmp_path_factory) -> Path:
    from whitecap.pipeline import import_case

    tmp = tmp_path_factory.mktemp("casefoam")
    churning_case(tmp / "case")
    import_case(tmp / "case", tmp / "run", show_progress=False)
    return tmp / "run"


def _foam(imported: Path, dest: Path) -> RunInfo:
    import shutil

    from whitecap.diffuse.driver import postprocess

    shutil.copytree(imported, dest)
    postprocess(dest, show_progress=False)
    return RunInfo.load(dest)


def test_foam_on_an_imported_case_leaves_no_diffuse_particle_inside_the_building_or_the_body(imported, tmp_path,
                                                                                           monkeypatch):
    """After import + foam, no diffuse particle lies inside the building or the floating cube (at
    its pose of each frame); the same foam with the imported obstacles left out (as before they
    were used) leaves many inside both, so the check can see them."""
    import whitecap.diffuse.driver as driver

    info = RunInfo.load(imported)
    assert {o.name: o.role for o in info.obstacles} == {"mk50": "body", "mk10": "container",
                                                              "mk11": "obstacle"}
    _foam(imported, tmp_path / "with")
    made = sum(len(read(tmp_path / "with" / rel)) for _, rel in RunInfo.load(tmp_path / "with").files("diffuse"))
    assert made > 1000  # plenty of particles were made and kept around the solids
    assert inside_counts(tmp_path / "with", ("mk11", "mk50")) == {"mk11": 0, "mk50": 0}

    monkeypatch.setattr(driver, "run_obstacles", lambda src, info: [])
    _foam(imported, tmp_path / "without")
    without = inside_counts(tmp_path / "without", ("mk11", "mk50"))
    assert without["mk11"] > 20 and without["mk50"] > 20, without


def test_a_spray_drop_does_not_fly_through_a_wall_thinner_than_its_flight(imported):
    """A drop whose flight over a frame crosses the whole building (from one side to the other,
    ending outside it) hits the face it met first and bounces back off it."""
    from whitecap.diffuse.driver import run_obstacles
    from whitecap.diffuse.generator import SPRAY, FoamGenerator

    info = RunInfo.load(imported)
    grids = run_obstacles(imported, info)
    building = grids[[o.name for o in info.obstacles].index("mk11")]
    gen = FoamGenerator.__new__(FoamGenerator)  # only what _obstacles reads
    gen.obstacles, gen.r = [building], R
    x0 = np.array([[0.35, 0.2, 0.1]])  # 5 cm before the building's face at x = 0.4
    x1 = np.array([[0.55, 0.2, 0.1]])  # 5 cm beyond its far face at x = 0.5
    x, v, alive = gen._obstacles(x0, x1.copy(), np.array([[4.0, 0.0, 0.0]]), np.array([SPRAY], np.uint8))
    assert alive.all()
    assert x[0, 0] < 0.4 and v[0, 0] < 0  # in front of the near face, moving back


def test_splishsplash_tank_is_a_wall_around_the_fluid_and_the_sphere_a_moving_solid(tmp_path):
    """The SPlisHSPlasH tank (isWall) is a closed box with the fluid inside it: its SDF is inverted,
    so every fluid particle is free space and points beyond its walls are wall; the floating sphere
    stays a solid, found at its pose of each frame."""
    from whitecap.diffuse.driver import run_obstacles
    from whitecap.pipeline import import_case

    run = tmp_path / "run"
    import_case(TINY_SPLISHSPLASH, run, show_progress=False)
    info = RunInfo.load(run)
    grids = run_obstacles(run, info)
    role = [o.role for o in info.obstacles]
    tank, sphere = grids[role.index("container")], grids[role.index("body")]
    for index, rel in info.files("fluid"):
        fluid = read(run / rel).positions
        assert (tank.sample(fluid) > 0).all()  # inside the box: free
        tank.at_frame(info.frame(index).time, info.body_pose(index, tank.index))
        sphere.at_frame(info.frame(index).time, info.body_pose(index, sphere.index))
        lo, hi = tank.grid.aabb_lo, tank.grid.aabb_hi
        beyond = np.array([hi + 0.5 * R, lo - 0.5 * R, hi + [0, 0, 10.0]])  # in and far beyond the walls
        assert (tank.sample(beyond) < 0).all()
        centre = info.body_pose(index, sphere.index).position
        mesh = read_mesh(run / info.obstacles[sphere.index].mesh)
        rest_centre = np.asarray(mesh.vertices, np.float64).mean(0)
        M = obstacle_matrix(info.obstacles[sphere.index], info.body_pose(index, sphere.index))
        world_centre = M[:3, :3] @ rest_centre + M[:3, 3]
        assert sphere.sample(world_centre[None])[0] < -0.1, (index, centre)
        assert sphere.sample(world_centre[None] + [0.0, 0.0, 2.0])[0] > 0  # above it: free


def test_foam_into_another_folder_carries_the_cases_shapes_and_lists_only_its_own_files(imported, tmp_path):
    """`foam RUN --out DIR` of an imported case: DIR is a run of its own, with the case's shape meshes
    (files of the run) copied along so that its obstacles resolve there, and a run.json that lists only
    files DIR holds; the diffuse frames are those of foam made in the run itself."""
    from whitecap.diffuse.driver import postprocess
    from whitecap.io.run import obstacle_path, owned_files

    out = tmp_path / "copy"
    postprocess(imported, out=out, show_progress=False)
    info = RunInfo.load(out)
    for o in info.obstacles:
        p = obstacle_path(o.mesh, info, out)
        assert p is not None and p.parent.parent == out and p.read_bytes() == (imported / o.mesh).read_bytes()
    listed = [rel for f in info.frames for rel in f.files.values()]
    assert listed and all((out / rel).is_file() for rel in listed)
    assert {k for f in info.frames for k in f.files} == {"fluid", "diffuse"}
    on_disk = {p for p in out.rglob("*") if p.is_file() and p.name != ".whitecap.lock"}
    assert on_disk == set(owned_files(out)) | {out / "diffuse" / "counts.csv"}  # nothing unrecorded
    same = _foam(imported, tmp_path / "in_place")
    for i, rel in same.files("diffuse"):
        assert (out / rel).read_bytes() == (tmp_path / "in_place" / rel).read_bytes(), i
    for i, rel in info.files("fluid"):  # the run's fluid files, as they are (io.write_copy)
        assert (out / rel).read_bytes() == (imported / rel).read_bytes(), i
