"""Viewer tests, headless: GGUI draws offscreen through lavapipe.

Each render runs `whitecap view --headless` in a subprocess (GGUI keeps one
window per process), then the PNGs are checked against the camera projection.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from whitecap.config import View
from whitecap.errors import InputError
from whitecap.io import ParticleFrame, read, write
from whitecap.io.run import RunInfo, frame_name

W, H = 320, 240
SRC = Path(__file__).resolve().parents[1] / "src"


def _cli(*args, env_extra=None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", **(env_extra or {})}
    return subprocess.run([sys.executable, "-m", "whitecap.cli", "view", *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=120)


def _render(target, out, *extra) -> list[Path]:
    r = _cli(target, "--headless", "--out", out, "--size", W, H, "--no-legend", *extra)
    assert r.returncode == 0, r.stderr[-2000:]
    return sorted(Path(out).glob("view_*.png"))


def _img(path) -> np.ndarray:
    import imageio.v2 as imageio

    return imageio.imread(path)[..., :3].astype(int)


def _camera(run):
    from whitecap.view.app import initial_camera
    from whitecap.view.sources import PlaybackSource

    return initial_camera(View(), PlaybackSource(run).bounds)


def _saturated(img) -> np.ndarray:
    """Pixels of the colour map (saturated), not the grey background or box lines."""
    return (img.max(-1) - img.min(-1)) > 40


# ------------------------------------------------------------------ rendering
def test_dam_break_frame_lands_where_the_fluid_projects(tiny_run, tmp_path):
    from whitecap.view.draw import project

    pngs = _render(tiny_run, tmp_path, "--frames", 1)
    assert [p.name for p in pngs] == ["view_00000.png"]
    img = _img(pngs[0])
    assert img.shape == (H, W, 3)
    pts = read(tiny_run / frame_name("fluid", 0)).positions
    lo, hi = pts.min(0), pts.max(0)
    corners = np.array([[(hi if (k >> a) & 1 else lo)[a] for a in range(3)] for k in range(8)])
    px = project(corners, _camera(tiny_run), W, H)
    (c0, r0), (c1, r1) = np.floor(px.min(0)).astype(int), np.ceil(px.max(0)).astype(int)
    fluid = _saturated(img)
    inside = fluid[max(r0, 0):r1, max(c0, 0):c1]
    # The block is drawn: most of its projected box is covered by fluid colour.
    assert inside.mean() > 0.3
    # Nothing fluid-coloured outside the projected box (a margin of one particle's size in pixels).
    m = 12
    outside = fluid.copy()
    outside[max(r0 - m, 0):r1 + m, max(c0 - m, 0):c1 + m] = False
    assert outside.sum() == 0
    # The right half of the image (empty side of the dam break) holds no fluid.
    assert c1 < W // 2 + m and not fluid[:, W // 2 + m:].any()


def test_playback_writes_one_png_per_frame_and_mp4(tiny_run, tmp_path):
    n = len(RunInfo.load(tiny_run).files("fluid"))
    pngs = _render(tiny_run, tmp_path, "--mp4")
    assert [p.name for p in pngs] == [f"view_{i:05d}.png" for i in range(n)]
    # The dam breaks: the fluid spreads right between the first and the last frame.
    right = [np.nonzero(_saturated(_img(p)).any(0))[0].max() for p in (pngs[0], pngs[-1])]
    assert right[1] > right[0] + 3
    import imageio.v2 as imageio

    with imageio.get_reader(tmp_path / "view.mp4") as rd:
        assert sum(1 for _ in rd) == n


def test_diffuse_types_render_in_their_colours(tiny_run, tmp_path):
    from whitecap.view.draw import project

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    info = RunInfo.load(run)
    # One big particle of each type in the empty part of the box, away from the fluid.
    pos = np.array([[0.32, 0.1, 0.3], [0.42, 0.1, 0.3], [0.52, 0.1, 0.3]], np.float32)
    d = ParticleFrame(pos, np.zeros_like(pos), arrays={
        "type": np.array([0, 1, 2], np.uint8), "lifetime": np.ones(3, np.float32),
        "radius": np.full(3, 0.02, np.float32)})
    (run / "diffuse").mkdir()
    write(run / frame_name("diffuse", 0), d)
    info.set_file(0, "diffuse", frame_name("diffuse", 0))
    info.save(run)
    img = _img(_render(run, tmp_path / "png", "--frames", 1)[0])
    px = np.round(project(pos, _camera(run), W, H)).astype(int)
    spray, foam, bubble = (np.median(img[r - 1:r + 2, c - 1:c + 2].reshape(-1, 3), axis=0) for c, r in px)
    bg = img[2, W // 2]
    for c in (spray, foam, bubble):
        assert np.abs(c - bg).sum() > 150  # drawn, clearly not background
    assert np.ptp(spray) < 20 and np.ptp(foam) < 20  # white and grey are neutral
    assert spray.mean() > foam.mean() + 15  # spray white is brighter than foam grey
    assert bubble[2] > bubble[0] + 25  # bubbles are blue


# ------------------------------------------------------------------ errors
def test_missing_sequence_is_one_line_error(tmp_path):
    r = _cli(tmp_path / "nope", "--headless", "--out", tmp_path / "o")
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert lines[-1].startswith("error: ") and "nope" in lines[-1]
    assert "Traceback" not in r.stderr


def test_no_vulkan_names_the_packages(tiny_run, tmp_path):
    r = _cli(tiny_run, "--headless", "--out", tmp_path, env_extra={"WHITECAP_FAKE_NO_VULKAN": "1"})
    assert r.returncode != 0
    assert "mesa-vulkan-drivers" in r.stderr and "libvulkan1" in r.stderr
    assert not list(tmp_path.glob("*.png"))


# ------------------------------------------------------------------ pieces (no window)
def test_numbered_sequence_in_numeric_order(tmp_path):
    from whitecap.view.sources import find_sequence

    for i in (10, 2, 1):
        write(tmp_path / f"part_{i}.npz", ParticleFrame(np.zeros((2, 3)) + i))
    (tmp_path / "notes.txt").write_text("x")
    assert [p.name for p in find_sequence(tmp_path)] == ["part_1.npz", "part_2.npz", "part_10.npz"]
    assert [p.name for p in find_sequence(tmp_path / "part_2.npz")][-1] == "part_10.npz"
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no numbered particle files"):
        find_sequence(tmp_path / "empty")


def test_obstacle_transform_rotates_x_then_y_then_z():
    from whitecap.view.geometry import obstacle_transform

    m = obstacle_transform([1.0, 0.0, 0.0], [90.0, 90.0, 0.0], 2.0)
    # (0,1,0) -> scale 2 -> Rx90 -> (0,0,2) -> Ry90 -> (2,0,0) -> +translate
    np.testing.assert_allclose((m @ [0, 1, 0, 1])[:3], [3.0, 0.0, 0.0], atol=1e-9)


def test_orbit_camera_keeps_distance_and_target():
    from whitecap.view.state import OrbitCamera

    cam = OrbitCamera.looking([2.0, -1.0, 1.0], [0.5, 0.5, 0.2], 45.0)
    np.testing.assert_allclose(cam.eye, [2.0, -1.0, 1.0], atol=1e-9)
    d = cam.distance
    cam.orbit(0.7, 0.3)
    assert np.linalg.norm(cam.eye - cam.target) == pytest.approx(d)
    cam.pan(0.1, 0.0)
    cam.zoom(0.5)
    assert cam.distance == pytest.approx(d / 2)
