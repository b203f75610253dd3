"""Server-side point splatting for the browser viewer: particles drawn into an RGB
image and a depth image for one camera, as GGUI draws them (shaded spheres).

The browser viewer sends these pictures instead of the points when a run is large
(:mod:`.web`, ``--points server``): where WebGL runs in software, drawing 100k points
costs the browser far more than decoding one JPEG. The depth image lets viser's page
composite the picture with the objects it still draws itself (domain box, obstacles,
surface mesh): viser reads depth as the distance along the camera's view axis in
scene units [m] (``viewZToPerspectiveDepth(-depth)`` in its client's background
shader), which is what :func:`render` writes.

Camera convention (viser's ``client.camera``, OpenCV's): ``wxyz`` rotates camera
axes to world axes, the camera's x points right, y down and z forward (into the
picture); ``fov`` is the vertical field of view [rad]. A point p in camera
coordinates lands at pixel (W/2 + f·p_x/p_z, H/2 + f·p_y/p_z) with f = H / (2 tan(fov/2)),
in continuous pixel coordinates where pixel (col, row) covers [col, col+1) × [row, row+1).

Each particle i with world centre x_i and radius r_i covers the disc of projected
radius ρ_i = f·r_i / z_i around its projected centre (at least the pixel that holds the
centre). The disc is a sphere seen from the front: at normalised offset d from the
centre the surface is nearer by r_i·sqrt(1 - d²), and its normal gives Lambert shading
under GGUI's lights (:data:`AMBIENT`, :data:`DIFFUSE`). The nearest surface wins per
pixel: one pass packs (depth bits, particle index) into a 64-bit key and keeps the
minimum with an atomic (positive floats order as their bit patterns), a second pass
shades each pixel from the particle that won it. Two kernels, no sorting, no locks.

Taichi kernels run on the process's Taichi runtime (CPU, or CUDA under a live CUDA
simulation), in the project's style; NumPy cannot scatter a per-pixel minimum without
``np.minimum.at``, which is about 50× slower than these kernels for 100k points.
"""

import io
import math
from typing import Any

import numpy as np
import taichi as ti

from ..geometry import unit_quat_matrix

# GGUI's lights (view/draw.py: ambient 0.45, one point light 0.7 above the eye).
AMBIENT = 0.45
DIFFUSE = 0.7
# Direction towards the light in camera coordinates (x right, y down, z forward): from the
# eye and above it, as GGUI's point light at eye + extent·up, normalised below.
LIGHT_DIR = (0.0, -0.6, -1.0)
MIN_PIXEL_RADIUS = 0.75  # a particle smaller than this on screen still covers the pixel of its centre [px]
NEAR = 1e-3  # particles nearer the eye than this along the view axis are not drawn [m]
EMPTY_KEY = np.iinfo(np.int64).max
FAR_DEPTH = 1.0e4  # depth written where no particle is [m] (viser clips it to its largest, 167.8 m)

# viser's depth image (its client's background shader): 24-bit fixed point in units of 1e-5 m in
# a PNG's red (high byte), green and blue (low byte) channels, up to 167.77 m.
VISER_DEPTH_UNIT_M = 1e-5
VISER_DEPTH_MAX = 2**24 - 1
# Depth sent in steps of 256 units (2.56 mm): the low byte is then always zero, which halves
# the PNG (80 kB instead of 190 kB for 100k particles at 640x480) and its encoding time. Half a
# step (1.3 mm) is well under a particle radius, the scale at which fluid meets an obstacle.
DEPTH_STEP_UNITS = 256
PNG_COMPRESS_LEVEL = 1  # zlib level of the depth PNG: 1 is 2.5x faster than 6 for 15 % more bytes

_L = np.asarray(LIGHT_DIR, np.float64) / np.linalg.norm(LIGHT_DIR)
_LIGHT = tuple(float(c) for c in _L)

