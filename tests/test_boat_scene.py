"""scenes/boat.toml: the example scene of a boat at sea loads and is wired as it says (no simulation)."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import trimesh

from whitecap.config import load_scene
from whitecap.geometry import obstacle_transform

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "boat.toml"


def _boat(scene):
    k = int(scene.render.camera_follow.split(":", 1)[1])
    return k, scene.obstacle[k]


def test_boat_scene_validates_and_follows_a_floating_dynamic_body():
    scene = load_scene(SCENE)
    assert isinstance(scene.render.camera_follow, str) and scene.render.camera_follow.startswith("body:")
    k, boat = _boat(scene)
    assert boat.dynamic and boat.motion is None
    assert boat.density is not None and boat.density < scene.solver.rest_density  # it floats
    # The open sea, no tank, a low camera over the water.
    assert scene.render.sea and scene.render.container in (None, "none") and not scene.render.ground
    assert scene.render.camera_preset == "over_water"
    # The waves come from a prescribed wave maker, not another dynamic body.
    assert any(o.motion is not None and o.motion.kind == "piston" for o in scene.obstacle)
    assert sum(o.dynamic for o in scene.obstacle) == 1


def test_boat_assets_exist_are_small_and_the_texture_maps_by_uvs():
    scene = load_scene(SCENE)
    _, boat = _boat(scene)
    base = SCENE.parent
    col = trimesh.load(base / boat.mesh, force="mesh")
    assert col.is_watertight and col.is_winding_consistent and col.volume > 0
    render = trimesh.load(base / boat.render_mesh, force="mesh")
    uv = getattr(render.visual, "uv", None)
    assert uv is not None and len(uv) == len(render.vertices)
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    # The render hull lies on the collision hull (same frame, within 2 mm).
    assert np.allclose(render.bounds, col.bounds, atol=0.002)
    img = iio.imread(base / boat.texture)
    assert img.ndim == 3 and img.shape[2] in (3, 4) and img.shape[0] >= 256 and img.shape[1] >= 256
    # Painted, not blank: red antifouling, a white stripe and navy topside all present.
    px = img[..., :3].reshape(-1, 3).astype(int)
    assert ((px[:, 0] > 120) & (px[:, 1] < 60)).mean() > 0.05          # red
    assert (px.min(1) > 220).mean() > 0.01                              # white
    assert ((px[:, 2] > 60) & (px[:, 0] < 40)).mean() > 0.05            # navy
    assets = [base / p for p in (boat.mesh, boat.render_mesh, boat.texture)] + [
        base / o.mesh for o in scene.obstacle if o is not boat]
    assert sum(p.stat().st_size for p in set(assets)) < 1_000_000


def test_boat_starts_at_the_water_inside_the_domain():
    scene = load_scene(SCENE)
    _, boat = _boat(scene)
    hull = trimesh.load(SCENE.parent / boat.mesh, force="mesh")
    hull.apply_transform(obstacle_transform(boat))
    lo, hi = hull.bounds
    water = max(f.upper[2] for f in scene.fluid)
    assert lo[2] < water < hi[2]                                         # keel in, deck out
    assert np.all(lo > np.array(scene.domain.lower)) and np.all(hi < np.array(scene.domain.upper))


def test_boat_makes_way_into_the_waves_and_stays_in_the_domain():
    """Driven ahead (toward the wave maker) with surge, sway and yaw held and heave, pitch free, at a
    speed that leaves it clear of the wave maker and inside the domain at the last frame."""
    scene = load_scene(SCENE)
    _, boat = _boat(scene)
    assert boat.drive is not None
    assert boat.translation_dof == [False, False, True] and boat.rotation_dof[1] and not boat.rotation_dof[2]
    u = boat.drive.velocity[0]
    maker = next(o for o in scene.obstacle if o.motion is not None)
    assert u < 0 and maker.translate[0] < boat.translate[0]  # toward the waves
    hull = trimesh.load(SCENE.parent / boat.mesh, force="mesh")
    hull.apply_transform(obstacle_transform(boat))
    t_end = scene.output.frames / scene.solver.frame_rate
    travel = u * (t_end - boat.drive.ramp / 2)  # the smoothstep ramp lags by half its length
    bow_end = hull.bounds[0][0] + travel
    assert bow_end > maker.translate[0] + maker.motion.stroke / 2 + 0.2  # 20 cm clear of the paddle's face
    assert hull.bounds[1][0] < scene.domain.upper[0]
