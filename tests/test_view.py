"""Viewer tests, headless: GGUI draws offscreen through lavapipe.

Each render runs `whitecap view --headless` in a subprocess (GGUI keeps one
window per process), then the PNGs are checked against the camera projection.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
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
                          capture_output=True, text=True, env=env, timeout=120,
                          cwd=tempfile.gettempdir())  # GGUI writes imgui.ini into the working directory


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
    (run / "diffuse").mkdir(exist_ok=True)
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


def test_window_without_display_says_use_headless(tiny_run):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    r = subprocess.run([sys.executable, "-m", "whitecap.cli", "view", str(tiny_run)], capture_output=True, text=True,
                       env={**env, "PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}, timeout=60)
    assert r.returncode != 0 and "--headless" in r.stderr.strip().splitlines()[-1]


def test_no_vulkan_names_the_packages(tiny_run, tmp_path):
    r = _cli(tiny_run, "--headless", "--out", tmp_path, env_extra={"WHITECAP_FAKE_NO_VULKAN": "1"})
    assert r.returncode != 0
    assert "mesa-vulkan-drivers" in r.stderr and "libvulkan1" in r.stderr
    assert not list(tmp_path.glob("*.png"))


# ------------------------------------------------------------------ pieces (no window)
def test_numbered_sequence_plays_in_frame_order(tmp_path):
    from whitecap.view.sources import PlaybackSource

    for i in (10, 2, 1):
        write(tmp_path / f"part_{i}.npz", ParticleFrame(np.zeros((2, 3)) + i))
    src = PlaybackSource(tmp_path)
    assert src.indices == [1, 2, 10] and len(src) == 3
    assert src.frame(2).positions[0, 0] == 10.0
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError):
        PlaybackSource(tmp_path / "empty")


def test_dualsphysics_sequence_plays_back(tmp_path):
    from whitecap.view.app import initial_camera
    from whitecap.view.draw import project
    from whitecap.view.sources import PlaybackSource

    data = Path(__file__).parent / "data" / "dualsphysics"
    pngs = _render(data, tmp_path)
    assert len(pngs) == len(list(data.glob("PartFluid_*.vtk")))
    src = PlaybackSource(data)
    pts = src.frame(0).positions
    lo, hi = pts.min(0), pts.max(0)
    corners = np.array([[(hi if (k >> a) & 1 else lo)[a] for a in range(3)] for k in range(8)])
    px = project(corners, initial_camera(View(), src.bounds), W, H)
    (c0, r0), (c1, r1) = np.floor(px.min(0)).astype(int), np.ceil(px.max(0)).astype(int)
    fluid = _saturated(_img(pngs[0]))
    assert fluid[max(r0, 0):r1, max(c0, 0):c1].mean() > 0.2


def test_obstacle_transform_rotates_x_then_y_then_z():
    from whitecap.config import Obstacle
    from whitecap.geometry import obstacle_transform
    from whitecap.io.record import Obstacle as Record

    m = obstacle_transform(Record.model_validate({"translate": [1.0, 0.0, 0.0], "rotate": [90.0, 90.0, 0.0],
                                                  "scale": 2.0}))
    # The scene model and its run.json dict place an obstacle alike; missing keys are the defaults.
    o = Obstacle(mesh="m.obj", translate=[1.0, 0.0, 0.0], rotate=[90.0, 90.0, 0.0], scale=2.0)
    np.testing.assert_array_equal(obstacle_transform(o), m)
    np.testing.assert_array_equal(obstacle_transform(Record.model_validate({"mesh": "m.obj"})), np.eye(4))
    # (0,1,0) -> scale 2 -> Rx90 -> (0,0,2) -> Ry90 -> (2,0,0) -> +translate
    np.testing.assert_allclose((m @ [0, 1, 0, 1])[:3], [3.0, 0.0, 0.0], atol=1e-9)


def test_orbit_camera_keeps_distance_and_target():
    from whitecap.view.state import OrbitCamera

    cam = OrbitCamera.looking([2.0, -1.0, 1.0], [0.5, 0.5, 0.2], 45.0)
    np.testing.assert_allclose(cam.eye, [2.0, -1.0, 1.0], atol=1e-9)
    d = cam.distance
    cam.orbit(0.7, 0.3)
    assert np.linalg.norm(cam.eye - cam.target) == pytest.approx(d)
    # Pan: eye and target shift together in the view plane by the given fraction of the distance,
    # so the old target moves on screen with the drag (right for dx > 0, up for dy > 0) by
    # dx / (tan(fov/2) · aspect) of the half width, and by dy / tan(fov/2) of the half height.
    from whitecap.view.draw import project

    half = np.tan(np.radians(cam.fov) / 2)
    for dx, dy in ((0.1, 0.0), (0.0, 0.1)):
        eye, target = cam.eye.copy(), cam.target.copy()
        f, _, _ = cam.basis()
        cam.pan(dx, dy)
        np.testing.assert_allclose(cam.eye - eye, cam.target - target, atol=1e-12)
        assert np.linalg.norm(cam.target - target) == pytest.approx(np.hypot(dx, dy) * d)
        assert abs(np.dot(cam.target - target, f)) < 1e-12
        np.testing.assert_allclose(cam.basis()[0], f, atol=1e-12)  # same view direction
        col, row = project(target[None], cam, W, H)[0]
        assert col == pytest.approx(W / 2 * (1 + dx / (half * W / H)), abs=0.5)
        assert row == pytest.approx(H / 2 * (1 - dy / half), abs=0.5)
    cam.zoom(0.5)
    assert cam.distance == pytest.approx(d / 2)
    np.testing.assert_allclose(np.linalg.norm(cam.eye - cam.target), d / 2)


def test_obstacle_mesh_is_drawn_where_it_projects(tiny_run, tmp_path):
    import json

    import trimesh

    from whitecap.view.draw import project

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(run / "block.obj")
    meta = json.loads((run / "run.json").read_text())
    # A red cube, 45° about z, in the empty right part of the box; a missing mesh is skipped.
    meta["obstacles"] = [
        {"mesh": "block.obj", "translate": [0.45, 0.1, 0.1], "rotate": [0, 0, 45], "scale": 1.0,
         "color": [0.9, 0.1, 0.1]},
        {"mesh": "missing.obj"},
    ]
    (run / "run.json").write_text(json.dumps(meta))
    img = _img(_render(run, tmp_path / "png", "--frames", 1)[0])
    c, r = np.round(project(np.array([[0.45, 0.1, 0.1]]), _camera(run), W, H)[0]).astype(int)
    red = (img[..., 0] > img[..., 1] + 40) & (img[..., 0] > img[..., 2] + 40)
    assert red[r - 2:r + 3, c - 2:c + 3].all()
    assert not red[:, : W // 3].any()  # nothing red over the fluid column on the left


class _FakeWindow:
    """Stands in for a GGUI window: scripted key presses, held keys and cursor."""

    def __init__(self, presses=(), held=(), cursor=(0.3, 0.5)):
        self.presses, self.held, self.cursor = list(presses), set(held), cursor

    def get_events(self, tag=None):
        ev = [type("E", (), {"key": k}) for k in self.presses]
        self.presses = []
        return ev

    def is_pressed(self, *keys):
        return any(k in self.held for k in keys)

    def get_cursor_pos(self):
        return self.cursor

    def get_window_shape(self):
        return (W, H)


def test_keys_and_mouse_change_the_state():
    import taichi as ti

    from whitecap.view.app import Input
    from whitecap.view.state import OrbitCamera, ViewerState

    st = ViewerState(camera=OrbitCamera.looking([2.0, -1.0, 1.0], [0.5, 0.5, 0.2], 45.0))
    win = _FakeWindow(presses=[ti.ui.SPACE, "1", "3", "v", "h", "p", "c"])
    inp = Input(win, move_speed=1.0, extent=1.0)
    inp.poll(st)
    assert st.paused and not st.visible.fluid and st.visible.diffuse and not st.visible.obstacles
    assert st.recording and st.show_help and st.screenshot and st.color_mode == "density"
    win.presses = ["n", "r"]
    inp.poll(st)
    assert st.step_once and st.reset
    # Left drag orbits around the target: the eye moves, the distance stays.
    eye0, d0, tgt0 = st.camera.eye.copy(), st.camera.distance, st.camera.target.copy()
    win.held, win.cursor = {ti.ui.LMB}, (0.4, 0.5)
    inp.poll(st)
    assert np.linalg.norm(st.camera.eye - eye0) > 1e-3 and st.camera.distance == pytest.approx(d0)
    np.testing.assert_allclose(st.camera.target, tgt0)
    # W moves the camera forward, towards the target.
    win.held = {"w"}
    eye1 = st.camera.eye.copy()
    inp.last_t -= 0.05
    inp.poll(st)
    f = tgt0 - eye1
    assert np.dot(st.camera.eye - eye1, f) > 0


def test_live_scene_simulates_while_rendering(tmp_path):
    from tests.conftest import tiny_scene_dict
    from whitecap.config import scene_from_dict

    scene = tmp_path / "tiny.toml"
    scene.write_text(scene_from_dict(tiny_scene_dict()).to_toml())
    pngs = _render(scene, tmp_path / "png", "--frames", 4)
    assert len(pngs) == 4
    # Frame 0 is the resting column; by frame 3 the front has run to the right.
    right = [np.nonzero(_saturated(_img(p)).any(0))[0].max() for p in (pngs[0], pngs[-1])]
    assert right[1] > right[0] + 3


class _FakeGui:
    """Records panel widgets; sliders return a scripted new value."""

    def __init__(self, new_values):
        self.new_values, self.texts = new_values, []

    def sub_window(self, *a):
        import contextlib

        return contextlib.nullcontext(self)

    def text(self, t, color=None):
        self.texts.append(t)

    def slider_int(self, label, v, lo, hi):
        return self.new_values.get(label, v)

    slider_float = slider_int

    def checkbox(self, label, v):
        return self.new_values.get(label, v)

    def button(self, label):
        return self.new_values.get(label, False)


def test_panel_sliders_change_the_live_solver_parameters():
    from tests.conftest import tiny_scene_dict
    from whitecap.config import scene_from_dict
    from whitecap.view.app import draw_panel
    from whitecap.view.state import OrbitCamera, ViewerState

    scene = scene_from_dict(tiny_scene_dict())
    live = type("Live", (), {"live": True, "scene": scene, "__len__": lambda self: 1})()
    gui = _FakeGui({"iterations": 9, "XSPH c": 0.2, "vorticity eps": 0.0, "colour by density": True})
    win = _FakeWindow()
    win.get_gui = lambda: gui
    st = ViewerState(camera=OrbitCamera.looking([2, -1, 1], [0, 0, 0], 45.0), counts={"fluid": 5, "spray": 2})
    draw_panel(win, st, live, scene)
    assert (scene.solver.iterations, scene.solver.xsph_c, scene.solver.vorticity_epsilon) == (9, 0.2, 0.0)
    assert st.color_mode == "density" and "spray: 2" in gui.texts
    # Playback controls: the frame slider moves the frame, loop can be turned off.
    play = type("Play", (), {"live": False, "__len__": lambda self: 4,
                             "frame": lambda self, k: type("F", (), {"index": k})()})()
    gui.new_values = {"frame": 3, "loop": False}
    draw_panel(win, st, play, None)
    assert st.frame == 3 and not st.loop


LOOP_SCRIPT = """
import sys
from whitecap.view.app import make_window, run_interactive
win = make_window((320, 240), headless=True)
# Offscreen windows have no input or show(): stand-ins for an idle user.
win.show = lambda: win.save_image(sys.argv[2] + "/shown.png")
win.get_events = lambda tag=None: []
win.is_pressed = lambda *keys: False
win.get_cursor_pos = lambda: (0.5, 0.5)
st = run_interactive(sys.argv[1], out=sys.argv[2], max_frames=3, window=win, recording=True)
print(st.frame, st.record_index, st.counts["fluid"], st.steps_per_s > 0)
"""


def test_interactive_loop_simulates_and_records(tmp_path):
    from tests.conftest import tiny_scene_dict
    from whitecap.config import scene_from_dict

    scene = tmp_path / "tiny.toml"
    scene.write_text(scene_from_dict(tiny_scene_dict()).to_toml())
    env = {**os.environ, "PYTHONPATH": f"{SRC}{os.pathsep}{Path(__file__).parents[1]}"}
    r = subprocess.run([sys.executable, "-c", LOOP_SCRIPT, str(scene), str(tmp_path)], capture_output=True,
                       text=True, env=env, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    frame, recorded, nfluid, stepping = r.stdout.split()[-4:]
    assert (int(frame), int(recorded), stepping) == (3, 3, "True") and int(nfluid) > 1000
    assert len(list(tmp_path.glob("record_*.png"))) == 3


def test_playback_steps_loops_and_pauses():
    from whitecap.view.app import _advance
    from whitecap.view.state import OrbitCamera, ViewerState

    src = type("Play", (), {"live": False, "info": type("I", (), {"frame_rate": 1e9})(), "__len__": lambda self: 3})()
    st = ViewerState(camera=OrbitCamera.looking([2, -1, 1], [0, 0, 0], 45.0))
    seen = []
    for _ in range(4):
        _advance(st, src)
        seen.append(st.frame)
    assert seen == [1, 2, 0, 1]  # loops
    st.loop, st.frame = False, 2
    _advance(st, src)
    assert st.frame == 2  # holds the last frame
    st.paused, st.frame = True, 0
    _advance(st, src)
    assert st.frame == 0
    st.step_once = True
    _advance(st, src)
    assert st.frame == 1 and st.paused and not st.step_once
    st.reset = True
    _advance(st, src)
    assert st.frame == 0
    # At a real frame rate, playback waits for the frame's time to pass, whatever
    # the clock's origin: a clock that reads 5 s (a machine just booted) or 1e6 s.
    src.info.frame_rate = 1e-3  # one frame per 1000 s
    for origin in (5.0, 1.0e6):
        st.paused, st.last_advance, st.frame = False, None, 0
        _advance(st, src, now=origin)
        assert st.frame == 1  # the first advance is never held back
        _advance(st, src, now=origin + 1.0)
        assert st.frame == 1  # held: the frame's 1000 s have not passed
        _advance(st, src, now=origin + 1000.5)
        assert st.frame == 2


def test_live_buffers_filled_on_the_device_match_the_host_colour_map():
    """A live solver's particles are coloured by a kernel on the device; it must give the
    positions and colours of the numpy path used for files (speed and density modes)."""
    import taichi as ti

    from whitecap.sim import runtime
    from whitecap.view.colors import colormap
    from whitecap.view.draw import _Buffer
    from whitecap.view.kernels import fill_fluid_buffer

    runtime.init(runtime.current() or "cpu")
    rng = np.random.default_rng(1)
    n = 1000
    x = rng.random((n, 3)).astype(np.float32)
    v = rng.normal(size=(n, 3)).astype(np.float32)
    rho = (1000.0 + 40.0 * rng.normal(size=n)).astype(np.float32)
    xs, vs, rs = ti.Vector.ndarray(3, ti.f32, n), ti.Vector.ndarray(3, ti.f32, n), ti.ndarray(ti.f32, n)
    xs.from_numpy(x)
    vs.from_numpy(v)
    rs.from_numpy(rho)
    buf = _Buffer()
    buf.reserve(n)
    for by_density, (lo, hi), s in ((0, (0.0, 2.5), np.linalg.norm(v, axis=1)), (1, (950.0, 1050.0), rho)):
        fill_fluid_buffer(n, xs, vs, rs, by_density, lo, hi, buf.pos, buf.col)
        np.testing.assert_allclose(buf.pos.to_numpy()[:n], x)
        np.testing.assert_allclose(buf.col.to_numpy()[:n], colormap(s, lo, hi), atol=1e-5)
        assert len(np.unique(buf.col.to_numpy()[:n].round(3), axis=0)) > 100  # a spread of colours, not one


def test_saved_frames_colour_each_particle_by_its_speed(tiny_run, tmp_path):
    """Three blocks at rest, at half and at the full default speed range sqrt(2|g|H) are drawn in
    the colour map's colours at 0, 1/2 and 1 (compared by chromaticity: lighting scales brightness)."""
    from whitecap.view.colors import GRAVITY, colormap
    from whitecap.view.draw import project

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    info = RunInfo.load(run)
    top = info.domain["upper"][2] - info.domain["lower"][2]
    v_max = np.sqrt(2 * GRAVITY * top)  # the viewer's default speed range is [0, v_max]
    ax = np.arange(5) * 0.02
    block = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3) - 0.04
    centres = np.array([[0.1, 0.1, 0.2], [0.3, 0.1, 0.2], [0.5, 0.1, 0.2]])
    fractions = (0.0, 0.5, 1.0)
    pos = np.concatenate([block + c for c in centres])
    vel = np.concatenate([np.tile([f * v_max, 0.0, 0.0], (len(block), 1)) for f in fractions])
    write(run / frame_name("fluid", 0), ParticleFrame(pos, vel, density=np.full(len(pos), 1000.0)))
    img = _img(_render(run, tmp_path / "png", "--frames", 1)[0]).astype(float)
    ts = np.linspace(0, 1, 101)
    cmap = colormap(ts, 0.0, 1.0)
    cmap_chroma = cmap / cmap.sum(1, keepdims=True)
    for (c, r), f in zip(np.round(project(centres, _camera(run), W, H)).astype(int), fractions):
        rgb = np.median(img[r - 2:r + 3, c - 2:c + 3].reshape(-1, 3), axis=0)
        chroma = rgb / rgb.sum()
        t = ts[np.argmin(np.linalg.norm(cmap_chroma - chroma, axis=1))]
        assert abs(t - f) < 0.15, (f, t, rgb)


