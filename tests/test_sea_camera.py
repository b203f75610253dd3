"""Open sea around the domain (render/sea.py) and the follow camera (render/camera_follow.py).

The camera paths and the sea's geometry are pure numpy; one test renders a
small frame in Blender (a child process, as `whitecap render` runs it) to
check that the sea meets the simulated water without a seam.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from whitecap.config import Render
from whitecap.io.run import RunInfo
from whitecap.render import camera_follow, sea, stage

from .conftest import BPY_END

SRC = Path(__file__).resolve().parents[1] / "src"
LO, HI = np.array([0.0, 0.0, 0.0]), np.array([0.8, 0.4, 0.4])
FPS = 30.0


def run_info(positions=None, quaternions=None, translate=(0.5, 0.2, 0.1)) -> RunInfo:
    """A run of len(positions) frames whose obstacle 0 (a missing mesh: its centre is its
    translate) has the given recorded poses."""
    n = len(positions) if positions is not None else 1
    frames = []
    for i in range(n):
        f = {"index": i, "time": i / FPS, "files": {}, "made_from": {}}
        if positions is not None:
            q = quaternions[i] if quaternions is not None else [1.0, 0.0, 0.0, 0.0]
            f["bodies"] = [{"position": list(map(float, positions[i])), "quaternion": list(q)}]
        frames.append(f)
    return RunInfo(particle_radius=0.01, rest_density=1000.0, particle_mass=0.008, gravity=[0.0, 0.0, -9.81],
                   domain={"lower": LO.tolist(), "upper": HI.tolist()}, frame_rate=FPS, frames=frames,
                   obstacles=[{"mesh": "no_such_mesh.obj", "translate": list(translate)}])


# ============================================================================ follow camera
def test_follow_camera_tracks_the_body_with_the_set_smoothing():
    """A body that jumps 0.3 m in x at frame 10: the look-at point follows the critically damped
    step response 1 − (1 + t/τ)·e^(−t/τ), never overshoots, and the camera keeps a fixed offset
    from it. With smoothing 0 the camera is rigidly attached."""
    n, tau = 60, 0.25
    pos = np.zeros((n, 3))
    pos[10:, 0] = 0.3
    info = run_info(pos)
    cfg = Render(camera_follow="body:0", camera_smoothing=tau)
    keys, targets = camera_follow.follow_keys(cfg, info, None, 0, n - 1, 4 / 3)
    x = np.array([targets[i][0] for i in range(n)]) - 0.5
    assert np.allclose(x[:10], 0.0)
    t = (np.arange(n) - 9) / FPS
    want = 0.3 * (1 - (1 + t / tau) * np.exp(-t / tau))
    assert np.allclose(x[10:], want[10:], atol=1e-9)
    assert x.max() <= 0.3 + 1e-12 and 0.29 < x[-1]  # no overshoot, settled after 8 τ
    offsets = np.array([np.subtract(keys[i], targets[i]) for i in range(n)])
    assert np.allclose(offsets, offsets[0]) and np.linalg.norm(offsets[0]) > 0.01
    rigid = camera_follow.follow_keys(Render(camera_follow="body:0", camera_smoothing=0), info, None, 0, n - 1,
                                      4 / 3)[1]
    assert np.allclose([rigid[i][0] - 0.5 for i in range(n)], pos[:, 0])


def test_follow_camera_lags_a_steady_body_by_two_time_constants():
    """A body moving at a steady 0.5 m/s: the smoothed point lags it by 2·τ·v (within a frame's
    travel); the keys of a later frame range are those of the whole run (smoothing from frame 0)."""
    n, tau, v = 90, 0.2, 0.5
    pos = np.zeros((n, 3))
    pos[:, 1] = v * np.arange(n) / FPS
    info = run_info(pos)
    cfg = Render(camera_follow="body:0", camera_smoothing=tau)
    _, targets = camera_follow.follow_keys(cfg, info, None, 0, n - 1, 4 / 3)
    lag = (0.2 + pos[-1, 1]) - targets[n - 1][1]
    assert lag == pytest.approx(2 * tau * v, abs=v / FPS)
    later = camera_follow.follow_keys(cfg, info, None, 50, n - 1, 4 / 3)
    assert sorted(later[1]) == list(range(50, n)) and later[1][70] == targets[70]


def test_follow_camera_turns_with_the_body():
    """The followed point is the body's centre carried by the whole pose: a quarter turn about z
    (about the world origin, as run.json's poses are) moves the centre (0.5, 0.2) to (−0.2, 0.5)."""
    q = [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]
    info = run_info(np.zeros((3, 3)), [q] * 3)
    track = camera_follow.body_track(info, 0, [0.5, 0.2, 0.1], [0, 1, 2])
    assert np.allclose(track, [[-0.2, 0.5, 0.1]] * 3)


def test_follow_an_obstacle_that_is_not_there_is_a_one_line_error():
    from whitecap.errors import InputError

    with pytest.raises(InputError, match="camera_follow = 'body:3'.*1 obstacle"):
        camera_follow.follow_keys(Render(camera_follow="body:3"), run_info(np.zeros((2, 3))), None, 0, 1, 4 / 3)
    with pytest.raises(ValueError, match="body:K"):
        Render(camera_follow="boat")


@pytest.mark.parametrize("follow", [None, "body:0"])
def test_over_water_preset_is_low_and_looks_across_the_water(follow):
    """over_water: the camera stands its height (default 4 % of the framed width) above the sea
    level, outside the framed region, and looks within 6° of the horizontal."""
    info = run_info(np.zeros((3, 3)), translate=(0.5, 0.2, 0.12))  # a body floating at the level
    cfg = Render(camera_preset="over_water", sea_level=0.12, camera_follow=follow)
    keys, targets = camera_follow.follow_keys(cfg, info, (LO, HI), 0, 2, 16 / 9)
    for i in range(3):
        p, t = np.array(keys[i]), np.array(targets[i])
        assert 0 < p[2] - 0.12 <= 0.04 * 0.8 + 1e-9
        d = t - p
        pitch = math.degrees(math.atan2(-d[2], np.linalg.norm(d[:2])))
        assert -1 < pitch < 6, pitch
    assert keys[0][1] < 0 if follow is None else keys[0][1] < 0.2  # in front (−y) of what it frames
    cfg = Render(camera_preset="over_water", sea_level=0.12, camera_height=0.05)
    assert camera_follow.follow_keys(cfg, info, (LO, HI), 0, 0, 1.0)[0][0][2] == pytest.approx(0.17)
    # stage.camera_keys (what the exports write) gives the same positions
    keys = stage.camera_keys(cfg, info, (LO, HI), 0, 0, 1.0)[0]
    assert keys == camera_follow.follow_keys(cfg, info, (LO, HI), 0, 0, 1.0)[0]


# ============================================================================ sea geometry
def water_slab(lo, hi, n: int, height) -> tuple[np.ndarray, np.ndarray]:
    """A closed box of water over the footprint of [lo, hi]: a top grid of n×n cells at
    ``height(x, y)``, the floor at lo z, the sides on the walls. Vertices and faces."""
    xs, ys = np.linspace(lo[0], hi[0], n + 1), np.linspace(lo[1], hi[1], n + 1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    top = np.column_stack([X.ravel(), Y.ravel(), height(X, Y).ravel()])
    bot = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, lo[2])])
    v = np.vstack([top, bot])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    B = (n + 1) ** 2
    f = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            f += [[a, b, c], [a, c, d], [a + B, c + B, b + B], [a + B, d + B, c + B]]
    ring = [idx[i, 0] for i in range(n)] + [idx[n, j] for j in range(n)] + \
           [idx[i, n] for i in range(n, 0, -1)] + [idx[0, j] for j in range(n, 0, -1)]
    for k in range(len(ring)):
        a, b = ring[k], ring[(k + 1) % len(ring)]
        f += [[a + B, b + B, b], [a + B, b, a]]
    return v, np.array(f)


