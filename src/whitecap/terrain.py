"""Terrain: a scene's ground from a 16-bit heightmap or a surface mesh, as a static obstacle.

The ``[terrain]`` section (config.Terrain) becomes two meshes in a cache
(``$WHITECAP_CACHE/terrain``, keyed by the source file's content and the
section's geometry):

- the **collision solid**: the heightfield sampled every ``resolution`` metres
  over the terrain's part of the domain (plus the kernel support), closed by
  vertical sides down to a flat base below the domain floor. It is watertight
  and goes through the obstacle machinery (sim/obstacles.py: SDF grid,
  penalty, projection, density map) like any static ``[[obstacle]]``;
- the **render surface**: the same heightfield sampled every
  ``render_resolution`` metres (finer) over the whole terrain, top surface
  only, drawn with the procedural terrain material (render/terrain.py).

:func:`expand` appends that obstacle (``material = "terrain"``) to
``scene.obstacle`` when a scene is loaded, so every stage that reads obstacles
(solver, diffuse particles, viewer, renderer, run.json) sees the terrain
without a second collision path. A resolved scene.toml already holds the
entry, so loading it again adds nothing.

Heightmap convention: a single-channel 16-bit image (PNG); pixel value 0 is
``height[0]``, 65535 is ``height[1]`` [m]; column 0 is at x = ``lower[0]``, the
last column at x = ``lower[0] + size[0]``; the **top row** is at
y = ``lower[1] + size[1]`` (north up, as an image is viewed from above).
Between pixels heights are a cubic spline of the pixel values.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from .errors import InputError
from .io.atomic import atomic_path
from .resources import cache_dir

TERRAIN_CACHE_VERSION = 1
#: The material name that marks an obstacle made from ``[terrain]``.
TERRAIN_MATERIAL = "terrain"
#: Most vertices a render surface may have (a 2000 × 2000 grid: about 100 MB in Blender).
MAX_RENDER_VERTICES = 4_000_000
#: Most grid points a terrain mesh is sampled on into a heightfield.
MAX_RAYS = 1_000_000


# ============================================================================ heightmaps
def read_heightmap(path: Path, field: str = "terrain.heightmap") -> np.ndarray:
    """A 16-bit single-channel image as heights in [0, 1] (float64, rows top to bottom), or
    InputError in one line naming the file and the field."""
    import imageio.v3 as iio

    if not path.is_file():
        raise InputError(f"{path}: {field}: file not found")
    try:
        img = np.asarray(iio.imread(path))
    except Exception as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise InputError(f"{path}: {field}: not an image ({first})") from None
    if img.ndim == 3 and img.shape[2] in (2, 4):  # grey + alpha, RGBA: the alpha is not a height
        img = img[..., :-1]
    if img.ndim == 3 and img.shape[2] == 3 and (img == img[..., :1]).all():
        img = img[..., 0]  # a grey image stored as RGB
    if img.ndim != 2:
        raise InputError(f"{path}: {field}: expected a single-channel (grayscale) image, got shape {img.shape}")
    if img.dtype != np.uint16:
        bits = 8 * img.dtype.itemsize
        raise InputError(f"{path}: {field}: {'an' if bits == 8 else 'a'} {bits}-bit image ({img.dtype}); "
                         "a heightmap must be a 16-bit grayscale PNG (scripts/make_terrain_assets.py writes one)")
    if min(img.shape) < 2:
        raise InputError(f"{path}: {field}: {img.shape[1]}×{img.shape[0]} pixels; a heightmap needs at least 2×2")
    return img.astype(np.float64) / 65535.0


def smooth_noise(shape: tuple[int, ...], scale: float, rng: np.random.Generator) -> np.ndarray:
    """Value noise of feature size ``scale`` pixels, in about [-1, 1]: Gaussian-filtered white noise,
    wrapped at the edges, for the procedural heightmaps of the example scenes (scripts/make_*_assets.py)."""
    from scipy.ndimage import gaussian_filter

    n = gaussian_filter(rng.standard_normal(shape), scale, mode="wrap")
    return n / (np.abs(n).max() + 1e-12)


def write_heightmap(path: Path, heights: np.ndarray) -> None:
    """Heights in [0, 1] (rows top to bottom) as a 16-bit grayscale PNG."""
    import imageio.v3 as iio

    h = np.clip(np.asarray(heights, np.float64), 0.0, 1.0)
    iio.imwrite(path, np.round(h * 65535.0).astype(np.uint16))


class Heightfield:
    """z(x, y) [m] of a terrain: a cubic spline through a grid of heights."""

    def __init__(self, z: np.ndarray, lower, size):
        """``z``: (rows, cols) heights [m], rows from +y (top) to −y; ``lower``: (x, y) of the
        lower corner; ``size``: (sx, sy) [m]."""
        from scipy.ndimage import spline_filter

        self.z = np.asarray(z, np.float64)
        self.coef = spline_filter(self.z, order=3, mode="nearest")
        self.lower = np.asarray(lower, np.float64)
        self.size = np.asarray(size, np.float64)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        from scipy.ndimage import map_coordinates

        rows, cols = self.z.shape
        c = (np.asarray(x) - self.lower[0]) / self.size[0] * (cols - 1)
        r = (1.0 - (np.asarray(y) - self.lower[1]) / self.size[1]) * (rows - 1)
        return map_coordinates(self.coef, [r.ravel(), c.ravel()], order=3, mode="nearest",
                               prefilter=False).reshape(np.shape(x))


def heightfield_from_mesh(mesh, spacing: float) -> Heightfield:
    """A surface mesh (open or closed) as a heightfield: the highest surface above each point of a
    grid of ``spacing`` over its x-y bounds (each triangle rasterised onto the grid); points no
    triangle covers take the nearest covered point's height."""
    from scipy.ndimage import distance_transform_edt

    V = np.asarray(mesh.vertices, np.float64)
    F = np.asarray(mesh.faces, np.int64)
    lo, hi = V.min(0), V.max(0)
    nx = max(int(np.ceil((hi[0] - lo[0]) / spacing)) + 1, 2)
    ny = max(int(np.ceil((hi[1] - lo[1]) / spacing)) + 1, 2)
    dx, dy = (hi[0] - lo[0]) / (nx - 1), (hi[1] - lo[1]) / (ny - 1)
    z = np.full(nx * ny, -np.inf)
    tri = V[F]  # (m, 3, 3)
    ax = tri[:, :, 0]
    ay = tri[:, :, 1]
    i0 = np.clip(np.ceil((ax.min(1) - lo[0]) / dx - 1e-9), 0, nx - 1).astype(np.int64)
    i1 = np.clip(np.floor((ax.max(1) - lo[0]) / dx + 1e-9), 0, nx - 1).astype(np.int64)
    j0 = np.clip(np.ceil((ay.min(1) - lo[1]) / dy - 1e-9), 0, ny - 1).astype(np.int64)
    j1 = np.clip(np.floor((ay.max(1) - lo[1]) / dy + 1e-9), 0, ny - 1).astype(np.int64)
    wi, wj = np.maximum(i1 - i0 + 1, 0), np.maximum(j1 - j0 + 1, 0)
    count = wi * wj
    chunk = np.searchsorted(np.cumsum(count), np.arange(0, count.sum() + 4_000_000, 4_000_000))
    for a, b in zip(chunk[:-1], chunk[1:] + 1):
        t = np.repeat(np.arange(a, min(b, len(F))), count[a:b])
        if not len(t):
            continue
        k = np.arange(len(t)) - np.repeat(np.cumsum(count[a:b]) - count[a:b], count[a:b])
        gi, gj = i0[t] + k // wj[t], j0[t] + k % wj[t]
        px, py = lo[0] + gi * dx, lo[1] + gj * dy
        p0, p1, p2 = tri[t, 0], tri[t, 1], tri[t, 2]
        d = (p1[:, 1] - p2[:, 1]) * (p0[:, 0] - p2[:, 0]) + (p2[:, 0] - p1[:, 0]) * (p0[:, 1] - p2[:, 1])
        ok = np.abs(d) > 1e-18  # a vertical triangle covers no area seen from above
        d = np.where(ok, d, 1.0)
        l0 = ((p1[:, 1] - p2[:, 1]) * (px - p2[:, 0]) + (p2[:, 0] - p1[:, 0]) * (py - p2[:, 1])) / d
        l1 = ((p2[:, 1] - p0[:, 1]) * (px - p2[:, 0]) + (p0[:, 0] - p2[:, 0]) * (py - p2[:, 1])) / d
        l2 = 1.0 - l0 - l1
        inside = ok & (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
        zz = l0 * p0[:, 2] + l1 * p1[:, 2] + l2 * p2[:, 2]
        np.maximum.at(z, (gi * ny + gj)[inside], zz[inside])
    z = z.reshape(nx, ny).T[::-1]  # rows from +y down, as an image
    miss = ~np.isfinite(z)
    if miss.all():
        raise InputError("terrain.mesh: no triangle covers any area seen from above")
    if miss.any():
        _, (ri, ci) = distance_transform_edt(miss, return_indices=True)
        z = z[ri, ci]
    return Heightfield(z, lo[:2], hi[:2] - lo[:2])


# ============================================================================ meshes
def grid_surface(hf: Heightfield, x0: float, x1: float, y0: float, y1: float, spacing: float):
    """Vertices and faces of the heightfield's surface over [x0, x1] × [y0, y1], sampled about every
    ``spacing`` [m]; faces wound counter-clockwise seen from above (normals up). Also returns the
    grid shape (nx, ny); vertex (i, j) is at index i·ny + j."""
    nx = max(int(np.ceil((x1 - x0) / spacing)) + 1, 2)
    ny = max(int(np.ceil((y1 - y0) / spacing)) + 1, 2)
    X, Y = np.meshgrid(np.linspace(x0, x1, nx), np.linspace(y0, y1, ny), indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), hf(X, Y).ravel()], 1)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
    a = (i * ny + j).ravel()
    b, c, d = a + ny, a + ny + 1, a + 1
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return V, F, (nx, ny)


