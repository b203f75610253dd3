"""Viewer checks that catch realistic one-line bugs the other tests let through
(scripts/mutation_audit.py): runs whose frames are not numbered 0..n in order, a turned
body's normals, and the colour map's continuity."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from whitecap.io import ParticleFrame, read, write
from whitecap.io.run import RunInfo, frame_name

INDICES = (5, 7, 9, 11)  # the tiny run's frames 0..3, renumbered
HANG_GUARD_S = 600.0  # event waits: only a guard against a hung viewer; each ends on its event first


def renumbered_run(tiny_run, tmp_path) -> Path:
    """The tiny run with its frames renumbered 5, 7, 9, 11 (files renamed to match), and per frame
    its own time, diffuse particles (as many as the frame's position in the list plus one, all of
    one type) and pose of a block obstacle (lifted 1 cm per frame index)."""
    import trimesh

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    meta = json.loads((run / "run.json").read_text())
    trimesh.creation.box(extents=(0.08, 0.08, 0.08)).export(run / "block.obj")
    meta["obstacles"] = [{"mesh": "block.obj", "translate": [0.45, 0.1, 0.06]}]
    meta["frames"] = meta["frames"][: len(INDICES)]
    for k, (f, idx) in enumerate(zip(meta["frames"], INDICES)):
        assert f["index"] == k
        for kind in [kd for kd in f["files"] if kd not in ("fluid",)]:
            (run / f["files"].pop(kind)).unlink(missing_ok=True)
            f["made_from"].pop(kind, None)
        (run / f["files"]["fluid"]).rename(run / frame_name("fluid", idx))
        f["files"]["fluid"] = frame_name("fluid", idx)
        f["index"], f["time"] = idx, idx / meta["frame_rate"]
        n = k + 1
        d = ParticleFrame(np.tile(np.float32([0.1 * k, 0.05, 0.3]), (n, 1)), np.zeros((n, 3), np.float32),
                          np.arange(n, dtype=np.uint32),
                          arrays={"type": np.full(n, k % 3, np.uint8), "lifetime": np.ones(n, np.float32),
                                  "radius": np.full(n, 0.004, np.float32)})
        write(run / frame_name("diffuse", idx), d)
        f["files"]["diffuse"] = frame_name("diffuse", idx)
        f["made_from"]["diffuse"] = meta["simulation"]
        f["bodies"] = [{"position": [0.0, 0.0, 0.01 * idx], "quaternion": [1.0, 0.0, 0.0, 0.0]}]
    (run / "run.json").write_text(json.dumps(meta))
    info = RunInfo.load(run)
    assert [i for i, _ in info.files("fluid")] == list(INDICES) == [i for i, _ in info.files("diffuse")]
    return run


def test_playback_of_frames_5_7_9_11_shows_each_frames_own_data(tiny_run, tmp_path):
    """Position k of the played list is frame INDICES[k]: its index, time, particles, diffuse
    particles and body pose are those run.json gives that frame index, not frame number k's."""
    from whitecap.view.sources import PlaybackSource

    run = renumbered_run(tiny_run, tmp_path)
    src = PlaybackSource(run)
    assert len(src) == len(INDICES)
    for k, idx in reversed(list(enumerate(INDICES))):  # out of order, past the cache's first entries
        fr = src.frame(k)
        assert fr.index == idx, (k, fr.index)
        assert fr.time == pytest.approx(idx / 30.0)
        np.testing.assert_array_equal(fr.positions, read(run / frame_name("fluid", idx)).positions)
        assert fr.diffuse_positions is not None and len(fr.diffuse_positions) == k + 1
        assert (fr.diffuse_type == k % 3).all()
        assert fr.bodies is not None and fr.bodies[0].position == pytest.approx([0.0, 0.0, 0.01 * idx])