def test_open_walls_keeps_only_the_free_surface():
    v, f = water_slab(LO, HI, 8, lambda x, y: 0.1 + 0.01 * np.sin(8 * x))
    kept = sea.open_walls(v, f, LO, HI, 0.01)
    assert len(kept) == 2 * 8 * 8 and (v[kept][:, :, 2] > 0.05).all()


def test_wall_normals_are_level_with_the_sea_at_the_side_walls():
    """The reconstruction's normals lean out over the last few radii before a side wall (no
    particles beyond it); with the sea they lose their part across the wall there (the sea is the
    water's mirror, level across the wall), keep it a reach inside, and stay unit length. A
    normal facing the wall (on a face open_walls drops) points up instead of vanishing."""
    r = 0.01
    reach = sea.WALL_NORMAL_REACH * r
    y = np.array([0.0, 0.3 * reach, reach, 0.2, HI[1] - 0.3 * reach, HI[1]])
    v = np.column_stack([np.full(len(y), 0.5), y, np.full(len(y), 0.1)])
    lean = np.array([0.0, -0.6, 0.8])  # leaning out over the y = 0 wall
    n = np.tile(lean, (len(y), 1))
    n[-2:] = (0.0, 0.6, 0.8)  # leaning out over the y = HI[1] wall
    out = sea.wall_normals(v, n, LO, HI, reach)
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0)
    assert np.allclose(out[[0, -1]], (0.0, 0.0, 1.0))  # at either wall: level
    assert np.allclose(out[[2, 3]], lean)  # a reach inside and beyond: as reconstructed
    assert 0 < -out[1, 1] < 0.6 and 0 < out[-2, 1] < 0.6  # in between: part of the lean
    facing = sea.wall_normals(v[:1], np.array([[0.0, -1.0, 0.0]]), LO, HI, reach)
    assert np.allclose(facing, (0.0, 0.0, 1.0))
    corner = sea.wall_normals(np.array([[LO[0], LO[1], 0.1]]), np.array([[-0.5, -0.5, 0.7]]), LO, HI, reach)
    assert np.allclose(corner, (0.0, 0.0, 1.0))