def closed_solid(V: np.ndarray, F: np.ndarray, shape: tuple[int, int], base: float):
    """The surface (from :func:`grid_surface`) closed by vertical sides down to z = ``base`` and a
    flat bottom: a watertight solid with outward normals."""
    nx, ny = shape
    vid = lambda i, j: i * ny + j  # noqa: E731
    # the border, counter-clockwise seen from above
    ring = np.asarray([vid(i, 0) for i in range(nx - 1)] + [vid(nx - 1, j) for j in range(ny - 1)]
                      + [vid(i, ny - 1) for i in range(nx - 1, 0, -1)] + [vid(0, j) for j in range(ny - 1, 0, -1)])
    n, m = len(V), len(ring)
    bottom = V[ring].copy()
    bottom[:, 2] = base
    centre = np.array([[V[:, 0].min() + V[:, 0].max(), V[:, 1].min() + V[:, 1].max(), 2 * base]]) / 2
    t, t1 = ring, np.roll(ring, -1)
    b = n + np.arange(m)
    b1 = np.roll(b, -1)
    c = np.full(m, n + m)
    sides = np.concatenate([np.stack([t, b, b1], 1), np.stack([t, b1, t1], 1)])
    floor = np.stack([c, b1, b], 1)
    return np.concatenate([V, bottom, centre]), np.concatenate([F, sides, floor])


