"""scenes/creek.toml: the mountain creek loads and its terrain, emitter, sink and pool fit
together as its header says (no simulation)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from whitecap.config import load_scene
from whitecap.terrain import heightfield

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "creek.toml"
sys.path.insert(0, str(ROOT / "scripts"))

import make_creek_assets as assets  # noqa: E402


def test_creek_scene_matches_its_asset_script():
    scene = load_scene(SCENE)
    t = scene.terrain
    assert list(t.lower) == list(assets.LOWER) and list(t.size) == list(assets.SIZE)
    assert list(t.height) == list(assets.HEIGHT)
    # The terrain reaches well beyond the domain (hillside around the water); grass, rock where steep.
    lo, hi = np.asarray(scene.domain.lower), np.asarray(scene.domain.upper)
    assert t.lower[0] < lo[0] - 0.5 and t.lower[0] + t.size[0] > hi[0] + 0.5
    assert t.material == "grass" and t.rock_slope < 45  # grassy ground, rock on the crag, banks and stones
    assert scene.render.container in (None, "none") and not scene.render.ground


def test_water_enters_at_the_top_of_the_channel_and_leaves_at_the_bottom():
    scene = load_scene(SCENE)
    hf = heightfield(scene, str(SCENE))
    r = scene.solver.particle_radius
    (em,), (sink,) = scene.emitter, scene.sink
    sites, direction, speed = em.sites(r)
    # The emitter: above the channel bed at the upstream end, pointing downstream (+x).
    ground = hf(sites[:, 0], sites[:, 1])
    assert (sites[:, 2] - ground > r).all(), "emitter sites in or on the ground"
    assert direction[0] > 0 and speed > 0
    x0 = sites[:, 0].mean()
    assert x0 < 0.1 * (scene.domain.upper[0] - scene.domain.lower[0])
    assert np.allclose(sites[:, 1].mean(), assets.axis_y(x0), atol=0.02)  # on the creek's axis
    # It is the top of the creek: the bed falls from there to the pool and beyond.
    xs = np.linspace(x0, scene.domain.upper[0], 50)
    bed = hf(xs, assets.axis_y(xs))
    assert bed[0] > bed.min() + 0.3
    assert sites[:, 2].min() > bed[1:].max()
    # The sink: across the bottom end of the domain, past the pool's lip, covering the whole
    # channel section there, and downstream of everything else.
    assert sink.shape == "box" and sink.lower[0] > assets.POOL[1] and sink.upper[0] >= scene.domain.upper[0]
    assert sink.lower[1] <= scene.domain.lower[1] and sink.upper[1] >= scene.domain.upper[1]
    assert sink.lower[2] <= float(hf(np.array([sink.lower[0]]), assets.axis_y(np.array([sink.lower[0]])))[0])
    # The pool: the initial block sits in it, full to the lip, away from the sink.
    (pool,) = scene.fluid
    assert assets.POOL[0] - 0.05 <= pool.lower[0] and pool.upper[0] <= sink.lower[0]
    assert pool.upper[2] <= assets.LIP + 2 * r  # full to the lip, a particle layer at most above it
    # The channel's banks hold the water: higher than the flow on both sides all along.
    for x in np.linspace(0.1, 1.8, 12):
        y0 = assets.axis_y(x)
        bank = hf(np.array([x, x]), np.array([y0 - 0.38, y0 + 0.38]))
        assert (bank > hf(np.array([x]), np.array([y0]))[0] + 0.12).all(), x


def test_the_inflow_falls_from_a_notch_in_a_crag_that_curves_round_the_channels_head():
    scene = load_scene(SCENE)
    hf = heightfield(scene, str(SCENE))
    sites, _, _ = scene.emitter[0].sites(scene.solver.particle_radius)
    x0, y0 = sites[:, 0].mean(), assets.axis_y(0.0)
    # Rock walls either side of the notch stand well above the water entering through it.
    walls = hf(np.full(2, x0), np.array([y0 - 0.3, y0 + 0.3]))
    assert (walls > sites[:, 2].max() + 0.1).all()
    # The crag's face is no straight wall across the valley: where it falls below the notch's
    # lip moves downstream away from the channel, and its line is broken.
    xs = np.linspace(-0.6, 0.8, 701)

    def face_x(dy):
        z = hf(xs, np.full_like(xs, y0 + dy))
        return xs[np.argmax(z < assets.NOTCH[0])]

    left = [face_x(-d) for d in (0.25, 0.45, 0.65)]
    right = [face_x(d) for d in (0.25, 0.45, 0.65)]
    assert left[2] > left[0] + 0.1 and right[2] > right[0] + 0.1
    assert abs(face_x(-0.45) - face_x(0.45)) > 0.005


def test_creek_heightmap_is_made_by_its_script():
    import imageio.v3 as iio

    img = iio.imread(ROOT / "scenes" / "assets" / "creek.png")
    assert img.dtype == np.uint16 and img.shape == (assets.PIXELS[1], assets.PIXELS[0])
    assert np.array_equal(img, np.round(assets.creek_heights() * 65535).astype(np.uint16))