def test_sea_meets_the_water_at_the_wall_and_settles_to_its_level():
    """Ring 0 lies on the walls at the simulated water's height there, faces look up, and past
    the blend the sea is at its level give or take half the wave height."""
    h = lambda x, y: 0.1 + 0.02 * np.sin(6 * x + 3 * y)  # noqa: E731
    v, _ = water_slab(LO, HI, 40, h)
    layout = sea.sea_layout(LO, HI, 0.01, 50.0, fine=0.16 / 12, fine_until=0.5)
    edge, inset = sea.edge_heights(layout, v, 0.01, 0.08, reach=0.2)
    walls = layout.wall >= 0
    assert np.allclose(edge[walls], h(layout.base[walls, 0], layout.base[walls, 1]), atol=0.003)
    assert (inset == 0).all()  # the water touches every wall
    z, s = sea.sea_heights(layout, edge, 0.08, 0.2, 1.0, 0.01, 0.16, 0.0, 9.81)
    n = len(layout.base)
    assert np.allclose(z[:n], edge, rtol=0, atol=1e-12) and (s[:n] == 0).all()
    zr = z.reshape(len(layout.d), n)
    assert np.abs(zr[layout.d >= 0.2] - 0.08).max() <= 0.005 + 1e-9  # within half the wave height
    assert zr[(layout.d >= 0.2) & (layout.d < 0.3)].std() > 1e-3  # waves where the mesh resolves them
    xy = layout.xy()[layout.faces]
    area = np.cross(xy[:, 1] - xy[:, 0], xy[:, 2] - xy[:, 0])
    assert (area >= -1e-12).all() and layout.d[-1] >= 50.0


def test_sea_meets_water_that_leaves_a_wall_where_the_water_is():
    """Water that stands off the left wall (x = 0) by 0.1 m, as in front of a wave maker, and
    leaves a stretch of the front wall dry (an obstacle on it): the sea's edge on the left wall
    moves in to the water's edge (inset 0.1 m, ring 0 there, at the water's height), the dry
    stretch is bridged without a step, and no sea vertex drops to the floor."""
    h = lambda x, y: 0.1 + 0.02 * np.sin(6 * x + 3 * y)  # noqa: E731
    lo = LO + [0.1, 0.0, 0.0]
    v, _ = water_slab(lo, HI, 40, h)
    dry = (v[:, 1] < 1e-9) & (v[:, 0] > 0.4) & (v[:, 0] < 0.5)
    v[dry, 1] = 0.02  # off the front wall there
    layout = sea.sea_layout(LO, HI, 0.01, 50.0, fine=0.16 / 12, fine_until=0.5)
    edge, inset = sea.edge_heights(layout, v, 0.01, 0.08, reach=0.2)
    left = layout.wall == 3
    assert np.allclose(inset[left], 0.1, atol=1e-6)
    assert np.allclose(edge[left], h(0.1, layout.base[left, 1]), atol=0.003)
    xy = sea.sea_xy(layout, inset, 0.2)
    n = len(layout.base)
    assert np.allclose(xy[:n][left, 0], 0.1)
    front = (layout.wall == 0) & (layout.base[:, 0] > 0.12)
    x, z = layout.base[front, 0], edge[front]
    assert np.abs(np.diff(z)).max() < 0.004 and np.allclose(z, h(x, 0.0), atol=0.006)
    zs, _ = sea.sea_heights(layout, edge, 0.08, 0.2, 1.0, 0.0, 0.16, 0.0, 9.81)
    assert zs.min() > 0.07  # never down to the floor (a dark trough along the wall)
    area = np.cross(*(xy[layout.faces][:, k] - xy[layout.faces][:, 0] for k in (1, 2)))
    assert (area >= -1e-12).all()  # the rings stay in order outward


