"""Headless GGUI viewer (lavapipe): what the images show, playback, colours, errors."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from whitecap import io
from whitecap.config import View
from whitecap.io.run import RunInfo
from whitecap.view import DIFFUSE_COLORS, project, require_vulkan

try:
    require_vulkan()
except Exception:  # pragma: no cover
    pytest.skip("no Vulkan driver (apt-get install mesa-vulkan-drivers libvulkan1)", allow_module_level=True)

SRC = Path(__file__).resolve().parents[1] / "src"
PANEL = (slice(0, int(0.32 * 720)), slice(0, int(0.47 * 1280)))  # the info panel, top left


def view(*args) -> subprocess.CompletedProcess:
    # One GGUI window per process: each render runs in its own process.
    return subprocess.run([sys.executable, "-m", "whitecap.cli", "view", *map(str, args)], capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(SRC), "WHITECAP_PROGRESS": "0"})


def image(path: Path) -> np.ndarray:
    import imageio.v2 as imageio

    a = imageio.imread(path)[..., :3].astype(np.float32) / 255
    a[PANEL] = 0.0  # ignore the text panel
    return a


def fluid_mask(a: np.ndarray) -> np.ndarray:
    return (a[..., 2] > a[..., 0] + 0.12) & (a[..., 2] > 0.35)


@pytest.fixture(scope="module")
def playback(tiny_run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("view")
    r = view(tiny_run, "--headless", "--out", out, "--mp4")
    assert r.returncode == 0, r.stderr[-2000:]
    return out


def test_playback_writes_one_png_per_frame(playback, tiny_run):
    n = len(RunInfo.load(tiny_run).files("fluid"))
    assert sorted(p.name for p in playback.glob("view_*.png")) == [f"view_{i:05d}.png" for i in range(n)]
    import imageio.v2 as imageio

    assert imageio.get_reader(str(playback / "view.mp4"), format="FFMPEG").count_frames() == n


def test_fluid_drawn_where_it_projects_and_nowhere_else(playback, tiny_run):
    info = RunInfo.load(tiny_run)
    f = io.read(tiny_run / info.files("fluid")[-1][1])
    a = image(playback / "view_00003.png")
    assert a.std() > 0.05  # not blank
    domain = (np.array(info.domain["lower"]), np.array(info.domain["upper"]))
    px = project(f.positions, View(), domain, (1280, 720))
    (x0, y0), (x1, y1) = px.min(0), px.max(0)
    pad = 12  # particle radius on screen
    inside = np.zeros(a.shape[:2], bool)
    inside[int(max(y0 - pad, 0)):int(y1 + pad), int(max(x0 - pad, 0)):int(x1 + pad)] = True
    m = fluid_mask(a)
    assert m[inside].mean() > 0.2, m[inside].mean()
    assert m[~inside].sum() < 0.01 * m.sum()


def test_diffuse_types_have_their_colours(tiny_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    info = RunInfo.load(run)
    # Three clusters beside the water, one per type.
    rng = np.random.default_rng(0)
    pts, kinds = [], []
    for t, x in enumerate((0.3, 0.42, 0.54)):
        pts.append(rng.normal([x, 0.1, 0.1], 0.012, (300, 3)))
        kinds.append(np.full(300, t, np.uint8))
    pts, kinds = np.concatenate(pts), np.concatenate(kinds)
    io.write(run / "diffuse/diffuse_00000.ply", io.ParticleFrame(pts, np.zeros_like(pts), arrays={
        "type": kinds, "lifetime": np.ones(len(pts), np.float32), "radius": np.full(len(pts), 0.005, np.float32)}))
    info.set_file(0, "diffuse", "diffuse/diffuse_00000.ply")
    info.save(run)
    r = view(run, "--headless", "--frames", "1", "--out", tmp_path / "img")
    assert r.returncode == 0, r.stderr[-2000:]
    a = image(tmp_path / "img" / "view_00000.png")
    domain = (np.array(info.domain["lower"]), np.array(info.domain["upper"]))
    means = []
    for t in range(3):
        c = project(pts[kinds == t].mean(0, keepdims=True), View(), domain, (1280, 720))[0].astype(int)
        patch = a[c[1] - 4:c[1] + 5, c[0] - 4:c[0] + 5].reshape(-1, 3).mean(0)
        means.append(patch)
    spray, foam, bubbles = means
    assert spray.min() > 0.8  # white
    assert foam.max() - foam.min() < 0.06 and foam.mean() < spray.mean() - 0.05  # grey, darker than spray
    assert bubbles[2] - bubbles[0] > 0.12  # pale blue
    assert (DIFFUSE_COLORS[2][2] - DIFFUSE_COLORS[2][0]) > 0.3


def test_missing_sequence_is_a_clear_error(tmp_path):
    r = view(tmp_path / "nothing", "--headless", "--out", tmp_path / "o")
    assert r.returncode != 0
    err = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "nothing" in err[0] and "no such run directory or sequence" in err[0]


def test_live_scene_headless(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(
        "[domain]\nupper = [0.6, 0.2, 0.4]\n[solver]\nparticle_radius = 0.015\n"
        "[[fluid]]\nlower = [0, 0, 0]\nupper = [0.2, 0.2, 0.3]\n[view]\nwindow = [320, 240]\n"
    )
    r = view(scene, "--headless", "--frames", "3", "--out", tmp_path / "img")
    assert r.returncode == 0, r.stderr[-2000:]
    import imageio.v2 as imageio

    a, b = (imageio.imread(tmp_path / "img" / f"view_{i:05d}.png")[..., :3].astype(float) for i in (0, 2))
    assert a.shape[:2] == (240, 320)
    assert np.abs(a - b).mean() > 0.5  # the simulation moved between the frames
