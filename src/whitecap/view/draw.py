"""Drawing: turns a :class:`ViewerState` and a :class:`Frame` into GGUI calls.

Nothing here reads input; :mod:`whitecap.view.app` does that.
"""

from __future__ import annotations

import numpy as np
import taichi as ti

from .colors import DIFFUSE_COLORS, colormap, fitted_range, fluid_scalar, free_fall_speed
from .geometry import box_lines
from .kernels import fill_fluid_buffer
from .sources import Frame
from .state import ViewerState

Z_NEAR = 0.01  # camera near plane [m]
Z_FAR = 1000.0  # camera far plane [m]
LEGEND_BAR = (0.02, 0.06, 0.22, 0.09)  # colour bar x0, y0, x1, y1 in canvas fractions (y down)
LEGEND_STEPS = 32  # quads in the colour bar
LEGEND_BOX_PX = (250, 60)  # range text box width, height [px]
BOX_LINE_WIDTH = 2.0  # domain box outline width [px]

HELP = [
    "mouse: left drag orbit, right drag pan, middle drag / z x zoom",
    "W A S D Q E: move the camera",
    "space: pause   n: step   r: reset",
    "p: screenshot   v: record PNGs",
    "1/2/3: fluid / diffuse / obstacles   c: speed/density",
    "h: this help   esc: quit",
]


class _Buffer:
    """Growable GGUI vertex buffers (Taichi fields, capacity doubles)."""

    def __init__(self):
        self.cap = 0
        self.pos = self.col = self.rad = None

    def reserve(self, n: int) -> None:
        if n > self.cap:
            self.cap = max(1024, 1 << int(np.ceil(np.log2(n))))
            self.pos = ti.Vector.field(3, ti.f32, self.cap)
            self.col = ti.Vector.field(3, ti.f32, self.cap)
            self.rad = ti.field(ti.f32, self.cap)

    def fill(self, pos: np.ndarray, col: np.ndarray, rad: np.ndarray | None = None) -> int:
        n = len(pos)
        self.reserve(n)
        if n:
            pad = self.cap - n
            self.pos.from_numpy(np.pad(np.asarray(pos, np.float32), ((0, pad), (0, 0))))
            self.col.from_numpy(np.pad(np.asarray(col, np.float32), ((0, pad), (0, 0))))
            if rad is not None:
                self.rad.from_numpy(np.pad(np.asarray(rad, np.float32), (0, pad)))
        return n