def _save(path: Path, V: np.ndarray, F: np.ndarray) -> None:
    import trimesh

    with atomic_path(path) as tmp:
        trimesh.Trimesh(V, F, process=False).export(str(tmp), file_type="ply")


# ============================================================================ the scene
def source_of(scene, source: str = "scene") -> tuple[Path, str]:
    """The terrain's source file and its field name; InputError when neither or both are set."""
    t = scene.terrain
    if (t.heightmap is None) == (t.mesh is None):
        raise InputError(f"{source}: terrain: give exactly one of 'heightmap' and 'mesh'")
    field = "terrain.heightmap" if t.heightmap is not None else "terrain.mesh"
    path = scene.resolve(t.heightmap if t.heightmap is not None else t.mesh)
    if not path.is_file():
        raise InputError(f"{source}: {field}: file not found: {path}")
    return path, field


def heightfield(scene, source: str = "scene") -> Heightfield:
    """The terrain's heightfield in world coordinates [m]."""
    t = scene.terrain
    path, field = source_of(scene, source)
    if t.heightmap is not None:
        h = read_heightmap(path, field)
        z0, z1 = t.height if t.height is not None else default_height(scene)
        lower = t.lower if t.lower is not None else scene.domain.lower[:2]
        if t.size is not None:
            size = t.size
        else:
            size = [u - lo for lo, u in zip(scene.domain.lower[:2], scene.domain.upper[:2])]
        return Heightfield(z0 + h * (z1 - z0), lower, size)
    import trimesh

    try:
        m = trimesh.load(str(path), force="mesh")
    except Exception as exc:
        first = str(exc).splitlines()[0] if str(exc) else exc
        raise InputError(f"{path}: {field}: not a readable mesh ({first})") from None
    if m is None or len(getattr(m, "faces", [])) == 0:
        raise InputError(f"{path}: {field}: the mesh is empty (no triangles)")
    lo, hi = m.bounds
    rays = np.prod((hi[:2] - lo[:2]) / render_spacing(scene) + 1)
    return heightfield_from_mesh(m, render_spacing(scene) * max(1.0, float(np.sqrt(rays / MAX_RAYS))))


