"""The browser viewer: the GGUI viewer's scene served to a web page (viser).

For machines without Vulkan or a display (a remote GPU box, an HPC login node,
WSL2) and for Jupyter. It reads the same sources as GGUI (:mod:`.sources`:
a written run or particle sequence played back from disk, or a scene simulated
live), steps them with the same playback logic (:func:`.app._advance`) and
colours them with the same map (:mod:`.colors`). The page is viser's own client,
served from the installed package; nothing is fetched from the network.

    whitecap view out/dam_break --web            # prints http://localhost:8080
    whitecap view scenes/dam_break.toml --web    # live simulation

    import whitecap.view
    whitecap.view.web("out/dam_break")           # inline in a Jupyter notebook

One loop thread owns the source: it advances frames (paced at the run's frame
rate, as GGUI) and sends each one it draws. A live scene waits, paused, for the
first page to connect before it simulates, so the start of the flow is not over
before anyone looks (play, from the page or from Python, also starts it). Browser events (sliders, buttons)
only change the viewer's state and wake the loop. viser keeps only the newest
update of each scene object for a client that falls behind, so a slow browser
skips frames instead of queueing them, and the server holds one frame at a time
(plus the source's small cache): memory stays bounded whatever the run's length.

Where the particles are drawn (``points``): ``browser`` sends the points and the page
draws them with WebGL; ``server`` draws them here (:mod:`.splat`, shaded spheres as
GGUI's) for each connected page's own camera and sends a JPEG picture with a depth
image, which viser's page composites with what it still draws itself (domain box,
obstacles, moving bodies, surface mesh). ``auto`` picks ``server`` above
SERVER_POINTS_ABOVE particles, as ParaView's remote render threshold and trame's
remote/local switch move rendering to the server when the geometry is large. The
choice is made once, at the first frame drawn, and kept for the run: it changes only
when the count passes the threshold by a factor AUTO_HYSTERESIS (above it ×, or below
it ÷), so a run near the threshold does not flip its look from frame to frame. Where
WebGL runs in software (a machine without a GPU) 100k points cost the browser about
0.3 s of CPU a frame, and through an SSH tunnel a 640×480 picture (~50 kB) is far
less to send than 100k points (~1.5 MB). Each page has a render thread that draws the
newest frame for the newest camera, sends it, and waits for the page to answer a
small request before drawing again, so no more pictures are made than the page takes.
"""

from __future__ import annotations

import collections
import contextlib
import errno
import io
import logging
import socket
import threading
import time
from typing import Any, Callable, Literal, cast

import numpy as np

from ..config import DEFAULT_ARCH, DEFAULT_UP
from ..errors import InputError, WhitecapError
from ..geometry import pose_matrix
from ..io.diffuse_types import TYPE_NAMES
from .app import FOAM_SLIDERS, _advance, _current, _new_state, open_source
from .colors import DIFFUSE_COLORS, colormap, fitted_range, fluid_scalar, free_fall_speed
from .geometry import box_lines, load_obstacle_meshes

log = logging.getLogger("whitecap.view")

DEFAULT_HOST = "localhost"  # serve on this machine only; --host 0.0.0.0 opens it up
DEFAULT_PORT = 8080
MAX_POINTS = 300_000  # fluid (and per-type diffuse) points drawn at most; more are subsampled
SUBSAMPLE_SEED = 0  # the subsample is the same particles every frame
IDLE_WAIT_S = 0.25  # how long the loop sleeps when nothing plays (a browser event wakes it at once)
PLAY_WAIT_S = 0.004  # loop period while playing: the pacing in app._advance decides when a frame is due
DOMAIN_COLOR = (191, 191, 204)  # domain box outline, as GGUI's (0.75, 0.75, 0.8)
DOMAIN_LINE_PX = 2.0  # domain box outline width [px]
SURFACE_COLOR = (90, 150, 220)  # reconstructed fluid surface
SURFACE_OPACITY = 0.7
COLORBAR_PX = (16, 256)  # colour bar image height, width [px]
# Point shapes offered. Discs look like GGUI's spheres; squares skip a per-pixel test (in headless
# Chromium's software WebGL without multisampling, no measurable gain: 2.7 frames/s for both).
PointShape = Literal["circle", "square"]
POINT_SHAPES: tuple[PointShape, ...] = ("circle", "square")
# Headless Chromium's flags for the tests and the benchmark (one place): software WebGL through
# ANGLE on SwiftShader, the only WebGL this GPU-less machine's Chromium offers (ANGLE on Vulkan
# through Mesa's lavapipe gives no WebGL context at all in Chromium 156 here). "swiftshader-webgl"
# (SwiftShader for WebGL only) rather than "swiftshader": 10-15 % less browser CPU per frame shown
# for 100k points (bench_view --web, 3 interleaved pairs), same picture.
HEADLESS_CHROMIUM_ARGS = ("--enable-unsafe-swiftshader", "--use-gl=angle", "--use-angle=swiftshader-webgl",
                          "--ignore-gpu-blocklist", "--webgl-antialiasing-mode=none", "--webgl-msaa-sample-count=0")