# Pure-Taichi bodies need the runtime; compile once per process on first use.
# The kernels' argument types (typed Any to a type checker: taichi's annotations are not Python types).
_cam_t: Any = ti.types.ndarray(dtype=ti.f32, ndim=1)  # 12 numbers: R (row-major, camera->world), eye
_vec3_t: Any = ti.types.ndarray(dtype=ti.math.vec3, ndim=1)
_f32_t: Any = ti.types.ndarray(dtype=ti.f32, ndim=1)
_key_t: Any = ti.types.ndarray(dtype=ti.i64, ndim=2)
_rgb_t: Any = ti.types.ndarray(dtype=ti.u8, ndim=3)
_depth_t: Any = ti.types.ndarray(dtype=ti.f32, ndim=2)
_template: Any = ti.template()


@ti.func
def _to_camera(cam: _template, x):
    """World point x -> camera coordinates p = Rᵀ (x - eye)."""
    d = x - ti.Vector([cam[9], cam[10], cam[11]])
    return ti.Vector([cam[0] * d[0] + cam[3] * d[1] + cam[6] * d[2],
                      cam[1] * d[0] + cam[4] * d[1] + cam[7] * d[2],
                      cam[2] * d[0] + cam[5] * d[1] + cam[8] * d[2]])


@ti.kernel
def splat_nearest_sphere(pos: _vec3_t, rad: _f32_t, cam: _cam_t, focal: ti.f32, key: _key_t):
    """For every pixel, the nearest sphere surface over it: key = (bits(z) << 32) | i, where
    z = z_i - r_i sqrt(1 - d²) is the surface's distance along the view axis and d the
    pixel centre's offset from the projected centre in units of ρ_i = f r_i / z_i."""
    H, W = key.shape[0], key.shape[1]
    for i in range(pos.shape[0]):
        p = _to_camera(cam, pos[i])
        if p[2] > NEAR:
            u = 0.5 * W + focal * p[0] / p[2]
            v = 0.5 * H + focal * p[1] / p[2]
            rho = ti.max(focal * rad[i] / p[2], MIN_PIXEL_RADIUS)
            c0 = ti.max(ti.cast(ti.floor(u - rho), ti.i32), 0)
            c1 = ti.min(ti.cast(ti.floor(u + rho), ti.i32), W - 1)
            r0 = ti.max(ti.cast(ti.floor(v - rho), ti.i32), 0)
            r1 = ti.min(ti.cast(ti.floor(v + rho), ti.i32), H - 1)
            for row in range(r0, r1 + 1):
                for col in range(c0, c1 + 1):
                    du = (col + 0.5 - u) / rho
                    dv = (row + 0.5 - v) / rho
                    d2 = du * du + dv * dv
                    if d2 < 1.0:
                        z = p[2] - rad[i] * ti.sqrt(1.0 - d2)
                        k = (ti.cast(ti.bit_cast(ti.max(z, 0.0), ti.i32), ti.i64) << 32) | ti.cast(i, ti.i64)
                        ti.atomic_min(key[row, col], k)


@ti.kernel
def shade_sphere_pixels(pos: _vec3_t, rad: _f32_t, col: _vec3_t, cam: _cam_t, focal: ti.f32, key: _key_t,
                        bg: ti.math.vec3, rgb: _rgb_t, depth: _depth_t):
    """Each pixel's colour and depth from the sphere that won it: c_i (A + D max(n·l, 0)) with
    n the sphere normal n = (du, dv, -sqrt(1 - d²)) (camera coordinates) and l the light
    direction; the background colour and FAR_DEPTH where no particle is."""
    H, W = key.shape[0], key.shape[1]
    light = ti.Vector([_LIGHT[0], _LIGHT[1], _LIGHT[2]])
    for row, c in ti.ndrange(H, W):
        k = key[row, c]
        out = bg
        z = FAR_DEPTH
        if k != ti.i64(EMPTY_KEY):
            hi = k >> 32
            i = ti.cast(k - (hi << 32), ti.i32)
            z = ti.bit_cast(ti.cast(hi, ti.i32), ti.f32)
            p = _to_camera(cam, pos[i])
            rho = ti.max(focal * rad[i] / p[2], MIN_PIXEL_RADIUS)
            du = (c + 0.5 - (0.5 * W + focal * p[0] / p[2])) / rho
            dv = (row + 0.5 - (0.5 * H + focal * p[1] / p[2])) / rho
            nz = -ti.sqrt(ti.max(1.0 - du * du - dv * dv, 0.0))
            lam = ti.max(du * light[0] + dv * light[1] + nz * light[2], 0.0)
            out = col[i] * (AMBIENT + DIFFUSE * lam)
        for ch in ti.static(range(3)):
            rgb[row, c, ch] = ti.cast(ti.min(ti.max(out[ch] * 255.0 + 0.5, 0.0), 255.0), ti.u8)
        depth[row, c] = z


