"""Real-time viewer (Taichi GGUI): live simulation, playback, or headless PNGs.

    whitecap view scenes/dam_break.toml            live: the solver runs while you watch
    whitecap view out/dam_break                    playback of a run (or any particle sequence)
    whitecap view out/dam_break --headless --frames 30 --out shots --mp4

The viewer's state is one explicit dataclass (:class:`ViewState`); frames
come from a *source* (live solver or files) as plain arrays; drawing is one
function used by both the interactive loop and headless rendering. Taichi
compute stays on the CPU; GGUI draws through Vulkan (lavapipe on machines
without a GPU).
"""

from __future__ import annotations

import ctypes.util
import glob
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import Scene, View, load_scene
from ..errors import InputError, WhitecapError
from ..io import read
from ..io.run import RunInfo
from ..progress import console, progress

DIFFUSE_COLORS = np.array([[1.0, 1.0, 1.0], [0.82, 0.82, 0.82], [0.62, 0.8, 1.0]], np.float32)  # spray, foam, bubbles
SLOW, FAST = np.array([0.05, 0.2, 0.65]), np.array([0.75, 0.92, 1.0])  # fluid colour ramp
HELP = "space pause | n step | r reset | p screenshot | v record | 1/2/3 fluid/diffuse/obstacles | h help | RMB+drag orbit, WASD/QE move"


def require_vulkan() -> None:
    """Fail with the package to install when no Vulkan loader or driver exists."""
    icds = glob.glob("/usr/share/vulkan/icd.d/*.json") + glob.glob("/etc/vulkan/icd.d/*.json")
    if ctypes.util.find_library("vulkan") is None or not icds:
        raise WhitecapError(
            "the viewer needs a Vulkan driver; on Debian/Ubuntu install it with: "
            "apt-get install mesa-vulkan-drivers libvulkan1"
        )


# ============================================================================ frames
@dataclass
class Frame:
    """What one frame shows."""

    index: int
    time: float
    fluid_x: np.ndarray
    fluid_v: np.ndarray
    density: np.ndarray | None = None
    diffuse_x: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    diffuse_type: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))


class PlaybackSource:
    """Frames from a whitecap run directory or a numbered particle sequence."""

    def __init__(self, path: str | Path, up: str = "z"):
        p = Path(path)
        self.up = up
        if p.is_dir() and (p / "run.json").exists():
            self.info = RunInfo.load(p)
            self.run = p
            self.frames = [(i, p / rel) for i, rel in self.info.files("fluid")]
            self.diffuse = {i: p / rel for i, rel in self.info.files("diffuse")}
            self.radius = self.info.particle_radius
            self.domain = (np.array(self.info.domain["lower"]), np.array(self.info.domain["upper"]))
            self.obstacles = self.info.obstacles
            self.scene_dir = Path(self.info.extra.get("scene_dir", p))
            self.dt = 1.0 / self.info.frame_rate
        else:
            if not p.exists() and not any(c in str(p) for c in "*?["):
                raise InputError(f"{p}: no such run directory or sequence")
            from ..io.sequence import find_sequence

            self.info, self.run = None, None
            self.frames = find_sequence(p)
            self.diffuse = {}
            first = read(self.frames[0][1], up=up)
            lo, hi = first.positions.min(0), first.positions.max(0)
            self.domain = (lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo))
            # Without metadata, a radius from the spacing of the first frame.
            from scipy.spatial import cKDTree

            d, _ = cKDTree(first.positions).query(first.positions[:2000], k=2)
            self.radius = float(np.median(d[:, 1]) / 2)
            self.obstacles, self.scene_dir, self.dt = [], p.parent, 1.0
        if not self.frames:
            raise InputError(f"{p}: no frames to show")

    def __len__(self) -> int:
        return len(self.frames)

    def get(self, k: int) -> Frame:
        index, path = self.frames[k % len(self.frames)]
        f = read(path, **({} if self.info else {"up": self.up}))
        if f.velocities is None:
            f.velocities = np.zeros_like(f.positions)
        fr = Frame(index, index * self.dt, f.positions, f.velocities, f.density)
        if index in self.diffuse:
            d = read(self.diffuse[index])
            fr.diffuse_x, fr.diffuse_type = d.positions, d.arrays.get("type", np.ones(len(d), np.uint8))
        return fr