def test_a_column_in_a_dry_domain_is_not_the_sea():
    """A dam-break column 0.3 m high in the left quarter of a dry domain, the sea's level at
    0.05 m: the walls it touches carry its height, but the sea does not reach in over the dry
    floor to its far face (no inset) and the dry walls' long gaps are the floor, which a terrain
    above it hides (as before the sea could move in)."""
    v, _ = water_slab(LO, [0.2, HI[1], HI[2]], 20, lambda x, y: 0.3 + 0 * x)
    layout = sea.sea_layout(LO, HI, 0.01, 50.0, fine=0.16 / 12, fine_until=0.5)
    edge, inset = sea.edge_heights(layout, v, 0.01, 0.05, reach=0.8)
    assert (inset == 0).all()
    right = layout.wall == 1
    assert np.allclose(edge[right], LO[2])
    left = layout.wall == 3
    assert np.allclose(edge[left], 0.3, atol=1e-6)


def test_edge_jitter_does_not_run_out_across_the_sea():
    """Edge heights that alternate by ±1 cm from sample to sample (a splash, the mesh's jitter at
    the wall): ring 0 keeps them, but three detail widths out the sea varies along the wall by
    well under a millimetre, so no ridges run out from the wall (stepped slabs)."""
    layout = sea.sea_layout(LO, HI, 0.01, 50.0, fine=0.16 / 12, fine_until=0.5)
    n = len(layout.base)
    edge = 0.1 + 0.01 * (-1.0) ** np.arange(n)
    blend = 0.2
    z, _ = sea.sea_heights(layout, edge, 0.1, blend, 0.0, 0.0, 0.16, 0.0, 9.81)
    z = z.reshape(len(layout.d), n)
    front = layout.wall == 0
    assert np.allclose(z[0], edge)
    k = np.searchsorted(layout.d, 3 * sea.EDGE_DETAIL * blend)
    assert z[k, front].std() < 5e-4, z[k, front].std()


def test_still_level_is_the_settled_water():
    info = run_info()
    assert sea.still_level(Render(sea_level=0.3), info, None) == 0.3
    assert sea.still_level(Render(), info, None) == 0.0  # no frame to measure: the floor


def test_sea_means_no_container_and_refuses_a_tank():
    info = run_info()
    assert stage.container_kind(Render(sea=True), info) == "none"
    assert stage.container_kind(Render(), info) == "glass"  # a simulated run's walls held its water
    with pytest.raises(ValueError, match="render.sea needs container = 'none'"):
        Render(sea=True, container="glass")


# ============================================================================ seam render
SEAM = r"""
import sys, json, bpy, numpy as np
from pathlib import Path
from mathutils import Vector
from bpy_extras.object_utils import world_to_camera_view
from whitecap.config import Render
from whitecap.io.run import RunInfo
from whitecap.render.scene import build_scene, load_frame
run, out, variants, pts = Path(sys.argv[1]), Path(sys.argv[2]), json.loads(sys.argv[3]), json.loads(sys.argv[4])
info = RunInfo.load(run)
res = {}
for name, over in variants.items():
    cfg = Render(**{"preview_resolution": [160, 120], "preview_samples": 16, "device": "cpu", "glare": 0.0,
                    "motion_blur": False, **over})
    h = build_scene(info, cfg, "preview", 0, 0, run_dir=run)
    load_frame(h, run, info, 0)
    sc = bpy.context.scene
    sc.frame_set(0)
    res[name] = {"uv": [list(world_to_camera_view(sc, sc.camera, Vector(p)))[:2] for p in pts],
                 "objects": sorted(o.name for o in sc.objects)}
    sc.render.filepath = str(out / f"{name}.png")
    bpy.ops.render.render(write_still=True)
print(json.dumps(res))
"""