def camera_rotation(wxyz) -> np.ndarray:
    """The camera-to-world rotation of viser's quaternion (w, x, y, z): columns are the
    camera's right, down and forward axes in world coordinates (the bodies' quaternion
    matrix, after normalising)."""
    return unit_quat_matrix(wxyz)


def focal_px(fov: float, height: int) -> float:
    """Focal length in pixels for a vertical field of view ``fov`` [rad] over ``height`` px."""
    return 0.5 * height / math.tan(0.5 * fov)


class Splatter:
    """Draws sets of spheres for cameras; holds the per-size buffers between pictures."""

    def __init__(self):
        self._key = None

    def render(self, positions, radii, colors, wxyz, eye, fov: float, size: tuple[int, int],
               background=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
        """An (H, W, 3) uint8 picture and an (H, W) float32 depth [m along the view axis]
        of spheres at ``positions`` (N, 3) [m] with ``radii`` (N,) [m] and ``colors`` (N, 3)
        in [0, 1], seen by the camera (viser's convention, see the module docstring)
        over ``size`` = (width, height) px. ``background`` fills pixels without particles."""
        from ..sim import runtime

        runtime.init(runtime.current() or "cpu")
        W, H = int(size[0]), int(size[1])
        if self._key is None or self._key.shape != (H, W):
            self._key = np.empty((H, W), np.int64)
        self._key.fill(EMPTY_KEY)
        rgb = np.empty((H, W, 3), np.uint8)
        depth = np.empty((H, W), np.float32)
        cam = np.concatenate([camera_rotation(wxyz).ravel(), np.asarray(eye, float)]).astype(np.float32)
        f = focal_px(fov, H)
        pos = np.ascontiguousarray(positions, np.float32).reshape(-1, 3)
        rad = np.ascontiguousarray(np.broadcast_to(np.asarray(radii, np.float32), (len(pos),)))
        col = np.ascontiguousarray(colors, np.float32).reshape(-1, 3)
        if len(pos):
            splat_nearest_sphere(pos, rad, cam, f, self._key)
        else:
            pos, rad, col = np.zeros((1, 3), np.float32), np.zeros(1, np.float32), np.zeros((1, 3), np.float32)
        shade_sphere_pixels(pos, rad, col, cam, f, self._key, ti.Vector([float(c) for c in background]), rgb, depth)
        return rgb, depth


def encode_depth_png(depth: np.ndarray) -> bytes:
    """The (H, W) depth [m along the view axis] as the PNG viser's page reads (module
    constants): an RGB PNG, red the high byte. (viser's own ``set_background_image(depth=)``
    writes the same numbers as a 4-channel PNG at zlib's default level: 57 ms and 190 kB
    per 640x480 picture of 100k particles here, against 9 ms and 80 kB for this.)"""
    from PIL import Image

    steps = np.minimum(np.asarray(depth, np.float32) * (1.0 / (VISER_DEPTH_UNIT_M * DEPTH_STEP_UNITS)) + 0.5,
                       VISER_DEPTH_MAX // DEPTH_STEP_UNITS).astype(np.uint32)
    units = steps * DEPTH_STEP_UNITS
    a = np.empty((*units.shape, 3), np.uint8)
    a[..., 0] = units >> 16
    a[..., 1] = (units >> 8) & 0xFF
    a[..., 2] = units & 0xFF
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=int(quality))
    return buf.getvalue()