def default_height(scene) -> list[float]:
    """Without ``height``: from the domain floor to a quarter of the domain's height above it."""
    lo, hi = scene.domain.lower[2], scene.domain.upper[2]
    return [lo, lo + 0.25 * (hi - lo)]


def collision_spacing(scene) -> float:
    t = scene.terrain
    return t.resolution if t.resolution is not None else 2.0 * scene.solver.particle_radius


def render_spacing(scene) -> float:
    t = scene.terrain
    return t.render_resolution if t.render_resolution is not None else collision_spacing(scene) / 4.0


def meshes(scene, source: str = "scene") -> tuple[Path, Path]:
    """The collision solid and the render surface of ``scene.terrain`` (cached): their paths."""
    t = scene.terrain
    path, field = source_of(scene, source)
    r = scene.solver.particle_radius
    geometry = t.model_dump(include={"height", "lower", "size", "resolution", "render_resolution", "base"})
    key = hashlib.sha256(path.read_bytes() + json.dumps(
        [geometry, field, scene.domain.lower, scene.domain.upper, r, scene.solver.kernel_support,
         TERRAIN_CACHE_VERSION]).encode()).hexdigest()[:32]
    folder = cache_dir("terrain")
    col, ren = folder / f"{key}_collision.ply", folder / f"{key}_render.ply"
    if col.is_file() and ren.is_file():
        return col, ren
    hf = heightfield(scene, source)
    tx0, ty0 = hf.lower
    tx1, ty1 = hf.lower + hf.size
    # The collision solid covers the terrain only where the fluid can reach it: the domain grown
    # by the kernel support and two SDF cells, so the SDF grid stays the domain's size.
    pad = (scene.solver.kernel_support + 2.0) * r
    lo, hi = np.array(scene.domain.lower) - pad, np.array(scene.domain.upper) + pad
    x0, x1, y0, y1 = max(tx0, lo[0]), min(tx1, hi[0]), max(ty0, lo[1]), min(ty1, hi[1])
    if x1 <= x0 or y1 <= y0:
        raise InputError(f"{source}: terrain: it spans x {tx0:g}..{tx1:g}, y {ty0:g}..{ty1:g}, "
                         f"outside the domain {scene.domain.lower}..{scene.domain.upper} (terrain.lower, terrain.size)")
    V, F, shape = grid_surface(hf, x0, x1, y0, y1, collision_spacing(scene))
    zmin = float(V[:, 2].min())
    base = t.base if t.base is not None else min(zmin, scene.domain.lower[2]) - pad
    if base >= zmin:
        raise InputError(f"{source}: terrain.base: {base:g} m is not below the terrain's lowest point {zmin:g} m")
    Vs, Fs = closed_solid(V, F, shape, base)
    ds = render_spacing(scene)
    count = (np.ceil((tx1 - tx0) / ds) + 1) * (np.ceil((ty1 - ty0) / ds) + 1)
    if count > MAX_RENDER_VERTICES:
        raise InputError(f"{source}: terrain.render_resolution: {ds:g} m gives {count:,.0f} vertices over "
                         f"{tx1 - tx0:g} × {ty1 - ty0:g} m, more than {MAX_RENDER_VERTICES:,}; make it coarser")
    Vr, Fr, _ = grid_surface(hf, tx0, tx1, ty0, ty1, ds)
    _save(col, Vs, Fs)
    _save(ren, Vr, Fr)
    return col, ren


def water_level(scene) -> float:
    """The still water line the wet sand reaches up to: ``terrain.water_level``, else the top of the
    highest fluid block, else the domain floor."""
    t = scene.terrain
    if t.water_level is not None:
        return t.water_level
    tops = [b.bounds()[1][2] for b in scene.fluid]
    return max(tops) if tops else scene.domain.lower[2]


def expand(scene, source: str = "scene") -> None:
    """Append the terrain's static obstacle to ``scene.obstacle`` (once) and settle its water level."""
    from .config import Obstacle

    if scene.terrain is None or any(o.material == TERRAIN_MATERIAL for o in scene.obstacle):
        return
    t = scene.terrain
    col, ren = meshes(scene, source)
    if t.water_level is None:
        t.water_level = water_level(scene)
    scene.obstacle = [*scene.obstacle, Obstacle(
        mesh=str(col), render_mesh=str(ren), material=TERRAIN_MATERIAL, friction=t.friction,
        sdf_resolution=t.sdf_resolution, color=[0.55, 0.45, 0.3])]