# Where the particles are drawn (module docstring). The threshold: on this project's 2-core
# machine without a GPU, headless Chromium's software WebGL shows 20k points at about 14
# frames/s and 100k at 4 (README, bench_view.py --web); it falls under the 10 frames/s target
# near 30k, above which drawing on the server is faster. Browsers with a GPU draw far more;
# choose --points browser there.
POINTS_MODES = ("auto", "browser", "server")
SERVER_POINTS_ABOVE = 30_000  # auto: particles (fluid + diffuse) in a frame above which the server draws them
AUTO_HYSTERESIS = 1.5  # auto: after the first frame's choice, switch only past SERVER_POINTS_ABOVE × or ÷ this
JPEG_QUALITY = 85  # server pictures [-]: ~40-50 kB at 640x480
ACK_KEY = "whitecap-picture-ack"  # localStorage key the page is asked for after each picture (the pacing round trip)
SENT_FRAMES_KEPT = 100_000  # pictures whose frame a page remembers (the benchmark maps the page's pictures to frames)
ACK_TIMEOUT_S = 10.0  # a page that answers nothing this long gets the next picture anyway
CANVAS_RGB = (20 / 255, 20 / 255, 20 / 255)  # viser's dark-mode canvas: server pictures fill it where no particle is
INSTALL_HINT = "the browser viewer needs viser: pip install 'whitecap[web]'"


def _u8(rgb) -> np.ndarray:
    return np.clip(np.round(np.asarray(rgb, np.float32) * 255.0), 0, 255).astype(np.uint8)


def _rgb8(rgb) -> tuple[int, int, int]:
    """One colour as viser takes it: 3 ints 0..255."""
    r, g, b = (int(c) for c in _u8(rgb))
    return r, g, b


def check_port(port) -> int:
    """``port`` as a TCP port number: 1..65535, or 0 for any free port; else a one-line error."""
    if isinstance(port, bool) or not isinstance(port, (int, np.integer)) or not 0 <= int(port) <= 65535:
        raise InputError(f"view --web: --port must be a number from 1 to 65535 (0: any free port), got {port}")
    return int(port)


def check_port_free(host: str, port: int) -> None:
    """A one-line error naming the port when something already listens on it (viser
    itself would quietly move to the next free port, away from an SSH forward)."""
    if not check_port(port):
        return
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise WhitecapError(f"view --web: cannot resolve host '{host}' ({exc.strerror})") from None
    for family, kind, proto, _, addr in infos:
        with socket.socket(family, kind, proto) as s:
            # as the server binds: a port left in TIME_WAIT is free, one with a listener is not
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(addr)
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    raise WhitecapError(f"view --web: port {port} is already in use on {host}; "
                                        "choose another with --port") from None
                if exc.errno == errno.EADDRNOTAVAIL:  # e.g. no IPv6 on this machine
                    continue
                raise WhitecapError(f"view --web: cannot serve on {host}:{port} ({exc.strerror})") from None


def subsample(n: int, max_points: int) -> np.ndarray | None:
    """Indices of ``max_points`` of ``n`` particles (sorted, the same ones for the same n),
    or None when all are drawn."""
    if n <= max_points:
        return None
    rng = np.random.default_rng(SUBSAMPLE_SEED)
    return np.sort(rng.choice(n, max_points, replace=False))