class Renderer:
    """Owns the GGUI scene objects and the vertex buffers of one window."""

    def __init__(self, window, radius: float, bounds, obstacles: list, point_scale: float = 1.0,
                 background=(0.13, 0.14, 0.17)):
        self.window = window
        self.canvas = window.get_canvas()
        self.scene = window.get_scene()
        self.camera = ti.ui.Camera()
        self.camera.up(0.0, 0.0, 1.0)
        self.camera.z_near(Z_NEAR)
        self.camera.z_far(Z_FAR)
        self.gui = window.get_gui()
        self.radius = float(radius)
        self.point_scale = float(point_scale)
        self.background = tuple(background)
        self.fluid = _Buffer()
        self.diffuse = _Buffer()
        lines = box_lines(bounds.lower, bounds.upper)
        self.box = ti.Vector.field(3, ti.f32, len(lines))
        self.box.from_numpy(lines)
        self.obstacles = []
        self.rest = []  # per drawn obstacle: [index in the scene, rest vertices, rest normals, pose drawn]
        for v, f, nrm, color, k in obstacles:
            vf = ti.Vector.field(3, ti.f32, len(v))
            vf.from_numpy(v)
            nf = ti.Vector.field(3, ti.f32, len(v))
            nf.from_numpy(nrm)
            idx = ti.field(ti.i32, f.size)
            idx.from_numpy(f.reshape(-1))
            self.obstacles.append((vf, idx, nf, color))
            self.rest.append([k, v, nrm, None])
        self.legend_v = ti.Vector.field(2, ti.f32, 6 * LEGEND_STEPS)
        self.legend_c = ti.Vector.field(3, ti.f32, 6 * LEGEND_STEPS)
        self._legend_geometry()
        self.extent = float(np.linalg.norm(np.asarray(bounds.upper) - np.asarray(bounds.lower)))
        self.speed_scale = free_fall_speed(bounds)

    def _legend_geometry(self) -> None:
        x0, y0, x1, y1 = LEGEND_BAR
        xs = np.linspace(x0, x1, LEGEND_STEPS + 1)
        # canvas coordinates have y up; LEGEND_BAR is given from the top
        ya, yb = 1.0 - y1, 1.0 - y0
        v = []
        for a, b in zip(xs[:-1], xs[1:]):
            v += [(a, ya), (b, ya), (b, yb), (a, ya), (b, yb), (a, yb)]
        self.legend_v.from_numpy(np.asarray(v, np.float32))
        t = np.repeat(np.arange(LEGEND_STEPS) + 0.5, 6) / LEGEND_STEPS
        self.legend_c.from_numpy(colormap(t, 0.0, 1.0))

    # --------------------------------------------------------------- camera
    def set_camera(self, state: ViewerState) -> None:
        cam = state.camera
        self.camera.position(*cam.eye)
        self.camera.lookat(*cam.target)
        self.camera.fov(cam.fov)
        self.scene.set_camera(self.camera)


    # --------------------------------------------------------------- drawing
    def color_range(self, state: ViewerState, frame: Frame) -> tuple[float, float]:
        if state.color_range is None:
            scalar = fluid_scalar(frame.as_dict(), state.color_mode)
            state.color_range = fitted_range(scalar, state.color_mode, self.speed_scale)
        return state.color_range

    def draw_scene(self, state: ViewerState, frame: Frame) -> None:
        self.set_camera(state)
        sc = self.scene
        sc.ambient_light((0.45, 0.45, 0.45))
        eye = state.camera.eye
        sc.point_light(pos=tuple(eye + np.array([0.0, 0.0, self.extent])), color=(0.7, 0.7, 0.7))
        vis = state.visible
        if vis.fluid and frame.n_fluid:
            lo, hi = self.color_range(state, frame)
            if frame.device is not None:
                d, n = frame.device, frame.device.n
                self.fluid.reserve(n)
                fill_fluid_buffer(n, d.x, d.v, d.rho, int(state.color_mode == "density"), lo, hi,
                                  self.fluid.pos, self.fluid.col)
            else:
                col = colormap(fluid_scalar(frame.as_dict(), state.color_mode), lo, hi)
                assert frame.positions is not None  # a frame without a device has its positions
                n = self.fluid.fill(frame.positions, col)
            sc.particles(self.fluid.pos, radius=self.radius * self.point_scale, per_vertex_color=self.fluid.col,
                         index_count=n)
        if (vis.diffuse and frame.diffuse_positions is not None and len(frame.diffuse_positions)
                and frame.diffuse_type is not None):  # sources set the three diffuse arrays together
            t = np.clip(frame.diffuse_type.astype(np.int64), 0, len(DIFFUSE_COLORS) - 1)
            n = self.diffuse.fill(frame.diffuse_positions, DIFFUSE_COLORS[t], frame.diffuse_radius)
            sc.particles(self.diffuse.pos, radius=self.radius, per_vertex_color=self.diffuse.col,
                         per_vertex_radius=self.diffuse.rad, index_count=n)
        if vis.obstacles:
            self.move_bodies(frame.bodies)
            for vf, idx, nf, color in self.obstacles:
                sc.mesh(vf, indices=idx, normals=nf, color=color, two_sided=True)
        if vis.domain:
            sc.lines(self.box, width=BOX_LINE_WIDTH, color=(0.75, 0.75, 0.8))
        self.canvas.set_background_color(self.background)
        self.canvas.scene(sc)

    def move_bodies(self, bodies: list | None) -> None:
        """Moving obstacles at this frame's pose (run.json's ``bodies``, or the live solver's)."""
        from .geometry import posed

        for (vf, _, nf, _), rest in zip(self.obstacles, self.rest):
            k, v, nrm, drawn = rest
            body = bodies[k] if bodies and k < len(bodies) else None
            if body is None or body == drawn:
                continue
            pv, pn = posed(v, nrm, body)
            vf.from_numpy(pv)
            nf.from_numpy(pn)
            rest[3] = body

    def draw_legend(self, state: ViewerState) -> None:
        """Colour bar with its range (the range text sits in a small GUI box under it)."""
        if not state.visible.fluid or state.color_range is None:
            return
        self.canvas.triangles(self.legend_v, per_vertex_color=self.legend_c)
        lo, hi = state.color_range
        unit = "m/s" if state.color_mode == "speed" else "kg/m^3"
        x0, y0, x1, y1 = LEGEND_BAR
        w, h = self.window.get_window_shape()
        bw, bh = min(LEGEND_BOX_PX[0] / w, 0.9), min(LEGEND_BOX_PX[1] / h, 0.5)
        with self.gui.sub_window("legend", x0, y1 + 0.005, bw, bh) as g:
            g.text(f"{state.color_mode} [{unit}]: {lo:.3g} .. {hi:.3g}")

    def draw_help(self) -> None:
        with self.gui.sub_window("help", 0.3, 0.3, 0.4, 0.3) as g:
            for line in HELP:
                g.text(line)


def camera_matrix(cam, aspect: float) -> np.ndarray:
    """Row-vector 4x4 matrix with p_clip = [x y z 1] @ M, from GGUI's own camera matrices."""
    c = ti.ui.Camera()
    c.up(0.0, 0.0, 1.0)
    c.z_near(Z_NEAR)
    c.z_far(Z_FAR)
    c.position(*cam.eye)
    c.lookat(*cam.target)
    c.fov(cam.fov)
    return np.asarray(c.get_view_matrix()) @ np.asarray(c.get_projection_matrix(aspect))


def project(points: np.ndarray, cam, width: int, height: int) -> np.ndarray:
    """Pixel coordinates (column, row from the top) of world points, as the viewer draws them."""
    p = np.c_[np.asarray(points, float), np.ones(len(points))] @ camera_matrix(cam, width / height)
    ndc = p[:, :2] / p[:, 3:4]
    return np.c_[(ndc[:, 0] + 1) * 0.5 * width, (1 - ndc[:, 1]) * 0.5 * height]