def seam_render(tmp_path, water_hi, variants: dict, level: float, edge_x: float) -> dict:
    """Preview frames (one per [render] variant) of a water slab over [LO, water_hi] and, per
    variant, the 8-bit pixel differences between points just inside and just outside the
    front edge (y = 0) and the water's right edge (x = edge_x), at the water's level."""
    import imageio.v2 as imageio

    from whitecap.io import write_mesh
    from whitecap.io.mesh import SurfaceMesh

    run = tmp_path / "run"
    v, f = water_slab(LO, water_hi, 48, lambda x, y: level + 0.004 * np.sin(14 * x) * np.cos(9 * y))
    write_mesh(run / "mesh/fluid_00000.ply", SurfaceMesh(v, f))
    info = run_info()
    info.obstacles = []
    info.set_file(0, "mesh", "mesh/fluid_00000.ply")
    info.save(run)
    d = 0.02
    pts, pairs = [], []
    for x in np.linspace(0.15, edge_x - 0.1, 12):
        pairs.append((len(pts), len(pts) + 1))
        pts += [[x, d, level], [x, -d, level]]
    for y in np.linspace(0.08, 0.35, 8):
        pairs.append((len(pts), len(pts) + 1))
        pts += [[edge_x - d, y, level], [edge_x + d, y, level]]
    out = subprocess.run([sys.executable, "-c", SEAM + BPY_END, run, tmp_path, json.dumps(variants), json.dumps(pts)],
                         capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(SRC)})
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads([ln for ln in out.stdout.splitlines() if ln.startswith("{")][-1])
    diffs = {}
    for name in variants:
        img = imageio.imread(tmp_path / f"{name}.png")[..., :3].astype(float)
        hgt, wid = img.shape[:2]
        across = []
        for a, b in pairs:
            (ua, va), (ub, vb) = res[name]["uv"][a], res[name]["uv"][b]
            ya, xa, yb, xb = int((1 - va) * hgt), int(ua * wid), int((1 - vb) * hgt), int(ub * wid)
            assert 1 <= ya < hgt - 1 and 1 <= xa < wid - 1 and 1 <= yb < hgt - 1 and 1 <= xb < wid - 1
            across.append(np.abs(img[ya - 1:ya + 2, xa - 1:xa + 2].mean((0, 1))
                                 - img[yb - 1:yb + 2, xb - 1:xb + 2].mean((0, 1))).mean())
        diffs[name] = (np.array(across), res[name]["objects"])
    return diffs


SEAM_CAMERA = {"camera_start": [1.25, -0.55, 0.45], "camera_target": [0.55, 0.2, 0.08]}


def test_sea_shows_no_seam_at_the_domain_edge(tmp_path):
    """A preview frame of water that fills the domain, with the sea around it: along the
    domain's front and right edges, pixels just inside and just outside differ by less than
    THRESHOLD (8-bit levels). Without the sea (container none) the water's side face shows
    there as a wall, far above it. No container object is drawn with the sea."""
    pytest.importorskip("bpy")
    level = 0.1
    variants = {"sea": {"sea": True, "sea_level": level, "ground": False, **SEAM_CAMERA},
                "nosea": {"container": "none", "ground": False, **SEAM_CAMERA}}
    diffs = seam_render(tmp_path, HI, variants, level, HI[0])
    (with_sea, objects), (without, _) = diffs["sea"], diffs["nosea"]
    assert "container" not in objects and "sea" in objects
    print("across the edge, 8-bit levels: sea", with_sea.round(1), "no sea", without.round(1))
    assert np.median(with_sea) < THRESHOLD and with_sea.max() < 2 * THRESHOLD, with_sea
    assert np.median(without) > 2 * THRESHOLD, without


def test_sea_shows_no_seam_where_the_water_leaves_a_wall(tmp_path):
    """Water that stands 0.1 m off the right wall (as in front of a wave maker; scenes/coast.toml's
    dark band behind the surf): the sea reaches in to the water's edge, so across that edge (and
    the front edge) pixels differ by less than THRESHOLD as where the water fills the domain. A
    sea that meets the floor at a wall the water does not touch shows a dark trough there."""
    pytest.importorskip("bpy")
    level = 0.1
    variants = {"sea": {"sea": True, "sea_level": level, "ground": False, **SEAM_CAMERA}}
    edge_x = HI[0] - 0.1
    with_sea = seam_render(tmp_path, [edge_x, HI[1], HI[2]], variants, level, edge_x)["sea"][0]
    print("across the water's edge, 8-bit levels:", with_sea.round(1))
    assert np.median(with_sea) < THRESHOLD and with_sea.max() < 2 * THRESHOLD, with_sea


#: Median pixel difference across the domain's edge with the sea [8-bit levels], set by looking (see the test).
THRESHOLD = 12.0