class LiveSource:
    """The solver (and in-simulation foam) advancing as the viewer asks."""

    def __init__(self, scene: Scene, arch: str = "cpu"):
        from ..sim.driver import build_solver, run_info_for

        self.scene = scene
        self.arch = arch
        self.solver = build_solver(scene, arch)
        self.info = run_info_for(scene, self.solver)
        self.radius = scene.solver.particle_radius
        self.domain = (np.array(scene.domain.lower), np.array(scene.domain.upper))
        self.obstacles = [o.model_dump() for o in scene.obstacle]
        self.scene_dir = Path(scene.base_dir)
        self.foam = None
        if scene.foam.enabled:
            from ..foam import FoamGenerator, resolve

            self.foam = FoamGenerator(resolve(scene.foam), self.radius, self.domain, scene.domain.gravity, scene.seed)
        self.index = 0
        self.steps_per_s = 0.0
        self._initial = self.solver.checkpoint()
        self.last = self._frame()

    def _frame(self) -> Frame:
        from ..io import ParticleFrame

        a = self.solver.arrays(with_density=self.scene.view.color_by == "density")
        fr = Frame(self.index, self.solver.time, a["positions"], a["velocities"], a["density"])
        if self.foam is not None:
            d = self.foam.step(ParticleFrame(a["positions"], a["velocities"], a["ids"]), self.index,
                               1.0 / self.scene.solver.frame_rate)
            fr.diffuse_x, fr.diffuse_type = d.positions, d.arrays["type"]
        return fr

    def advance(self) -> Frame:
        t0, s0 = time.perf_counter(), self.solver.step_count
        self.index += 1
        self.solver.advance_frame(self.index)
        self.steps_per_s = (self.solver.step_count - s0) / max(time.perf_counter() - t0, 1e-9)
        self.last = self._frame()
        return self.last

    def reset(self) -> Frame:
        self.solver.restore(self._initial)
        if self.foam is not None:
            from ..foam.generator import DiffuseState

            self.foam.state = DiffuseState.empty()
        self.index = 0
        self.last = self._frame()
        return self.last


# ============================================================================ state and drawing
@dataclass
class ViewState:
    cfg: View
    show_fluid: bool = True
    show_diffuse: bool = True
    show_obstacles: bool = True
    paused: bool = False
    recording: bool = False
    loop: bool = True
    help: bool = False
    cursor: int = 0  # playback position
    fps: float = 0.0
    color_range: tuple[float, float] = (0.0, 1.0)


def fluid_colors(fr: Frame, cfg: View) -> tuple[np.ndarray, tuple[float, float]]:
    if cfg.color_by == "density" and fr.density is not None:
        q = fr.density
        lo, hi = float(np.percentile(q, 1)), float(np.percentile(q, 99))
    else:
        q = np.linalg.norm(fr.fluid_v, axis=1)
        lo, hi = (cfg.speed_range if cfg.speed_range else (0.0, float(q.max()) if len(q) else 1.0))
    t = np.clip((q - lo) / max(hi - lo, 1e-9), 0, 1)[:, None]
    return ((1 - t) * SLOW + t * FAST).astype(np.float32), (lo, hi)


def obstacle_meshes(entries: list[dict], base: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """(vertices, triangle indices) of each obstacle's collision mesh, transformed."""
    import trimesh

    from ..config import Obstacle
    from ..sim.obstacles import transform_matrix

    out = []
    for e in entries:
        path = Path(e["mesh"]) if Path(e["mesh"]).is_absolute() else base / e["mesh"]
        if not path.is_file():
            continue
        m = trimesh.load(str(path), force="mesh")
        m.apply_transform(transform_matrix(Obstacle(**e)))
        out.append((np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32).ravel()))
    return out


def box_lines(lo, hi) -> np.ndarray:
    c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], np.float32)
    edges = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]
    return np.array([c[k] for e in edges for k in e], np.float32)


def default_camera(cfg: View, domain) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = domain
    c = (lo + hi) / 2
    L = float(np.linalg.norm(hi - lo))
    pos = np.array(cfg.camera_position) if cfg.camera_position else c + np.array([0.3 * L, -1.1 * L, 0.55 * L])
    look = np.array(cfg.camera_lookat) if cfg.camera_lookat else np.array([c[0], c[1], lo[2] + 0.25 * (hi[2] - lo[2])])
    return pos, look


def project(points: np.ndarray, cfg: View, domain, size) -> np.ndarray:
    """Pixel coordinates (x right, y down) of world points under the start camera
    (look-at view, vertical field of view ``cfg.fov``), as GGUI draws them."""
    pos, look = default_camera(cfg, domain)
    f = look - pos
    f /= np.linalg.norm(f)
    s = np.cross(f, [0.0, 0.0, 1.0])
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    rel = np.asarray(points, np.float64) - pos
    xc, yc, zc = rel @ s, rel @ u, rel @ f
    w, h = size
    t = np.tan(np.radians(cfg.fov) / 2)
    ndc_x = xc / (zc * t * (w / h))
    ndc_y = yc / (zc * t)
    return np.stack([(ndc_x + 1) / 2 * w, (1 - ndc_y) / 2 * h], axis=1)


