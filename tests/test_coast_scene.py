"""scenes/coast.toml: the breakwater in a storm loads and is wired as it says (no simulation).

That no particle ends a step inside the terrain while a wave runs up it is
tests/test_terrain.py::test_wave_running_up_the_terrain_never_ends_a_step_inside_it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from whitecap.config import load_scene
from whitecap.geometry import obstacle_transform
from whitecap.sim.obstacles import compute_sdf
from whitecap.terrain import Heightfield, read_heightmap

from .conftest import BPY_END

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "coast.toml"
sys.path.insert(0, str(ROOT / "scripts"))
import make_coast_assets as assets  # noqa: E402


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("WHITECAP_CACHE", str(tmp_path / "cache"))


def _by_material(scene, material):
    return [o for o in scene.obstacle if o.material == material]


def _placed(o, mesh: str | None = None) -> trimesh.Trimesh:
    m = trimesh.load(SCENE.parent / (mesh or o.mesh), force="mesh")
    m.apply_transform(obstacle_transform(o))
    return m


def _terrain(scene) -> Heightfield:
    t = scene.terrain
    lo, hi = t.height
    return Heightfield(lo + (hi - lo) * read_heightmap(SCENE.parent / t.heightmap), t.lower, t.size)


def test_coast_scene_is_an_open_sea_over_terrain_with_the_script_geometry():
    scene = load_scene(SCENE)
    assert scene.terrain is not None and scene.terrain.material == "sand"
    assert scene.render.sea and not scene.render.ground and scene.render.container in (None, "none")
    assert scene.render.sea_level == pytest.approx(assets.SEA_LEVEL) == scene.terrain.water_level
    assert list(scene.domain.lower) == list(assets.DOMAIN_LOWER)
    assert list(scene.domain.upper) == list(assets.DOMAIN_UPPER)
    assert list(scene.terrain.lower) == list(assets.TERRAIN_LOWER)
    assert list(scene.terrain.size) == list(assets.TERRAIN_SIZE)
    assert list(scene.terrain.height) == list(assets.TERRAIN_HEIGHT)
    assert max(f.upper[2] for f in scene.fluid) == pytest.approx(assets.SEA_LEVEL)
    # The terrain image is far larger than the domain: beach around it, sea bed under the open sea.
    t = scene.terrain
    assert t.lower[0] < scene.domain.lower[0] - 1 and t.lower[0] + t.size[0] > scene.domain.upper[0] + 1
    assert t.lower[1] < scene.domain.lower[1] - 1 and t.lower[1] + t.size[1] > scene.domain.upper[1] + 1


def test_the_wave_maker_is_a_piston_at_the_deep_end():
    scene = load_scene(SCENE)
    (paddle,) = [o for o in scene.obstacle if o.motion is not None]
    assert paddle.motion.kind == "piston" and paddle.motion.axis == [1.0, 0.0, 0.0]
    assert not any(o.dynamic for o in scene.obstacle)
    m = _placed(paddle)
    lo, hi = m.bounds
    # It spans the width and stands out of the water, its stroke inside the domain.
    assert lo[1] <= scene.domain.lower[1] and hi[1] >= scene.domain.upper[1] and hi[2] > assets.SEA_LEVEL + 0.1
    half = paddle.motion.stroke / 2
    assert lo[0] - half >= scene.domain.lower[0] - 1e-9
    # The deep end: the sea bed under the paddle is the lowest in the domain, and the paddle's face
    # touches the water.
    hf = _terrain(scene)
    xs = np.linspace(scene.domain.lower[0], scene.domain.upper[0], 61)
    bed = hf(xs, np.full_like(xs, 0.6))
    x_paddle = paddle.translate[0]
    assert hf(np.array([x_paddle]), np.array([0.6]))[0] <= bed.min() + 0.005
    assert min(f.lower[0] for f in scene.fluid) == pytest.approx(hi[0], abs=0.011)
    # and the breakwater lies between it and the beach.
    (bw,) = _by_material(scene, "concrete")
    assert _placed(bw).bounds[0][0] > hi[0] + half + 0.5


def test_the_asset_script_makes_watertight_units_and_solids():
    unit = assets.tetrapod()
    assert unit.is_watertight and unit.is_winding_consistent and unit.volume > 0
    # Four legs: about the size asked for, much less volume than its bounding box (not a blob).
    assert abs(np.ptp(unit.vertices[:, 2]) - assets.UNIT_SIZE) < 0.3 * assets.UNIT_SIZE
    assert unit.volume < 0.35 * np.prod(np.ptp(unit.vertices, axis=0))
    assert np.allclose(unit.center_mass, 0.0, atol=1e-3)
    saved = trimesh.load(SCENE.parent / "assets" / "coast_unit.ply", force="mesh")
    assert saved.is_watertight and abs(saved.volume - unit.volume) < 0.02 * unit.volume
    scene = load_scene(SCENE)
    for o in scene.obstacle:
        if o.material == "terrain":
            continue
        m = trimesh.load(SCENE.parent / o.mesh, force="mesh")
        assert m.is_watertight and m.is_winding_consistent and m.volume > 0, o.mesh
    # The drawn breakwater is many units (a few hundred copies of the one unit) on a core.
    (bw,) = _by_material(scene, "concrete")
    render = trimesh.load(SCENE.parent / bw.render_mesh, force="mesh", process=False)
    n_units = (len(render.faces) - 100) // len(unit.faces)
    assert 100 < n_units < 600
    files = [SCENE.parent / p for o in scene.obstacle if o.material != "terrain" for p in (o.mesh, o.render_mesh) if p]
    assert sum(p.stat().st_size for p in set(files)) < 4_500_000


def test_the_breakwater_stands_on_the_terrain_inside_the_domain():
    scene = load_scene(SCENE)
    (bw,) = _by_material(scene, "concrete")
    col = _placed(bw)
    lo, hi = col.bounds
    dom_lo, dom_hi = np.array(scene.domain.lower), np.array(scene.domain.upper)
    # (the solid reaches a few centimetres past the y = 0 wall, so the water along that wall meets it)
    assert np.all(lo[:2] >= dom_lo[:2] - 0.06) and np.all(hi >= dom_lo) and np.all(hi[:2] <= dom_hi[:2])
    assert hi[2] < dom_hi[2]
    # Its crest stands out of the still water, by more than the units' size, and its head is inside the domain
    # with open water beside it (the waves pass it and run up the beach).
    assert hi[2] > assets.SEA_LEVEL + assets.UNIT_SIZE
    assert hi[1] < dom_hi[1] - 0.3
    # It stands on the ground: its base is below the terrain surface everywhere under it (no gap the water
    # could run through), and its solid rises above the ground where the mound is.
    hf = _terrain(scene)
    v = np.asarray(col.vertices)
    bottom = v[v[:, 2] < lo[2] + 1e-6]
    assert np.all(bottom[:, 2] < hf(bottom[:, 0], bottom[:, 1]) - 0.02)
    x = np.full(50, assets.CREST_X)
    y = np.linspace(0.02, assets.HEAD_Y - 0.1, 50)
    sdf = compute_sdf(col.vertices, col.faces, np.stack([x, y, np.full(50, assets.SEA_LEVEL)], 1))
    assert np.all(sdf < 0)  # the crest line at the still water is inside the mound
    # The render mesh is the same breakwater, and runs on beyond the domain's y = 0 side.
    render = _placed(bw, bw.render_mesh)
    rlo, rhi = render.bounds
    assert rlo[1] < dom_lo[1] - 0.2 and abs(rhi[2] - hi[2]) < 0.02 and abs(rhi[1] - hi[1]) < 0.05


def test_rocks_lie_on_the_beach_beside_the_breakwater_head():
    scene = load_scene(SCENE)
    (rocks,) = _by_material(scene, "rock")
    m = _placed(rocks)
    parts = m.split(only_watertight=True)
    assert len(parts) == len(assets.ROCKS)
    hf = _terrain(scene)
    dom_lo, dom_hi = np.array(scene.domain.lower), np.array(scene.domain.upper)
    for p in parts:
        c = p.centroid
        ground = hf(np.array([c[0]]), np.array([c[1]]))[0]
        assert p.bounds[0][2] < ground < p.bounds[1][2]          # partly buried, partly out
        assert np.all(p.bounds[0][:2] > dom_lo[:2]) and np.all(p.bounds[1][:2] < dom_hi[:2])
        assert c[1] > assets.HEAD_Y - 0.1                       # beside the head, not on the breakwater


DRESS_SCRIPT = """
import types, bpy
from whitecap.io.record import Obstacle
from whitecap.render.terrain import dress_terrain
sc = bpy.context.scene
for k in range(3):
    me = bpy.data.meshes.new(f"m{k}")
    me.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 1)], [], [(0, 1, 2)])
    sc.collection.objects.link(bpy.data.objects.new(f"obstacle_{k}", me))
