"""The viewer's loops: interactive (live or playback) and headless.

Input handling lives here (keys and mouse change the :class:`ViewerState`);
:mod:`whitecap.view.draw` turns the state into pixels.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from ..config import DEFAULT_ARCH, DEFAULT_UP, Scene, View, load_scene
from ..errors import InputError, WhitecapError
from ..io.movie import encode_mp4
from .geometry import load_obstacle_meshes
from .sources import LiveSource, PlaybackSource
from .state import OrbitCamera, ViewerState
from .vulkan import INSTALL_HINT, require_vulkan

PANEL_PX = 330  # side panel width [px]; it sits on the right edge, full height


def panel_rect(window) -> tuple[float, float, float, float]:
    """Side panel x, y, width, height in window fractions."""
    w, _ = window.get_window_shape()
    f = min(PANEL_PX / w, 0.5)
    return (1.0 - f, 0.0, f, 1.0)
ORBIT_RATE = 4.0  # radians per window width of mouse drag
ZOOM_RATE = 3.0  # e-folds of distance per window height of middle drag
FOAM_SLIDERS = ("k_ta", "k_wc", "k_vo", "lifetime_multiplier")  # foam multipliers on the live panel
KEY_ZOOM = 1.03  # distance factor per frame with z / x held
VIEW_MP4_QUALITY = 7  # imageio 0-10: a preview, smaller than render/movie.mp4 (8)


# ----------------------------------------------------------------------------- setup
def open_source(target: str | Path, arch: str = DEFAULT_ARCH, up: str = DEFAULT_UP):
    """A LiveSource for a scene TOML, else a PlaybackSource for a run or sequence."""
    p = Path(target)
    if p.suffix.lower() == ".toml":
        if not p.is_file():
            raise InputError(f"{p}: scene file not found")
        return LiveSource(load_scene(p), arch), load_scene(p).view
    src = PlaybackSource(p, up=up)
    view_cfg = View()
    if src.info is not None and (p / "scene.toml").is_file():
        try:
            view_cfg = load_scene(p / "scene.toml").view
        except WhitecapError:
            pass
    return src, view_cfg


def initial_camera(cfg: View, bounds) -> OrbitCamera:
    lo, hi = np.asarray(bounds.lower, float), np.asarray(bounds.upper, float)
    center = 0.5 * (lo + hi)
    target = np.asarray(cfg.lookat, float) if cfg.lookat is not None else center
    if cfg.camera_position is not None:
        eye = np.asarray(cfg.camera_position, float)
    else:
        # Frame the box: eye in front (-y), a little to the side and above, far enough for the fov.
        diag = float(np.linalg.norm(hi - lo))
        dist = 0.5 * diag / np.tan(np.radians(cfg.fov) / 2) * 1.15
        direction = np.array([0.35, -1.0, 0.55])
        eye = target + dist * direction / np.linalg.norm(direction)
    return OrbitCamera.looking(eye, target, cfg.fov)


def make_window(res: tuple[int, int], headless: bool, fps_limit: int = 60):
    """A GGUI window; a clear one-line error when Vulkan is missing."""
    require_vulkan()
    has_display = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    if not headless and sys.platform.startswith("linux") and not has_display:
        # GLFW would print "cannot initialize GLFW" and exit the process.
        raise WhitecapError("view: no display for a window (DISPLAY is unset); use --headless --out DIR for PNGs")
    import taichi as ti

    from ..sim import runtime

    runtime.init(runtime.current() or "cpu")
    try:
        return ti.ui.Window("whitecap view", tuple(int(v) for v in res), show_window=not headless, fps_limit=fps_limit)
    except Exception as exc:  # taichi raises RuntimeError with a long Vulkan trace
        first = str(exc).splitlines()[0] if str(exc) else exc
        raise WhitecapError(f"{INSTALL_HINT} (window creation failed: {first})") from None


# ----------------------------------------------------------------------------- input
class Input:
    """Reads keys and mouse into the state. Kept apart from drawing."""

    def __init__(self, window, move_speed: float, extent: float):
        self.window = window
        self.last_cursor: tuple[float, float] | None = None
        self.move_speed = move_speed * extent
        self.last_t = time.perf_counter()

    def poll(self, state: ViewerState) -> None:
        import taichi as ti

        w = self.window
        for e in w.get_events(ti.ui.PRESS):
            k = e.key
            if k == ti.ui.ESCAPE:
                state.quit = True
            elif k == ti.ui.SPACE:
                state.paused = not state.paused
            elif k == "n":
                state.step_once, state.paused = True, True
            elif k == "r":
                state.reset = True
            elif k == "p":
                state.screenshot = True
            elif k == "v":
                state.recording = not state.recording
            elif k in ("1", "2", "3"):
                attr = {"1": "fluid", "2": "diffuse", "3": "obstacles"}[k]
                setattr(state.visible, attr, not getattr(state.visible, attr))
            elif k == "h":
                state.show_help = not state.show_help
            elif k == "c":
                state.color_mode = "density" if state.color_mode == "speed" else "speed"
                state.color_range = None
        now = time.perf_counter()
        dt, self.last_t = min(now - self.last_t, 0.1), now
        cam = state.camera
        step = self.move_speed * dt
        fwd = (w.is_pressed("w") - w.is_pressed("s")) * step
        right = (w.is_pressed("d") - w.is_pressed("a")) * step
        up = (w.is_pressed("e") - w.is_pressed("q")) * step
        if fwd or right or up:
            cam.move(fwd, right, up)
        if w.is_pressed("z"):
            cam.zoom(1 / KEY_ZOOM)
        if w.is_pressed("x"):
            cam.zoom(KEY_ZOOM)
        x, y = w.get_cursor_pos()
        if self.last_cursor is not None and x < panel_rect(w)[0]:
            dx, dy = x - self.last_cursor[0], y - self.last_cursor[1]
            if w.is_pressed(ti.ui.LMB):
                cam.orbit(-dx * ORBIT_RATE, -dy * ORBIT_RATE)
            elif w.is_pressed(ti.ui.RMB):
                cam.pan(dx, dy)
            elif w.is_pressed(ti.ui.MMB):
                cam.zoom(float(np.exp(dy * ZOOM_RATE)))
        self.last_cursor = (x, y)


# ----------------------------------------------------------------------------- panel
def draw_panel(window, state: ViewerState, source, scene: Scene | None) -> None:
    """The side panel: statistics, live parameter sliders, playback controls."""
    with window.get_gui().sub_window("whitecap", *panel_rect(window)) as g:
        g.text(f"frame {source.frame(state.frame).index if not source.live else state.frame}"
               f"   t = {state.sim_time:.3f} s")
        g.text(f"{state.fps:5.1f} fps" + (f"   {state.steps_per_s:6.1f} steps/s" if source.live else ""))
        for name, c in state.counts.items():
            g.text(f"{name}: {c:,}")
        g.text("paused" if state.paused else "playing")
        if state.recording:
            g.text(f"recording ({state.record_index} frames)", color=(1.0, 0.3, 0.3))
        if source.live and scene is not None:
            s = scene.solver
            s.iterations = g.slider_int("iterations", s.iterations, 1, 20)
            s.xsph_c = g.slider_float("XSPH c", s.xsph_c, 0.0, 0.5)
            s.vorticity_epsilon = g.slider_float("vorticity eps", s.vorticity_epsilon, 0.0, 0.5)
            fp = getattr(source, "foam_params", None)
            if fp is not None:
                for name in FOAM_SLIDERS:
                    v = float(getattr(fp, name))
                    new = g.slider_float(name, v, 0.0, max(4.0 * v, 1.0))
                    if new != v:
                        source.set_foam_params(**{name: new})
                        setattr(scene.foam, name, new)
        else:
            if g.button("play / pause"):
                state.paused = not state.paused
            if g.button("step"):
                state.step_once, state.paused = True, True
            state.loop = g.checkbox("loop", state.loop)
            state.frame = g.slider_int("frame", state.frame, 0, max(len(source) - 1, 0))
        mode = g.checkbox("colour by density", state.color_mode == "density")
        if (mode and state.color_mode != "density") or (not mode and state.color_mode != "speed"):
            state.color_mode, state.color_range = ("density" if mode else "speed"), None
        g.text("h: help")


# ----------------------------------------------------------------------------- loops
def _advance(state: ViewerState, source, now: float | None = None) -> None:
    """Move to the next frame unless paused (one frame when stepping).

    Playback is paced against the previous advance only: ``now`` is any
    monotonic clock reading (default ``time.perf_counter()``, whose origin is
    arbitrary, e.g. the boot), and the first advance is never held back.
    """
    if state.reset:
        state.reset = False
        if source.live:
            source.reset()
        state.frame = 0
        return
    if state.paused and not state.step_once:
        return
    if state.step_once:
        state.step_once = False
        state.last_advance = None  # a single step is never held back by the pacing
    if source.live:
        t0 = time.perf_counter()
        nsub = source.advance()
        state.steps_per_s = nsub / max(time.perf_counter() - t0, 1e-9)
        state.frame = source.index
    else:
        # Play at the run's frame rate, not the window's.
        now = time.perf_counter() if now is None else now
        if state.last_advance is not None and now - state.last_advance < 1.0 / _fps(source):
            return
        state.last_advance = now
        nxt = state.frame + 1
        if nxt >= len(source):
            nxt = 0 if state.loop else len(source) - 1
        state.frame = nxt


def _current(source, state: ViewerState):
    if source.live:
        return source.current(with_density=state.color_mode == "density")
    return source.frame(state.frame)


def _renderer(window, source, cfg: View):
    from .draw import Renderer

    obstacles = load_obstacle_meshes(source.obstacles(), source.obstacle_base())
    return Renderer(window, source.radius, source.bounds, obstacles, cfg.point_scale, cfg.background)


def _new_state(cfg: View, source) -> ViewerState:
    st = ViewerState(camera=initial_camera(cfg, source.bounds), color_mode=cfg.color_mode)
    if cfg.color_range is not None:
        st.color_range = (float(cfg.color_range[0]), float(cfg.color_range[1]))
    return st


def run_headless(
    target, out: str | Path, frames: int | None = None, mp4: bool = False, arch: str = DEFAULT_ARCH,
    size: tuple[int, int] | None = None, color_mode: str | None = None, up: str = DEFAULT_UP,
    panel: bool = False, legend: bool = True, show_progress: bool = True,
) -> list[Path]:
    """Render frames offscreen to OUT/view_NNNNN.png (and OUT/view.mp4). Returns the PNG paths.

    Live scenes are simulated for ``frames`` frames after frame 0 is drawn;
    playback draws ``frames`` frames of the sequence (all when None).
    """
    from ..io.atomic import atomic_path
    from ..progress import progress

    if frames is not None and int(frames) < 1:
        raise InputError(f"view --frames: expected at least 1, got {frames}")
    require_vulkan()
    source, cfg = open_source(target, arch, up)
    if color_mode:
        cfg = cfg.model_copy(update={"color_mode": color_mode})
    n = (len(source) if frames is None else min(int(frames), len(source))) if not source.live else (frames or 1)
    out = Path(out)
    own = source.path if not source.live and getattr(source, "info", None) is not None else None
    manifest = _claim_view_folder(out, [f"view_{k:05d}.png" for k in range(n)] + (["view.mp4"] if mp4 else []), own)
    window = make_window(tuple(size or cfg.window_size), headless=True)
    rend = _renderer(window, source, cfg)
    state = _new_state(cfg, source)
    paths = []
    scene = source.scene if source.live else None
    prog = progress(disable=None if show_progress else True)
    prog.start()
    task = prog.add_task("view", total=n)
    for k in range(n):
        if k > 0:
            if source.live:
                _advance(state, source)
            else:
                state.frame = k
        fr = _current(source, state)
        state.sim_time, state.counts = fr.time, fr.counts()
        rend.draw_scene(state, fr)
        if legend:
            rend.draw_legend(state)
        if panel:
            draw_panel(window, state, source, scene)
        if k == 0 and (legend or panel):
            # ImGui lays its windows out on the frame after they are first declared:
            # draw the first frame once unsaved so the saved one has the legend and panel.
            # (window.show() crashes without a visible window; save_image ends the frame instead.)
            warm = out / ".view_warmup.png"
            window.save_image(str(warm))
            warm.unlink(missing_ok=True)
            rend.draw_scene(state, fr)
            if legend:
                rend.draw_legend(state)
            if panel:
                draw_panel(window, state, source, scene)
        path = out / f"view_{k:05d}.png"
        with atomic_path(path) as tmp:
            window.save_image(str(tmp))
        manifest.record(path.name, "")
        paths.append(path)
        prog.advance(task)
    prog.stop()
    if mp4:
        encode_mp4(paths, out / "view.mp4", fps=_fps(source), quality=VIEW_MP4_QUALITY)
        manifest.record("view.mp4", "")
    return paths


VIEW_MANIFEST = "view.json"  # what headless views wrote into their folder (io/manifest.py)


def _claim_view_folder(out: Path, names: list[str], own: Path | None):
    """The folder's manifest, once nothing of the user's is in the way of ``names``; the frames an
    earlier, longer view left there are removed (they were ours), so the folder shows one view."""
    from ..io.manifest import Manifest
    from ..io.run import refuse_inside_other_run

    refuse_inside_other_run(out, own, "view")
    out.mkdir(parents=True, exist_ok=True)
    manifest = Manifest(out, VIEW_MANIFEST)
    manifest.refuse_foreign(names, "view")
    manifest.keep_only(names)
    manifest.plan(names)
    return manifest


def _fps(source) -> float:
    if source.live:
        return float(source.scene.solver.frame_rate)
    return float(source.info.frame_rate) if source.info is not None else 30.0


def run_interactive(target, arch: str = DEFAULT_ARCH, up: str = DEFAULT_UP, out: str | Path = "view_out",
                    size: tuple[int, int] | None = None, color_mode: str | None = None,
                    max_frames: int | None = None, window=None, recording: bool = False) -> ViewerState:
    """Open a window and show the scene (live) or the sequence (playback) until closed.

    ``size`` and ``color_mode`` override the scene's ``[view]`` as in :func:`run_headless`.
    ``max_frames``, ``window`` and ``recording`` let tests drive the loop with an offscreen window.
    Returns the final viewer state.
    """
    source, cfg = open_source(target, arch, up)
    if color_mode:
        cfg = cfg.model_copy(update={"color_mode": color_mode})
    window = window or make_window(tuple(size or cfg.window_size), headless=False, fps_limit=cfg.fps_limit)
    rend = _renderer(window, source, cfg)
    state = _new_state(cfg, source)
    state.recording = recording
    inp = Input(window, cfg.move_speed, rend.extent)
    scene = source.scene if source.live else None
    out = Path(out)
    t_last = time.perf_counter()
    drawn = 0
    while window.running and not state.quit and (max_frames is None or drawn < max_frames):
        drawn += 1
        inp.poll(state)
        _advance(state, source)
        fr = _current(source, state)
        state.sim_time, state.counts = fr.time, fr.counts()
        rend.draw_scene(state, fr)
        rend.draw_legend(state)
        draw_panel(window, state, source, scene)
        if state.show_help:
            rend.draw_help()
        now = time.perf_counter()
        state.fps = 0.9 * state.fps + 0.1 / max(now - t_last, 1e-6)
        t_last = now
        if state.screenshot or state.recording:
            out.mkdir(parents=True, exist_ok=True)
            if state.screenshot:
                name = out / f"screenshot_{state.shot_index:04d}.png"
                state.shot_index += 1
                state.screenshot = False
            else:
                name = out / f"record_{state.record_index:05d}.png"
                state.record_index += 1
            window.save_image(str(name))
        else:
            window.show()
    return state