def test_web_viewer_shows_the_surface_of_the_frame_played(tiny_run, tmp_path):
    """Without a browser: frames 5, 7, 9, 11 each have their own surface mesh (a box of another
    size); seeking to each played position shows that frame's surface, not the surface of the
    frame numbered like the position (frames 1..3 have none)."""
    pytest.importorskip("viser", reason="the browser viewer needs viser: pip install 'whitecap[web]'")
    import trimesh

    from whitecap.io import write_mesh
    from whitecap.io.mesh import SurfaceMesh
    from whitecap.view.web import WebViewer

    run = renumbered_run(tiny_run, tmp_path)
    (run / "mesh").mkdir()
    meta = json.loads((run / "run.json").read_text())
    boxes = {}
    for f in meta["frames"]:
        idx = f["index"]
        b = trimesh.creation.box(extents=(0.01 * idx, 0.05, 0.05))
        boxes[idx] = b
        write_mesh(run / "mesh" / f"surface_{idx:05d}.ply", SurfaceMesh(b.vertices, b.faces))
        f["files"]["mesh"] = f"mesh/surface_{idx:05d}.ply"
        f["made_from"]["mesh"] = meta["simulation"]
    (run / "run.json").write_text(json.dumps(meta))
    with WebViewer(run, port=0) as v:
        assert v.wait_drawn(0, HANG_GUARD_S)
        v._toggle("surface", True)
        for k in (2, 1, 3):
            v.seek(k)
            assert v.wait_drawn(k, HANG_GUARD_S), k
            # a frame's surface is set in the same pass that draws it, before drawn_frame is
            idx = INDICES[k]
            h = v.h_surface
            assert h is not None and h.visible, f"no surface shown for frame {idx} (position {k})"
            got = np.asarray(h.vertices)
            assert got.shape == boxes[idx].vertices.shape and np.allclose(got, boxes[idx].vertices, atol=1e-6), \
                f"frame {idx}'s surface is not the one shown at position {k}"


# ---------------------------------------------------------------- geometry and colours
def test_a_turned_bodys_normals_turn_with_it():
    """geometry.posed carries vertices and normals by a body pose: the normals it gives are the
    normals of the carried mesh (a box turned 30° about an oblique axis and moved)."""
    import trimesh

    from whitecap.io.record import Pose
    from whitecap.view.geometry import posed

    box = trimesh.creation.box(extents=(0.3, 0.2, 0.1))
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    a = math.radians(30)
    q = [math.cos(a / 2), *(math.sin(a / 2) * axis)]
    body = Pose(position=[0.4, -0.1, 0.25], quaternion=q)
    v, n = posed(np.asarray(box.vertices, np.float32), np.asarray(box.face_normals[0:1].repeat(len(box.vertices), 0),
                                                                    np.float32), body)
    moved = trimesh.Trimesh(v, box.faces, process=False)
    assert np.allclose(moved.face_normals[0], n[0], atol=1e-5)  # the first face's normal, carried
    assert np.allclose(moved.vertices.mean(0), body.position, atol=1e-5)
    # every vertex normal of the posed box agrees with the posed mesh's own
    _, vn = posed(np.asarray(box.vertices, np.float32), np.asarray(box.vertex_normals, np.float32), body)
    assert np.allclose(moved.vertex_normals, vn, atol=1e-5)


def test_the_colour_map_is_continuous_and_spans_its_stops():
    """The fluid's colour map runs from its first stop at the low end to its last at the high end,
    through each stop in turn, without jumps: values 1e-4 of the range apart get colours within 1e-3."""
    from whitecap.view.colors import COLORMAP_STOPS, colormap

    lo, hi = 2.0, 6.0
    s = np.linspace(lo, hi, 40001)
    c = colormap(s, lo, hi)
    assert np.allclose(c[0], COLORMAP_STOPS[0]) and np.allclose(c[-1], COLORMAP_STOPS[-1])
    for k, stop in enumerate(COLORMAP_STOPS):
        at = lo + (hi - lo) * k / (len(COLORMAP_STOPS) - 1)
        assert np.allclose(colormap(np.array([at]), lo, hi)[0], stop, atol=1e-6), k
    assert np.abs(np.diff(c, axis=0)).max() < 1e-3
    assert np.allclose(colormap(np.array([lo - 5.0, hi + 5.0]), lo, hi), COLORMAP_STOPS[[0, -1]])  # clamped


def test_the_speed_colour_range_reaches_the_speed_of_a_fall_through_the_box():
    """The speed colours run from 0 to at least the speed water reaches falling the box's height H
    (a drop released at the top hits the floor at √(2 g H)), so a resting first frame does not get
    a range of zero; a faster frame widens the range to its 99th percentile."""
    from whitecap.view.colors import GRAVITY, fitted_range, free_fall_speed
    from whitecap.view.sources import Bounds

    b = Bounds(np.array([0.0, 0.0, 0.1]), np.array([0.6, 0.2, 0.5]))
    z, u, dt = 0.5, 0.0, 1e-5  # a drop from the top, integrated to the floor
    while z > 0.1:
        u += GRAVITY * dt
        z -= u * dt
    assert free_fall_speed(b) == pytest.approx(u, rel=1e-3)
    assert fitted_range(np.zeros(50), "speed", free_fall_speed(b)) == pytest.approx((0.0, u), rel=1e-3)
    fast = np.linspace(0.0, 10.0, 1001)
    assert fitted_range(fast, "speed", free_fall_speed(b)) == pytest.approx((0.0, 9.9))