def test_window_gets_the_size_and_colour_asked_for(tiny_run, monkeypatch):
    from whitecap.cli import main
    from whitecap.view import app

    seen = {}

    class Stop(Exception):
        pass

    def fake_window(res, headless, fps_limit=60):
        seen["size"], seen["headless"] = tuple(res), headless
        return object()

    def fake_renderer(window, source, cfg):
        seen["color"] = cfg.color_mode
        raise Stop

    monkeypatch.setattr(app, "make_window", fake_window)
    monkeypatch.setattr(app, "_renderer", fake_renderer)
    with pytest.raises(Stop):
        main(["view", str(tiny_run), "--size", "321", "243", "--color", "density"])
    assert seen == {"size": (321, 243), "headless": False, "color": "density"}


def test_live_view_shows_the_scenes_obstacles(tmp_path):
    # The live source lists the scene's obstacles as run.json's records, which the mesh loader reads.
    import types

    import trimesh

    from tests.conftest import tiny_scene_dict
    from whitecap.config import scene_from_dict
    from whitecap.view.geometry import load_obstacle_meshes
    from whitecap.view.sources import LiveSource

    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(tmp_path / "block.obj")
    scene = scene_from_dict(tiny_scene_dict(obstacle=[{"mesh": "block.obj", "translate": [0.45, 0.1, 0.1],
                                                       "color": [0.9, 0.1, 0.1]}]), base_dir=tmp_path)
    live = types.SimpleNamespace(scene=scene)  # the listing needs no solver
    ((v, f, _, color, k),) = load_obstacle_meshes(LiveSource.obstacles(live), LiveSource.obstacle_base(live))
    assert k == 0 and color == (0.9, 0.1, 0.1) and len(f) == 12
    assert np.allclose(v.mean(0), [0.45, 0.1, 0.1], atol=1e-6)
