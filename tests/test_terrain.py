"""Terrain ([terrain]): heightmap → watertight solid, collision through the obstacle SDFs, errors, material."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from whitecap.cli import main
from whitecap.config import load_scene, scene_from_dict
from whitecap.errors import InputError
from whitecap.sim import obstacles as obs
from whitecap.sim.driver import build_solver
from whitecap.terrain import Heightfield, read_heightmap, write_heightmap

from .conftest import BPY_END

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
from make_terrain_assets import beach_heights  # noqa: E402


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("WHITECAP_CACHE", str(tmp_path / "cache"))


def beach_scene(tmp_path, r=0.01, **terrain) -> dict:
    """A 0.9 m flume: still water 0.1 m deep and a 0.3 m block at the left end that collapses
    into a bore running up a beach from a heightmap (toe at x ≈ 0.3 m, 0.3 m high at the right)."""
    png = tmp_path / "beach.png"
    write_heightmap(png, beach_heights(96, 24, seed=2, toe=0.3, top=0.95, rocks=0))
    return {
        "domain": {"upper": [0.9, 0.15, 0.4]},
        "solver": {"particle_radius": r},
        "fluid": [{"lower": [0, 0, 0], "upper": [0.45, 0.15, 0.1]}, {"lower": [0, 0, 0.1], "upper": [0.15, 0.15, 0.3]}],
        "terrain": {"heightmap": str(png), "height": [0.0, 0.4], **terrain},
        "foam": {"enabled": False},
    }


def test_heightmap_mesh_matches_the_image_and_is_watertight(tmp_path):
    png = tmp_path / "h.png"
    rng = np.random.default_rng(0)
    img = np.clip(0.5 + 0.1 * rng.standard_normal((9, 17)), 0, 1)
    write_heightmap(png, img)
    assert np.abs(read_heightmap(png) - img).max() < 1e-4  # 16 bits survive the round trip
    sc = scene_from_dict({"domain": {"upper": [1.6, 0.8, 0.5]}, "solver": {"particle_radius": 0.01},
                          "terrain": {"heightmap": str(png), "lower": [0, 0], "size": [1.6, 0.8],
                                      "height": [0.05, 0.25], "resolution": 0.1, "render_resolution": 0.025}})
    (o,) = sc.obstacle
    assert o.material == "terrain" and o.render_mesh != o.mesh
    solid = trimesh.load(o.mesh, process=True)
    assert solid.is_watertight and solid.is_winding_consistent and solid.volume > 0
    assert solid.bounds[0][2] < sc.domain.lower[2]  # closed down below the domain floor
    surface = trimesh.load(o.render_mesh)
    assert len(surface.vertices) > 10 * len(solid.vertices) / 2  # the render mesh is finer
    # Pixel centres: the columns every 0.1 m, the rows every 0.1 m from the top (+y) edge; the
    # collision grid (0.1 m) and the render grid (0.025 m) both have vertices there.
    rows, cols = np.meshgrid(np.arange(9), np.arange(17), indexing="ij")
    x, y = cols * 0.1, 0.8 - rows * 0.1
    want = 0.05 + 0.2 * img
    for m in (solid, surface):
        v = np.asarray(m.vertices)
        top = v[v[:, 2] > 0.0]
        key = {(round(a, 6), round(b, 6)): c for a, b, c in top}
        got = np.array([key[(round(a, 6), round(b, 6))] for a, b in zip(x.ravel(), y.ravel())])
        assert np.abs(got - want.ravel()).max() < 1e-4
    # Between pixels: a smooth spline, within the neighbours' range.
    hf = Heightfield(want, [0, 0], [1.6, 0.8])
    mid = hf(np.array([0.05]), np.array([0.75]))[0]
    assert min(want[0, 0], want[0, 1], want[1, 0], want[1, 1]) - 0.02 < mid < max(want[:2, :2].ravel()) + 0.02
    # A resolved scene (as simulate writes it) keeps the one terrain obstacle.
    again = scene_from_dict(__import__("tomllib").loads(sc.to_toml()))
    assert len(again.obstacle) == 1 and again.obstacle[0].mesh == o.mesh


def test_wave_running_up_the_terrain_never_ends_a_step_inside_it(tmp_path):
    sc = scene_from_dict(beach_scene(tmp_path))
    r = sc.solver.particle_radius
    s = build_solver(sc)
    grid = obs.load_obstacles(sc).grids[-1]
    solid = trimesh.load(sc.obstacle[-1].mesh)
    hf_x = lambda x: np.interp(x, *_profile(solid))  # noqa: E731
    shore = 0.0
    closest = np.inf
    for _ in range(140):  # 0.58 s: the bore runs up the slope
        s.step(1 / 240)
        x = s.state.x.to_numpy()
        closest = min(closest, float(grid.sample(x).min()))
        # Exact distances to the collision mesh, not only the solver's own field.
        assert obs.compute_sdf(solid.vertices, solid.faces, x).min() > -0.1 * r
        wet = x[np.abs(x[:, 2] - hf_x(x[:, 0])) < 3 * r]
        shore = max(shore, float(wet[:, 0].max()) if len(wet) else 0.0)
    assert closest > 0.99 * r, f"a particle ended a step {closest / r:.3f} r from the terrain"
    # Control: the water did run up the slope, well past the still-water shoreline (x ≈ 0.46 m).
    still = float(np.interp(0.1, _profile(solid)[1], _profile(solid)[0]))
    assert shore > still + 0.1, (shore, still)


def _profile(solid) -> tuple[np.ndarray, np.ndarray]:
    """The terrain's top surface along x at the flume's mid-width: (x, z), x increasing."""
    v = np.asarray(solid.vertices)
    top = v[v[:, 2] > solid.bounds[0][2] + 1e-6]
    ys = np.unique(top[:, 1].round(6))
    mid = top[np.abs(top[:, 1] - ys[len(ys) // 2]) < 1e-6]
    mid = mid[np.argsort(mid[:, 0])]
    return mid[:, 0], mid[:, 2]


def test_bad_heightmaps_are_one_line_errors(tmp_path, capsys):
    bad = tmp_path / "notes.png"
    bad.write_text("this is not a picture\n")
    eight = tmp_path / "eight.png"
    import imageio.v3 as iio

    iio.imwrite(eight, np.full((8, 8), 100, np.uint8))
    for path, what in ((bad, "not an image"), (eight, "8-bit")):
        scene = tmp_path / f"{path.stem}.toml"
        scene.write_text('[[fluid]]\nlower = [0, 0, 0]\nupper = [0.1, 0.1, 0.1]\n'
                         f'[terrain]\nheightmap = "{path.name}"\n')
        code = main(["simulate", str(scene), "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1, err
        assert path.name in err and "terrain.heightmap" in err and what in err, err
    with pytest.raises(InputError, match="terrain: give exactly one of 'heightmap' and 'mesh'"):
        scene_from_dict({"terrain": {"height": [0, 1]}}, "s.toml")
    with pytest.raises(InputError, match="terrain.heightmap: file not found"):
        scene_from_dict({"terrain": {"heightmap": "missing.png"}}, "s.toml", tmp_path)


def test_terrain_from_an_open_mesh(tmp_path):
    # A tilted open sheet: the ground is its surface, closed down into a solid.
    V = np.array([[0, 0, 0.05], [1, 0, 0.25], [1, 0.5, 0.25], [0, 0.5, 0.05]], float)
    sheet = trimesh.Trimesh(V, [[0, 1, 2], [0, 2, 3]])
    sheet.export(str(tmp_path / "sheet.obj"))
    sc = load_scene(_write(tmp_path / "s.toml", '[domain]\nupper = [1, 0.5, 0.5]\n[terrain]\nmesh = "sheet.obj"\n'))
    solid = trimesh.load(sc.obstacle[0].mesh)
    assert solid.is_watertight and solid.volume > 0
    v = np.asarray(solid.vertices)
    top = v[v[:, 2] > solid.bounds[0][2] + 1e-6]
    assert np.abs(top[:, 2] - (0.05 + 0.2 * np.clip(top[:, 0], 0, 1))).max() < 2e-3


def _write(p: Path, text: str) -> Path:
    p.write_text(text)
    return p


MATERIAL_SCRIPT = """
import sys, bpy
from whitecap.config import Terrain
from whitecap.render.terrain import terrain_material
t = Terrain(heightmap="x.png", water_level=0.2, grass_above=0.5)
for preview in (False, True):
    mat = terrain_material(t, (0.0, 0.6), 4.0, preview)
    names = {n.name for n in mat.node_tree.nodes}
    need = {"terrain_sand", "terrain_sand_grain", "terrain_sand_ripples", "terrain_rock_mask", "terrain_rock_cells",
            "terrain_grass_mask", "terrain_wet", "terrain_wet_colour", "terrain_wet_rough",
            # rock: cracks, a warm stain, moss on ledges and in crevices; grass: dry and bare patches;
            # crevices darker and the rock in a channel damp (ambient occlusion)
            "terrain_rock_cracks", "terrain_rock_warm", "terrain_moss", "terrain_grass_dry_mix",
            "terrain_grass_earth_mix", "terrain_occlusion", "terrain_crevice", "terrain_damp"}
    assert need <= names, need - names
    assert ("terrain_bump" in names) != preview
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    assert bsdf.inputs["Base Color"].is_linked and bsdf.inputs["Roughness"].is_linked
for preset in ("rock", "grass", "concrete"):
    names = {n.name for n in terrain_material(Terrain(heightmap="x.png", material=preset), (0, 1), 2.0).node_tree.nodes}
    assert f"terrain_{preset}" in names, (preset, names)
print("ok")
"""


def test_terrain_material_has_its_layers():
    pytest.importorskip("bpy")
    out = subprocess.run([sys.executable, "-c", MATERIAL_SCRIPT + BPY_END], capture_output=True, text=True, timeout=120,
                         env={**__import__("os").environ, "PYTHONPATH": str(ROOT / "src")})
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr[-2000:]