class WebViewer:
    """A viser server showing TARGET (scene TOML: live; run directory or sequence: playback).

    ``start()`` runs the loop in a background thread (notebooks, tests), ``serve()``
    runs it in the calling thread until interrupted (the CLI). ``port=0`` picks a free port.
    ``paced=False`` plays as fast as frames can be read (the benchmark).
    """

    def __init__(self, target, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, arch: str = DEFAULT_ARCH,
                 up: str = DEFAULT_UP,
                 color_mode: str | None = None, max_points: int = MAX_POINTS, paced: bool = True,
                 point_shape: str = "circle", points: str | None = None):
        try:
            import viser
        except ImportError:
            raise WhitecapError(INSTALL_HINT) from None
        if point_shape not in POINT_SHAPES:
            raise InputError(f"view --web: point shape must be one of {', '.join(POINT_SHAPES)}, got '{point_shape}'")
        if max_points < 1:
            raise InputError(f"view --max-points: expected at least 1, got {max_points}")
        port = check_port(port)
        self.source, self.cfg = open_source(target, arch, up)  # a missing run stops here, before any server
        points = points or self.cfg.web_points
        if points not in POINTS_MODES:
            raise InputError(f"view --points: expected one of {', '.join(POINTS_MODES)}, got '{points}'")
        self.points = points
        if color_mode:
            self.cfg = self.cfg.model_copy(update={"color_mode": color_mode})
        self.live = bool(self.source.live)
        self.scene = self.source.scene if self.live else None
        self.max_points = int(max_points)
        self.paced = paced
        self.state = _new_state(self.cfg, self.source)
        self.state.paused = True  # playback waits for play; live waits for the first page, then simulates
        self.waiting_for_page = self.live  # cleared by the first connection or by play / pause
        self.show = {"fluid": True, **{name: True for name in TYPE_NAMES}, "obstacles": True, "domain": True,
                     "surface": False}
        self.point_scale = float(self.cfg.point_scale)
        self.point_shape = cast(PointShape, point_shape)  # one of POINT_SHAPES, checked above
        self.speed_scale = free_fall_speed(self.source.bounds)
        self.drawn_frame: int | None = None  # source frame index of the picture last sent
        self.frames_sent = 0
        self.note = ""
        self.error: str | None = None  # the last frame that could not be shown, and why
        self._pending: dict = {}  # live parameter changes, applied by the loop between steps
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._drawn_key: tuple | None = None
        self._version = 0  # counts browser changes to what is shown
        self._surface_index: int | None = None
        self._sub_cache: dict[int, np.ndarray | None] = {}
        self._poses: dict[int, dict | None] = {}  # per obstacle, the body pose last sent (absent: at rest)
        self.drawn_on_server: bool | None = None  # where the last frame's particles were drawn
        self._auto_server: bool | None = None  # --points auto: the choice made for this run (module docstring)
        self.passes = 0  # loop passes made (wait_until's waiters count progress by them)
        self._events = threading.Condition()  # notified after each loop pass, drawn frame, connection and picture
        # server drawing: (seq, frame index, positions, radii, colours) of the frame shown
        self.spheres: tuple[int, int, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._spheres_seq = 0
        self._pictures: dict[int, "_PagePictures"] = {}  # server drawing: one render thread per connected page
        self._pictures_lock = threading.Lock()

        check_port_free(host, port)
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints its own banner; the CLI prints the URL
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.host, self.port = host, self.server.get_port()
        if port and self.port != port:  # lost a race for the port after the check
            self.server.stop()
            raise WhitecapError(f"view --web: port {port} is already in use on {host}; choose another with --port")
        self._build_scene(viser)
        self._build_gui()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    # ------------------------------------------------------------------ setup
    @property
    def url(self) -> str:
        host = socket.gethostname() if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{'[' + host + ']' if ':' in host else host}:{self.port}"

    def _build_scene(self, viser) -> None:
        sc, cam = self.server.scene, self.state.camera
        sc.set_up_direction("+z")
        ic = self.server.initial_camera
        ic.position, ic.look_at, ic.up = tuple(cam.eye), tuple(cam.target), (0.0, 0.0, 1.0)
        ic.fov = float(np.radians(cam.fov))
        # no share tunnel: nothing leaves the machine
        self.server.gui.configure_theme(dark_mode=True, show_logo=False, show_share_button=False)
        b = self.source.bounds
        self.h_domain = sc.add_line_segments("/domain", box_lines(b.lower, b.upper).reshape(-1, 2, 3), DOMAIN_COLOR,
                                             thickness=DOMAIN_LINE_PX, thickness_units="screen")
        # Points go to the browser in single precision, relative to the domain's centre. (Half
        # precision would halve the bytes but costs more to draw than it saves where WebGL runs
        # in software: Chromium's SwiftShader converts half-float vertices on the CPU.)
        self.origin = 0.5 * (np.asarray(b.lower, float) + np.asarray(b.upper, float))
        self.precision: Literal["float16", "float32"] = "float32"
        empty = np.zeros((1, 3), np.float32)
        x0, y0, z0 = (float(c) for c in self.origin)

        def cloud(name: str, color: tuple[int, int, int]):
            return sc.add_point_cloud(name, empty, color, point_size=self._size(), point_shape=self.point_shape,
                                      point_shading="flat", visible=False, precision=self.precision,
                                      position=(x0, y0, z0))

        self.h_fluid = cloud("/fluid", (0, 0, 0))
        self.h_diffuse = [cloud(f"/diffuse/{name}", _rgb8(DIFFUSE_COLORS[t])) for t, name in enumerate(TYPE_NAMES)]
        # viser's client builds a new point material whenever a cloud's colours change (every frame
        # for the fluid) and disposes the old one; three.js then deletes the shader program, which was
        # the only user, and compiles and links it again for the next frame. A second cloud with
        # per-point colours that never change holds the same program, so each new material reuses
        # it: 30 ms less browser main-thread CPU per frame shown in software WebGL (bench_view --web).
        # Its two points sit on a corner of the domain box, in the box's colour (a point of size 0
        # still covers one pixel), and hide with the box.
        corner = np.asarray(b.lower, np.float32)[None] - self.origin.astype(np.float32)
        self.h_program_keeper = sc.add_point_cloud(
            "/program_keeper", np.repeat(corner, 2, 0), np.repeat(np.asarray([DOMAIN_COLOR], np.uint8), 2, 0),
            point_size=0.0, point_shape=self.point_shape, point_shading="flat", precision=self.precision,
            position=(x0, y0, z0))
        self.h_obstacles = []
        for v, f, _, color, k in load_obstacle_meshes(self.source.obstacles(), self.source.obstacle_base()):
            h = sc.add_mesh_simple(f"/obstacles/{k}", v, f, color=_rgb8(color), side="double")
            self.h_obstacles.append((k, h))
        self.h_surface: Any = None  # viser's mesh handle of the frame's surface
        info = getattr(self.source, "info", None)
        self.surfaces = {i: self.source.path / rel for i, rel in info.files("mesh")} if info is not None else {}
        self._so3 = viser.transforms.SO3

    def _size(self) -> float:
        # viser draws a point of size s as a disc of s / tan(fov/2) · H / z pixels across: s is its radius [m]
        return float(self.source.radius) * self.point_scale

    def _build_gui(self) -> None:
        g = self.server.gui
        self.g_info = g.add_markdown(self._info_text(None))
        if self.live:
            with g.add_folder("simulation"):
                self.g_play = g.add_button("play / pause")
                self.g_step = g.add_button("step")
                self.g_reset = g.add_button("reset")
                assert self.scene is not None  # a live view has its scene
                s = self.scene.solver
                self.g_solver: dict[str, Any] = {  # viser's slider handles
                    "iterations": g.add_slider("iterations", 1, 20, 1, int(s.iterations)),
                    "xsph_c": g.add_slider("XSPH c", 0.0, 0.5, 0.005, float(s.xsph_c)),
                    "vorticity_epsilon": g.add_slider("vorticity eps", 0.0, 0.5, 0.005, float(s.vorticity_epsilon)),
                }
                for name, h in self.g_solver.items():
                    h.on_update(self._pending_from(("solver", name), h))
                fp = self.source.foam_params
                self.g_foam: dict[str, Any] = {}
                if fp is not None:
                    for name in FOAM_SLIDERS:
                        v = float(getattr(fp, name))
                        h = g.add_slider(name, 0.0, max(4.0 * v, 1.0), max(4.0 * v, 1.0) / 200, v)
                        h.on_update(self._pending_from(("foam", name), h))
                        self.g_foam[name] = h
            self.g_reset.on_click(lambda e: self._poke(reset=True))
        else:
            with g.add_folder("playback"):
                n = len(self.source)
                self.g_frame = g.add_slider("frame", 0, max(n - 1, 1), 1, 0, disabled=n < 2)
                self.g_play = g.add_button("play / pause")
                self.g_step = g.add_button("step")
                self.g_loop = g.add_checkbox("loop", self.state.loop)
            self.g_frame.on_update(self._on_frame_slider)
            self.g_loop.on_update(lambda e: self._poke(loop=self.g_loop.value))
        self.g_play.on_click(lambda e: self.play(self.state.paused))
        self.g_step.on_click(lambda e: self._poke(step_once=True, paused=True))
        with g.add_folder("display"):
            self.g_color = g.add_dropdown("colour by", ("speed", "density"), initial_value=self.state.color_mode)
            ramp = np.repeat(np.linspace(0, 1, COLORBAR_PX[1])[None], COLORBAR_PX[0], 0).ravel()
            self.g_colorbar = g.add_image(_u8(colormap(ramp, 0, 1)).reshape(*COLORBAR_PX, 3), format="png")
            self.g_range = g.add_markdown("")
            self.g_size = g.add_slider("point size", 0.1, 4.0, 0.05, self.point_scale)
            self.g_shape = g.add_dropdown("point shape", POINT_SHAPES, initial_value=self.point_shape)
            self.g_show: dict[str, Any] = {}
            kinds = ["fluid", *TYPE_NAMES, "obstacles", "domain"] + (["surface"] if self.surfaces else [])
            for kind in kinds:
                h = g.add_checkbox("surface mesh" if kind == "surface" else kind, self.show[kind])
                h.on_update(self._toggle_from(kind, h))
                self.g_show[kind] = h
        self.g_color.on_update(lambda e: self._poke(color_mode=self.g_color.value, color_range=None))
        self.g_size.on_update(lambda e: self._set_size(self.g_size.value))
        self.g_shape.on_update(lambda e: self._set_shape(self.g_shape.value))

    # ------------------------------------------------------------------ events (viser's threads)
    def _notify(self) -> None:
        with self._events:
            self._events.notify_all()

    def _poke(self, **changes) -> None:
        for k, v in changes.items():
            setattr(self.state, k, v)
        self._changed()

    def _changed(self) -> None:
        self._version += 1
        self._wake.set()

    def _on_frame_slider(self, event) -> None:
        if event.client is None:  # the loop moved the slider to the frame it drew
            return
        self._poke(frame=int(self.g_frame.value), paused=True)

    def _toggle(self, kind: str, on: bool) -> None:
        self.show[kind] = bool(on)
        self._changed()

    def _set_size(self, scale: float) -> None:
        self.point_scale = float(scale)
        self._changed()

    def _set_shape(self, shape: PointShape) -> None:
        self.point_shape = shape
        self._changed()

    def _pending_from(self, key: tuple[str, str], h: Any) -> Callable[[Any], None]:
        """A slider's update callback: its value becomes the pending setting ``key``."""
        return lambda e: self._set_pending(key, h.value)

    def _toggle_from(self, kind: str, h: Any) -> Callable[[Any], None]:
        """A checkbox's update callback: show or hide ``kind``."""
        return lambda e: self._toggle(kind, h.value)

    def _set_pending(self, key, value) -> None:
        self._pending[key] = value
        self._wake.set()

    # ------------------------------------------------------------------ control from Python
    def seek(self, k: int) -> None:
        """Show frame ``k`` (an index into the played sequence), paused."""
        self._poke(frame=int(np.clip(k, 0, len(self.source) - 1)), paused=True)

    def play(self, on: bool = True) -> None:
        self.waiting_for_page = False
        self._poke(paused=not on)

    # ------------------------------------------------------------------ loop
    def start(self) -> "WebViewer":
        """Run the loop in a background thread and return at once."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="whitecap-web", daemon=True)
            self._thread.start()
        return self

    def serve(self) -> None:
        """Run the loop in this thread until stopped (Ctrl-C)."""
        try:
            self._loop()
        finally:
            self.stop()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=10)
        with self._pictures_lock:
            pages, self._pictures = list(self._pictures.values()), {}
        for pp in pages:
            pp.close()
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()

    def __enter__(self) -> "WebViewer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def wait_until(self, predicate, timeout: float | None = None):
        """Wait until ``predicate()`` is true, checking it after each event of the viewer (a
        loop pass, a frame drawn, a page connecting, a server picture reaching its page);
        returns its value, or None after ``timeout`` seconds (None: no limit)."""
        with self._events:
            return self._events.wait_for(predicate, timeout) or None

    def wait_drawn(self, k: int, timeout: float | None = 60.0) -> bool:
        """Wait until played frame ``k`` has been drawn and sent (tests, notebooks)."""
        return bool(self.wait_until(lambda: self.state.frame == k and self.drawn_frame == self._index(k), timeout))

    def picture_shown(self, index: int) -> "_PagePictures | None":
        """A page that has received the server picture of source frame ``index`` for its
        current camera, drawn from the newest spheres (nothing newer is on the way to it)."""
        sph = self.spheres
        for pp in self.pages():
            if sph is not None and sph[1] == index and pp.settled(sph[0]):
                return pp
        return None

    def _index(self, k: int) -> int:
        return k if self.live else self.source.indices[k]

    def _apply_pending(self) -> None:
        assert self.scene is not None  # only a live view has settings pending
        while self._pending:
            (group, name), value = self._pending.popitem()
            if group == "solver":
                setattr(self.scene.solver, name, int(value) if name == "iterations" else float(value))
            elif self.source.foam_params is not None:
                self.source.set_foam_params(**{name: float(value)})
                setattr(self.scene.foam, name, float(value))

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._step()
            except WhitecapError as exc:  # a bad frame: say so in the panel and wait for the user
                self.error = str(exc)
                self.state.paused = True
                self.g_info.content = f"**error:** {self.error}"
                log.warning("%s", self.error)
                self._drawn_key = (self.state.frame, getattr(self.source, "steps", 0), self._version)
            self.passes += 1
            self._notify()
            self._wake.wait(PLAY_WAIT_S if not self.state.paused else IDLE_WAIT_S)
            self._wake.clear()

    def _step(self) -> None:
        """Apply pending live settings, advance when playing, and draw when anything changed."""
        if self.live:
            self._apply_pending()
        if not self.paced and not self.live:
            if self.drawn_on_server and self._pages_behind():
                return  # unpaced and drawn here: each page pictures each frame (no frame is read for nothing)
            self.state.last_advance = None  # every pass advances a frame
        _advance(self.state, self.source)
        key = (self.state.frame, getattr(self.source, "steps", 0), self._version)
        if key != self._drawn_key:
            self._drawn_key = key  # taken before drawing: an event during the draw draws again
            self._draw(_current(self.source, self.state))

    # ------------------------------------------------------------------ drawing
    def _sub(self, n: int) -> np.ndarray | None:
        if n not in self._sub_cache:
            if len(self._sub_cache) > 4:
                self._sub_cache.clear()
            self._sub_cache[n] = subsample(n, self.max_points)
        return self._sub_cache[n]

    def _fluid_values(self, d) -> tuple[np.ndarray, tuple[float, float]]:
        """The fluid's colour values and their range (fitted to the first frame drawn, then kept)."""
        st = self.state
        values = fluid_scalar(d, st.color_mode)
        if st.color_range is None:
            st.color_range = fitted_range(values, st.color_mode, self.speed_scale)
        return values, st.color_range

    def _draw_in_browser(self, fr) -> list[str]:
        """Send the frame's points; the page draws them with WebGL. Returns notes for the panel."""
        size, notes = self._size(), []
        d = fr.as_dict()
        pos = d["positions"]
        n = len(pos)
        if self.drawn_on_server is not False:
            self.spheres = None  # the pages' render threads take the server picture down
            self._wake_pages()
        self.drawn_on_server = False
        if n and self.show["fluid"]:
            values, (lo, hi) = self._fluid_values(d)
            idx = self._sub(n)
            if idx is not None:
                pos, values = pos[idx], values[idx]
                notes.append(f"fluid: drawing {len(idx):,} of {n:,} particles (subsample)")
            self.h_fluid.points = np.asarray(pos - self.origin, np.float32)
            self.h_fluid.colors = _u8(colormap(values, lo, hi))
            self.h_fluid.point_size = size
            self.h_fluid.point_shape = self.point_shape
            self.h_fluid.visible = True
        else:
            self.h_fluid.visible = False
        for t, h in enumerate(self.h_diffuse):
            sel = None
            if fr.diffuse_positions is not None and self.show[TYPE_NAMES[t]]:
                sel = np.flatnonzero(fr.diffuse_type == t)
            if sel is None or not len(sel):
                h.visible = False
                continue
            idx = self._sub(len(sel))
            if idx is not None:
                notes.append(f"{TYPE_NAMES[t]}: drawing {len(idx):,} of {len(sel):,} particles (subsample)")
                sel = sel[idx]
            h.points = np.asarray(fr.diffuse_positions[sel] - self.origin, np.float32)
            h.point_size = float(np.median(fr.diffuse_radius[sel])) * self.point_scale
            h.point_shape = self.point_shape
            h.visible = True
        return notes

    def _draw_on_server(self, fr) -> list[str]:
        """Hand the frame's spheres (every particle, no subsample: the cost of a picture grows
        with the count, not the bytes sent) to the pages' render threads. Returns notes."""
        d = fr.as_dict()
        pos, rad, col = [], [], []
        if len(d["positions"]) and self.show["fluid"]:
            pos.append(np.asarray(d["positions"], np.float32))
            rad.append(np.full(len(pos[-1]), self._size(), np.float32))
            values, (lo, hi) = self._fluid_values(d)
            col.append(colormap(values, lo, hi))
        if fr.diffuse_positions is not None:
            for t, name in enumerate(TYPE_NAMES):
                sel = np.flatnonzero(fr.diffuse_type == t) if self.show[name] else ()
                if len(sel):
                    pos.append(np.asarray(fr.diffuse_positions[sel], np.float32))
                    rad.append(np.asarray(fr.diffuse_radius[sel], np.float32) * self.point_scale)
                    col.append(np.repeat(DIFFUSE_COLORS[t][None], len(sel), 0))
        if self.drawn_on_server is not True:
            self.h_fluid.visible = False
            for h in self.h_diffuse:
                h.visible = False
        self.drawn_on_server = True
        self._spheres_seq += 1
        if pos:
            P, R, C = np.concatenate(pos), np.concatenate(rad), np.concatenate(col).astype(np.float32)
        else:
            P, R, C = np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros((0, 3), np.float32)
        self.spheres = (self._spheres_seq, fr.index, P, R, C)
        self._wake_pages()
        why = ""
        if self.points == "auto":
            why = (f" (more than {SERVER_POINTS_ABOVE:,}: --points auto)" if len(P) > SERVER_POINTS_ABOVE
                   else " (--points auto: kept for this run)")
        return [f"{len(P):,} particles drawn on the server{why}"]

    # ------------------------------------------------------------------ server pictures, per page
    def _connect(self, client) -> None:
        with self._pictures_lock:
            if not self._stop.is_set():
                self._pictures[client.client_id] = _PagePictures(self, client)
        if self.waiting_for_page:  # a live scene starts when someone looks
            self.play(True)
        self._notify()

    def _disconnect(self, client) -> None:
        with self._pictures_lock:
            pp = self._pictures.pop(client.client_id, None)
        if pp is not None:
            pp.close()

    def _wake_pages(self) -> None:
        with self._pictures_lock:
            for pp in self._pictures.values():
                pp.wake.set()

    def pages(self) -> list["_PagePictures"]:
        with self._pictures_lock:
            return list(self._pictures.values())

    def _pages_behind(self) -> bool:
        """Whether a connected page has not had a picture of the newest spheres yet."""
        sph = self.spheres
        return sph is not None and any(pp.ready() and pp.seq != sph[0] for pp in self.pages())

    def _on_server(self, fr) -> bool:
        """Whether this frame's particles are drawn here (``points``; ``auto``: chosen at the
        first frame and kept unless the count passes the threshold by AUTO_HYSTERESIS)."""
        if self.points != "auto":
            return self.points == "server"
        n = fr.n_fluid + (len(fr.diffuse_positions) if fr.diffuse_positions is not None else 0)  # a live frame: no copy
        if self._auto_server is None:
            self._auto_server = n > SERVER_POINTS_ABOVE
        elif self._auto_server and n < SERVER_POINTS_ABOVE / AUTO_HYSTERESIS:
            self._auto_server = False
        elif not self._auto_server and n > SERVER_POINTS_ABOVE * AUTO_HYSTERESIS:
            self._auto_server = True
        return self._auto_server

    def _draw(self, fr) -> None:
        st = self.state
        on_server = self._on_server(fr)
        with self.server.atomic():
            if on_server:
                notes = self._draw_on_server(fr)
            else:
                notes = self._draw_in_browser(fr)
            for k, h in self.h_obstacles:
                h.visible = self.show["obstacles"]
                body = fr.bodies[k] if fr.bodies and k < len(fr.bodies) else None
                if body == self._poses.get(k):  # at the pose already sent (static obstacles: always)
                    continue
                self._poses[k] = body
                M = pose_matrix(body)
                h.wxyz = self._so3.from_matrix(M[:3, :3]).wxyz
                h.position = M[:3, 3]
            self.h_domain.visible = self.h_program_keeper.visible = self.show["domain"]
            self._draw_surface(fr.index)
            self.note = "; ".join(notes)
            self.g_info.content = self._info_text(fr)
            if st.color_range is not None:
                unit = "m/s" if st.color_mode == "speed" else "kg/m³"
                lo, hi = st.color_range
                self.g_range.content = f"{st.color_mode} [{unit}]: {lo:.3g} .. {hi:.3g}"
            if not self.live and int(self.g_frame.value) != st.frame:
                self.g_frame.value = st.frame  # type: ignore[misc]  # viser's setter: its props base hides it from mypy
        self.drawn_frame = fr.index
        self.frames_sent += 1
        self._notify()

    def _draw_surface(self, index: int) -> None:
        path = self.surfaces.get(index) if self.show["surface"] else None
        if path is None:
            if self.h_surface is not None:
                self.h_surface.visible = False
            return
        if self._surface_index != index:
            from ..io import read_mesh

            m = read_mesh(path)
            if len(m.faces):
                self.h_surface = self.server.scene.add_mesh_simple(
                    "/surface", m.vertices, m.faces, color=SURFACE_COLOR, opacity=SURFACE_OPACITY, side="double")
            elif self.h_surface is not None:  # an empty surface: the previous frame's must not stay
                self.h_surface.remove()
                self.h_surface = None
            self._surface_index = index
        if self.h_surface is not None:
            self.h_surface.visible = True

    def _info_text(self, fr) -> str:
        if fr is None:
            return "loading…"
        st = self.state
        head = (f"frame {fr.index}" if self.live else f"frame {fr.index} ({st.frame + 1} of {len(self.source)})")
        mode = "waiting for a page to open" if self.waiting_for_page else "paused" if st.paused else "playing"
        lines = [f"**{head}** · t = {fr.time:.3f} s · {mode}"]
        if self.live:
            lines.append(f"{self.source.steps} solver steps")
        lines.append(" · ".join(f"{name}: {c:,}" for name, c in fr.counts().items()))
        if self.note:
            lines.append(f"*{self.note}*")
        return "\n\n".join(lines)

    # ------------------------------------------------------------------ notebook
    def _repr_html_(self) -> str:
        return (f'<iframe src="{self.url}" width="100%" height="{NOTEBOOK_HEIGHT_PX}" '
                f'style="border:1px solid #ccc"></iframe>'
                f'<div>whitecap viewer at <a href="{self.url}">{self.url}</a></div>')


NOTEBOOK_HEIGHT_PX = 560


class _PagePictures:
    """Server pictures for one connected page: a thread that draws the viewer's newest
    spheres (:attr:`WebViewer.spheres`) for the page's newest camera, sends the picture
    with its depth (viser composites it with the page's own objects), then asks the page
    for a localStorage value (:data:`ACK_KEY`) and waits for the answer: the page handles
    messages in order, so the answer means the picture has arrived and the next one may
    be drawn. Camera moves and new frames arriving meanwhile are coalesced into one picture.
    """

    def __init__(self, viewer: WebViewer, client):
        from .splat import Splatter

        self.viewer, self.client = viewer, client
        self.wake = threading.Event()
        self.sent = 0  # pictures sent
        self.seq: int | None = None  # WebViewer.spheres sequence number of the last picture
        self.frame: int | None = None  # source frame index of the last picture
        self.render_s = 0.0  # time spent drawing and encoding pictures [s]
        # source frame of each picture sent (benchmark)
        self.sent_frames: collections.deque[int] = collections.deque(maxlen=SENT_FRAMES_KEPT)
        self.acked = 0  # pictures the page has answered for (it has received them)
        self._key: tuple | None = None
        self._acked_key: tuple | None = None  # key of the last picture the page answered for
        self._closed = threading.Event()
        self._splatter = Splatter()
        client.camera.on_update(self._camera_moved)
        self._thread = threading.Thread(target=self._run, name=f"whitecap-page-{client.client_id}", daemon=True)
        self._thread.start()

    def _camera_moved(self, cam) -> None:
        self.wake.set()
        self.viewer._notify()

    def ready(self) -> bool:
        """Whether the page has told its camera (pictures can be drawn for it)."""
        return self.client.camera.update_timestamp != 0.0

    def _view(self) -> tuple:
        cam = self.client.camera
        return (tuple(cam.position), tuple(cam.wxyz), float(cam.fov), int(cam.image_width), int(cam.image_height))

    def settled(self, seq: int) -> bool:
        """Whether the page has received the picture of spheres ``seq`` for its current camera."""
        return self.ready() and self._acked_key == (seq, self._view())

    def close(self) -> None:
        self._closed.set()
        self.wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=ACK_TIMEOUT_S + 1)

    def _send(self, rgb: np.ndarray, depth: np.ndarray) -> None:
        """What ``client.scene.set_background_image(rgb, "jpeg", depth=depth)`` sends, with the
        depth PNG encoded by :func:`.splat.encode_depth_png` (viser's own encoding of it took
        most of the server's time per picture)."""
        from viser import _messages

        from .splat import encode_depth_png, encode_jpeg

        self.client._websock_connection.queue_message(_messages.BackgroundImageMessage(
            format="jpeg", rgb_data=encode_jpeg(rgb, JPEG_QUALITY), depth_data=encode_depth_png(depth)))

    def _run(self) -> None:
        while not self._closed.is_set():
            self.wake.wait(IDLE_WAIT_S)
            self.wake.clear()
            if self._closed.is_set():
                return
            try:
                self._picture()
            except RuntimeError:  # the page went away during the round trip
                return
            except Exception as exc:  # noqa: BLE001 -- a thread must not die silently
                log.warning("server picture for page %s: %s", self.client.client_id, exc)

    def _picture(self) -> None:
        if not self.ready():
            return
        sph = self.viewer.spheres
        view = self._view()
        W, H = view[3], view[4]
        key = (sph[0] if sph is not None else None, view)
        if key == self._key and self._acked_key != key and self.sent:
            self._ask()  # the page has not answered for this picture yet: ask again
            return
        if key == self._key or W <= 0 or H <= 0:
            return
        t0 = time.perf_counter()
        if sph is None or not len(sph[2]):
            if self._key is not None and self._key[0] is not None:
                self.client.scene.set_background_image(None)
        else:
            rgb, depth = self._splatter.render(sph[2], sph[3], sph[4], view[1], view[0], view[2], (W, H), CANVAS_RGB)
            self._send(rgb, depth)
        self.render_s += time.perf_counter() - t0
        self._key = key
        if sph is not None:
            self.seq, self.frame = sph[0], sph[1]
            self.sent += 1
            self.sent_frames.append(sph[1])
        self.viewer._wake.set()  # an unpaced loop waits for the pages to take each frame
        self._ask()

    def _ask(self) -> None:
        """The pacing round trip: the page answers after it has handled the picture sent
        before (it handles messages in order). A page that answers nothing for
        ACK_TIMEOUT_S gets the next picture anyway and is asked again for this one."""
        key = self._key
        try:
            self.client.local_storage.get_item(ACK_KEY, timeout=ACK_TIMEOUT_S)
        except TimeoutError:
            pass
        else:
            self._acked_key = key
            self.acked += 1
            self.viewer._notify()
        self.wake.set()  # a newer frame or camera may have come meanwhile


def serve(target, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, arch: str = DEFAULT_ARCH, up: str = DEFAULT_UP,
          color_mode: str | None = None, max_points: int = MAX_POINTS, points: str | None = None,
          announce=print) -> None:
    """The CLI's ``view --web``: serve until Ctrl-C, after printing the URL."""
    v = WebViewer(target, host=host, port=port, arch=arch, up=up, color_mode=color_mode, max_points=max_points,
                  points=points)
    announce(f"whitecap view: open {v.url} in a browser (Ctrl-C stops)"
             + ("; the simulation starts when the page opens" if v.live else ""))
    if v.host in ("localhost", "127.0.0.1", "::1"):
        announce(f"  from another machine: ssh -L {v.port}:localhost:{v.port} THIS_HOST, then open http://localhost:{v.port}")
    try:
        v.serve()
    except KeyboardInterrupt:
        pass


def web(target, host: str = DEFAULT_HOST, port: int = 0, **opts) -> WebViewer:
    """Start the browser viewer in the background and return it; in Jupyter, the returned
    object shows the viewer inline (an iframe of its page). ``port=0`` picks a free port.
    ``viewer.stop()`` ends it."""
    return WebViewer(target, host=host, port=port, **opts).start()