info = types.SimpleNamespace(obstacles=[Obstacle(material=m) for m in ("stone", "concrete", "rock")])
assert dress_terrain(sc, info, None, preview=True) == []          # no terrain: the ground stays
names = lambda k: {n.name for n in sc.objects[f"obstacle_{k}"].data.materials[0].node_tree.nodes}
assert not sc.objects["obstacle_0"].data.materials                  # stone is left to the obstacle material
assert {"terrain_concrete", "terrain_wet"} <= names(1), names(1)
assert "terrain_rock_cells" in names(2) and "terrain_rock_mask" not in names(2)
print("ok")
"""


def test_concrete_and_rock_obstacles_get_the_procedural_materials():
    pytest.importorskip("bpy")
    out = subprocess.run([sys.executable, "-c", DRESS_SCRIPT + BPY_END], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(ROOT / "src")})
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr[-2000:]


def test_an_imported_run_takes_the_terrain_of_its_scene_toml(tmp_path):
    """README's recipe: a run whitecap did not simulate gets its scene.toml's [terrain] at render time."""
    import types

    from whitecap.render.terrain import scene_terrain

    run = tmp_path / "run"
    run.mkdir()
    from whitecap.io.record import Obstacle

    info = types.SimpleNamespace(obstacles=[Obstacle(name="Box", role="container", mesh="geometry/Box.ply",
                                                     material="stone")],
                                 domain={"lower": [-0.85, -0.38, -0.01], "upper": [2.47, 1.06, 0.96]})
    assert scene_terrain(info, run) == []                               # no scene.toml
    (run / "scene.toml").write_text("[render]\nsea = true\n")
    assert scene_terrain(info, run) == []                               # no [terrain]
    heightmap = (SCENE.parent / "assets" / "coast_quay.png").as_posix()
    (run / "scene.toml").write_text(
        f'[terrain]\nheightmap = "{heightmap}"\nlower = {list(assets.QUAY_LOWER)}\nsize = {list(assets.QUAY_SIZE)}\n'
        f'height = {list(assets.QUAY_HEIGHT)}\nmaterial = "concrete"\nrender_resolution = 0.05\n'
        "[render]\nground = false\nsea = true\n")
    (entry,) = scene_terrain(info, run)
    assert entry.material == "terrain"
    surface = trimesh.load(entry.render_mesh, force="mesh")
    lo, hi = surface.bounds
    assert np.allclose(lo[:2], assets.QUAY_LOWER) and np.allclose(hi[:2], np.add(assets.QUAY_LOWER, assets.QUAY_SIZE))
    # The apron under the tank is flat, a few millimetres above the imported domain's floor.
    v = np.asarray(surface.vertices)
    under = v[(v[:, 0] > 0) & (v[:, 0] < 1.6) & (v[:, 1] > 0) & (v[:, 1] < 0.67)]
    assert np.abs(under[:, 2] - assets.QUAY_TOP).max() < 0.003 and assets.QUAY_TOP > info.domain["lower"][2]
    # A run whitecap simulated holds its terrain in run.json already: nothing is added twice.
    info.obstacles.append(entry)
    assert scene_terrain(info, run) == []