class Renderer:
    """GGUI window, scene and the fields drawn from (capacity grows as needed)."""

    def __init__(self, cfg: View, source, headless: bool):
        import taichi as ti

        require_vulkan()
        self.ti = ti
        self.cfg = cfg
        self.source = source
        try:
            self.window = ti.ui.Window("whitecap", tuple(cfg.window), show_window=not headless, vsync=not headless)
        except Exception as exc:
            raise WhitecapError(
                f"could not open a Vulkan window ({exc}); install Debian's mesa-vulkan-drivers libvulkan1"
            ) from None
        self.canvas = self.window.get_canvas()
        self.scene = self.window.get_scene()
        self.camera = ti.ui.Camera()
        pos, look = default_camera(cfg, source.domain)
        self.camera.position(*pos)
        self.camera.lookat(*look)
        self.camera.up(0, 0, 1)
        self.camera.fov(cfg.fov)
        self._cap = {}
        self.fields = {}
        lines = box_lines(*source.domain)
        self.box = ti.Vector.field(3, ti.f32, len(lines))
        self.box.from_numpy(lines)
        self.obstacles = []
        for v, idx in obstacle_meshes(source.obstacles, source.scene_dir):
            fv, fi = ti.Vector.field(3, ti.f32, len(v)), ti.field(ti.i32, len(idx))
            fv.from_numpy(v)
            fi.from_numpy(idx)
            self.obstacles.append((fv, fi))

    def _field(self, name: str, data: np.ndarray):
        ti = self.ti
        n = max(len(data), 1)
        if self._cap.get(name, 0) < n:
            cap = max(n, int(1.5 * self._cap.get(name, 0)))
            self.fields[name] = ti.Vector.field(3, ti.f32, cap)
            self._cap[name] = cap
        buf = np.zeros((self._cap[name], 3), np.float32)
        buf[: len(data)] = data
        self.fields[name].from_numpy(buf)
        return self.fields[name]

    def draw(self, fr: Frame, st: ViewState, info: str = "") -> None:
        cfg, sc = self.cfg, self.scene
        sc.set_camera(self.camera)
        sc.ambient_light((0.45, 0.45, 0.45))
        lo, hi = self.source.domain
        sc.point_light(pos=tuple((lo + hi) / 2 + np.array([0, -1.0, 2.0]) * np.linalg.norm(hi - lo)), color=(0.9, 0.9, 0.9))
        r = self.source.radius * cfg.point_scale
        if st.show_fluid and len(fr.fluid_x):
            col, st.color_range = fluid_colors(fr, cfg)
            sc.particles(self._field("fx", fr.fluid_x), radius=r, per_vertex_color=self._field("fc", col),
                         index_count=len(fr.fluid_x))
        if st.show_diffuse and len(fr.diffuse_x):
            col = DIFFUSE_COLORS[np.clip(fr.diffuse_type, 0, 2)]
            sc.particles(self._field("dx", fr.diffuse_x), radius=0.6 * r, per_vertex_color=self._field("dc", col),
                         index_count=len(fr.diffuse_x))
        if st.show_obstacles:
            for fv, fi in self.obstacles:
                sc.mesh(fv, indices=fi, color=(0.78, 0.7, 0.62), two_sided=True)
        sc.lines(self.box, width=2.0, color=(0.6, 0.6, 0.65))
        self.canvas.set_background_color(tuple(cfg.background))
        self.canvas.scene(sc)
        gui = self.window.get_gui()
        with gui.sub_window("whitecap", 0.01, 0.01, 0.45, 0.3):
            what = "speed [m/s]" if cfg.color_by == "speed" else "density [kg/m³]"
            gui.text(f"frame {fr.index}   t = {fr.time:.3f} s")
            gui.text(f"fluid {len(fr.fluid_x):,}   coloured by {what}: {st.color_range[0]:.3g} (blue) .. {st.color_range[1]:.3g} (white)")
            c = [int((fr.diffuse_type == t).sum()) for t in range(3)]
            gui.text(f"spray {c[0]:,} (white)  foam {c[1]:,} (grey)  bubbles {c[2]:,} (blue)")
            gui.text(info)
            if st.help:
                gui.text(HELP)


def _headless_frames(source, n: int | None) -> list[int]:
    total = len(source) if isinstance(source, PlaybackSource) else (n or 1)
    return list(range(min(total, n) if n else total))


def run_view(
    target: str | Path,
    headless: bool = False,
    frames: int | None = None,
    out: str | Path | None = None,
    mp4: bool = False,
    arch: str = "cpu",
    up: str = "z",
    show_progress: bool = True,
) -> list[Path]:
    """Show a scene live or play back a run/sequence; headless writes PNGs (and an MP4)."""
    from ..io.atomic import atomic_path
    from ..sim import runtime

    target = Path(target)
    if headless and out is None:
        raise InputError("--headless needs --out DIR for the images")
    require_vulkan()
    runtime.init(arch)
    if target.suffix == ".toml":
        scene = load_scene(target)
        source, cfg = LiveSource(scene, arch), scene.view
    else:
        source = PlaybackSource(target, up=up)
        cfg = load_scene(target / "scene.toml").view if (target / "scene.toml").is_file() else View()
    st = ViewState(cfg)
    ren = Renderer(cfg, source, headless)
    written: list[Path] = []
    if headless:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        bar = progress(disable=not show_progress)
        with bar:
            task = bar.add_task("view", total=len(_headless_frames(source, frames)), info="")
            for k in _headless_frames(source, frames):
                fr = source.get(k) if isinstance(source, PlaybackSource) else (source.last if k == 0 else source.advance())
                t0 = time.perf_counter()
                ren.draw(fr, st)
                path = out / f"view_{k:05d}.png"
                with atomic_path(path) as tmp:
                    ren.window.save_image(str(tmp))
                written.append(path)
                bar.update(task, advance=1, info=f"{1e3 * (time.perf_counter() - t0):.0f} ms/frame")
        if mp4:
            import imageio.v2 as imageio

            with atomic_path(out / "view.mp4") as tmp:
                with imageio.get_writer(str(tmp), fps=24, codec="libx264", macro_block_size=8, format="FFMPEG") as w:
                    for p in written:
                        w.append_data(imageio.imread(p))
        return written
    _interactive(ren, source, st, out)
    return written


def _interactive(ren: Renderer, source, st: ViewState, out) -> None:  # pragma: no cover (needs a display)
    ti, win = ren.ti, ren.window
    live = isinstance(source, LiveSource)
    fr = source.last if live else source.get(0)
    shots = Path(out or ".")
    rec = 0
    last = time.perf_counter()
    L = float(np.linalg.norm(source.domain[1] - source.domain[0]))
    while win.running:
        step = False
        for e in win.get_events(ti.ui.PRESS):
            k = e.key
            if k == " ":
                st.paused = not st.paused
            elif k == "n":
                step = True
            elif k == "r":
                fr = source.reset() if live else source.get(0)
                st.cursor = 0
            elif k == "p":
                shots.mkdir(parents=True, exist_ok=True)
                win.save_image(str(shots / f"screenshot_{fr.index:05d}.png"))
            elif k == "v":
                st.recording = not st.recording
            elif k in "123":
                attr = {"1": "show_fluid", "2": "show_diffuse", "3": "show_obstacles"}[k]
                setattr(st, attr, not getattr(st, attr))
            elif k == "h":
                st.help = not st.help
            elif k == ti.ui.ESCAPE:
                return
        ren.camera.track_user_inputs(win, movement_speed=st.cfg.move_speed * L, hold_key=ti.ui.RMB)
        if not st.paused or step:
            if live:
                fr = source.advance()
            else:
                st.cursor = st.cursor + 1 if st.cursor + 1 < len(source) or not st.loop else 0
                st.cursor = min(st.cursor, len(source) - 1)
                fr = source.get(st.cursor)
        now = time.perf_counter()
        st.fps = 1.0 / max(now - last, 1e-9)
        last = now
        info = f"{st.fps:.1f} fps" + (f"   {source.steps_per_s:.0f} steps/s" if live else "")
        ren.draw(fr, st, info)
        gui = win.get_gui()
        with gui.sub_window("controls", 0.01, 0.33, 0.45, 0.3):
            st.paused = not gui.checkbox("play", not st.paused)
            if live:
                s = source.scene.solver
                s.iterations = gui.slider_int("solver iterations", s.iterations, 1, 20)
                s.xsph_c = gui.slider_float("XSPH viscosity c", s.xsph_c, 0.0, 0.3)
                s.vorticity_epsilon = gui.slider_float("vorticity eps", s.vorticity_epsilon, 0.0, 0.5)
                if source.foam is not None:
                    p = source.foam.p
                    k_ta = gui.slider_float("foam k_ta", p.k_ta, 0.0, 10000.0)
                    k_wc = gui.slider_float("foam k_wc", p.k_wc, 0.0, 100000.0)
                    source.foam.with_params(k_ta=k_ta, k_wc=k_wc)
            else:
                st.loop = gui.checkbox("loop", st.loop)
                st.cursor = gui.slider_int("frame", st.cursor, 0, len(source) - 1)
        if st.recording:
            shots.mkdir(parents=True, exist_ok=True)
            win.save_image(str(shots / f"view_{rec:05d}.png"))
            rec += 1
        else:
            win.show()
