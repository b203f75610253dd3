"""Make the assets of scenes/coast.toml: a beach, a rubble-mound breakwater of tetrapods, rocks and a
wave maker (no downloads).

    python scripts/make_coast_assets.py

writes into scenes/assets/ (all in world coordinates, metres, z up; the scene places them as they are):

- ``coast.png``: the 16-bit heightmap of the coast (TERRAIN_LOWER, TERRAIN_SIZE, TERRAIN_HEIGHT): a flat
  sea bed at the deep end (x < BEACH_TOE), a concave sandy beach rising out of the water (the still water
  line wanders about SHORE_X along y), a berm and grassy dunes; the sea bed drops away beyond the domain
  toward the horizon.
- ``coast_unit.ply``: one armour unit, a tetrapod (four tapered, rounded legs from a centre toward the
  corners of a tetrahedron) of height about UNIT_SIZE: the zero level set of its signed distance
  (a union of round cones), by marching cubes (libigl), so it is watertight by construction.
- ``coast_breakwater_render.ply``: the breakwater as drawn: a trapezoid core of quarry run (a closed
  prism) under a double layer of tetrapods, copies of ``coast_unit.ply`` placed on the core's faces
  at random turns and a jittered spacing, with a round head at its seaward end (y = HEAD_Y). It runs
  on past the domain's y = 0 side (only drawn there), so it does not end at the domain's edge.
- ``coast_breakwater.ply``: its collision solid inside the domain: the highest surface of the
  render mesh (core and units) seen from above, sampled every COLLISION_SPACING and closed down to
  below the sea bed (whitecap.terrain's heightfield tools). The fluid meets the armour's outer
  shape; it does not seep through the voids between the units (they are below the resolution).
- ``coast_rocks_render.ply`` / ``coast_rocks.ply``: boulders beside the breakwater's head and on the
  beach next to it: noisy icospheres (drawn), and their convex hulls (collision; disjoint closed shells).
- ``coast_quay.png``: a quay by the sea (QUAY_*), the setting of the README's recipe for an imported
  DualSPHysics case: a flat concrete apron, a rock-armoured quay wall down to the sea bed, grass inland.
- ``coast_sky.exr``: the storm sky, an equirectangular environment image (value noise clouds, a pale
  horizon band, the sun a bright patch behind the clouds), written through Blender's Python module.
- ``coast_wavemaker.ply``: the piston paddle, a board wider than the domain; ``coast_wavemaker_render.ply``
  draws it as nothing (a 1 cm cube under the sea bed): it stands in for the swell from the open sea.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from whitecap.terrain import (  # noqa: E402
    closed_solid,
    grid_surface,
    heightfield_from_mesh,
    smooth_noise,
    write_heightmap,
)

ASSETS = ROOT / "scenes" / "assets"

# Scene geometry, shared with scenes/coast.toml and tests/test_coast_scene.py [m].
DOMAIN_LOWER = (0.0, 0.0, 0.0)
DOMAIN_UPPER = (3.0, 1.4, 0.7)
SEA_LEVEL = 0.25                         # still water
TERRAIN_LOWER = (-3.0, -3.0)
TERRAIN_SIZE = (9.0, 7.2)
TERRAIN_HEIGHT = (-0.15, 0.85)           # heights of pixel values 0 and 65535
TERRAIN_PX = (720, 576)                  # heightmap width, height [px]: 1.25 cm a pixel
BEACH_TOE = 1.0                          # x where the beach leaves the flat sea bed (z = 0)
SHORE_X = 2.45                           # x where the beach crosses the still water line (about)
BERM_X, BERM_Z = 3.25, 0.42              # the top of the beach
# The breakwater: a shore-parallel rubble mound along y, its crest line at x = CREST_X.
CREST_X = 1.75
CREST_Z = 0.37                           # the armour's crest, 12 cm above the still water
CREST_HALF = 0.06                        # half the crest's width (of the core)
SLOPE = 1.2                              # side slopes, horizontal over vertical (1:1.2)
HEAD_Y = 0.5                             # the seaward end (the round head), inside the domain
ROOT_Y = -0.6                            # the breakwater runs on beyond the domain to here (drawn only)
UNIT_SIZE = 0.09                         # a tetrapod's overall height
UNIT_SPACING = 0.068                     # mean spacing of units on the core's faces
COLLISION_SPACING = 0.008                # collision heightfield spacing (r = 8 mm in the scene)
PADDLE_X = 0.2                           # the wave maker's rest position (its centre)


# --------------------------------------------------------------------------- noise
# --------------------------------------------------------------------------- terrain
def beach_z(x: np.ndarray) -> np.ndarray:
    """The beach's profile across the shore [m]: flat sea bed, a concave beach up to the berm,
    and a sea bed that falls away beyond the domain's deep end (it is under the open sea)."""
    s = np.clip((x - BEACH_TOE) / (BERM_X - BEACH_TOE), 0.0, 1.0)
    z = BERM_Z * s ** 1.25
    return z - 0.12 * np.clip(-x / 2.0, 0.0, 1.0)


def coast_heights(seed: int = 5) -> np.ndarray:
    """Heights in [0, 1] of the heightmap (rows from +y down)."""
    rng = np.random.default_rng(seed)
    w, h = TERRAIN_PX
    x = TERRAIN_LOWER[0] + np.linspace(0, 1, w)[None, :] * TERRAIN_SIZE[0]
    y = TERRAIN_LOWER[1] + np.linspace(1, 0, h)[:, None] * TERRAIN_SIZE[1]
    x = np.broadcast_to(x, (h, w))
    y = np.broadcast_to(y, (h, w))
    # The shore wanders along y (a bay beyond the domain's +y side, a point beyond y = 0).
    wander = 0.25 * smooth_noise((h, 1), h / 6, rng) + 0.18 * np.tanh((y - 2.2) / 0.8) - 0.1 * np.tanh((-y - 1.0) / 0.6)
    inside = (x > -0.2) & (x < 3.2) & (y > -0.2) & (y < 1.4)   # keep the domain's beach close to the plan
    wander = np.where(inside, 0.05 * wander, wander)
    z = beach_z(x - wander)
    # Dunes behind the berm, with grass on them (scene: grass_above).
    dune = np.clip((x - wander - BERM_X) / 0.6, 0, 1) * (0.1 + 0.08 * smooth_noise((h, w), w / 14, rng))
    z = z + np.maximum(dune, 0.0)
    z = z + 0.01 * smooth_noise((h, w), w / 30, rng) * np.clip((x - BEACH_TOE) / 0.5, 0, 1)  # undulation
    z = z + 0.002 * np.sin(2 * np.pi * ((x - wander) * 18 + 1.5 * smooth_noise((h, w), w / 25, rng)))  # ripples
    lo, hi = TERRAIN_HEIGHT
    return np.clip((z - lo) / (hi - lo), 0.0, 1.0)


def terrain_z(x, y) -> np.ndarray:
    """The beach's height at (x, y) inside the domain, as the heightmap makes it (without its noise)."""
    return beach_z(np.asarray(x, float))


# --------------------------------------------------------------------------- armour units
#: A tetrapod's legs: unit vectors from its centre toward the corners of a regular tetrahedron.
TETRA = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / np.sqrt(3.0)


def round_cone_sdf(p: np.ndarray, a: np.ndarray, b: np.ndarray, ra: float, rb: float) -> np.ndarray:
    """Signed distance (approximate outside the cone's sides, exact enough for a level set) of
    points p (n, 3) to the round cone from a (radius ra) to b (radius rb)."""
    ab = b - a
    L = np.linalg.norm(ab)
    t = np.clip((p - a) @ ab / (L * L), 0.0, 1.0)
    q = a + t[:, None] * ab
    return np.linalg.norm(p - q, axis=1) - (ra + (rb - ra) * t)


def tetrapod(size: float = UNIT_SIZE, cells: int = 17) -> trimesh.Trimesh:
    """A tetrapod of overall height about ``size``, centred on its centre of mass, one leg up:
    the zero level set of the union of four round cones, meshed by marching cubes (watertight)."""
    import igl

    # Leg length from the centre to a tip's centre: a tetrapod stands on three legs with the fourth
    # up, so its height is the leg length times (1 + 1/3) plus the rounded tips (radius r1) at both ends.
    leg = size / (4.0 / 3.0 + 2 * 0.22)
    r0, r1 = 0.34 * leg, 0.22 * leg
    up = TETRA[0]
    R = trimesh.geometry.align_vectors(up, [0, 0, 1])[:3, :3]
    legs = TETRA @ R.T
    ext = leg + r0
    g = np.linspace(-ext, ext, cells)
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    # libigl wants S(x + y*nx + z*nx*ny): x fastest.
    P = np.stack([X.transpose(2, 1, 0).ravel(), Y.transpose(2, 1, 0).ravel(), Z.transpose(2, 1, 0).ravel()], 1)
    d = np.min([round_cone_sdf(P, np.zeros(3), leg * u, r0, r1) for u in legs], axis=0)
    d = np.where(np.max(np.abs(P), 1) > ext - 1e-9, np.maximum(d, 1e-3), d)  # closed at the grid's border
    V, F, _ = igl.marching_cubes(d, P, cells, cells, cells, 0.0)
    m = trimesh.Trimesh(V, F, process=True)
    if m.volume < 0:
        m.invert()
    m.apply_translation(-m.center_mass)
    return m


def _rot(rng: np.random.Generator) -> np.ndarray:
    """A random rotation (uniform on SO(3))."""
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    return trimesh.transformations.quaternion_matrix(q)[:3, :3]


def core_profile_half(z: np.ndarray) -> np.ndarray:
    """Half-width of the core at height z [m]: the crest, widening down the side slopes."""
    return CREST_HALF + SLOPE * (CREST_Z - UNIT_SIZE * 0.7 - z)


def core_mesh(y0: float, y1: float, bed: float, n: int = 48) -> trimesh.Trimesh:
    """The core: a trapezoid prism along y from y0 to y1 with a half-cone head at y1, as the convex hull
    of its sections (watertight), top at CREST_Z - 0.7 units, bottom at ``bed``."""
    top = CREST_Z - UNIT_SIZE * 0.7
    hb, ht = core_profile_half(np.array(bed)), CREST_HALF
    pts = []
    for y in (y0, y1):
        pts += [[CREST_X - hb, y, bed], [CREST_X + hb, y, bed], [CREST_X - ht, y, top], [CREST_X + ht, y, top]]
    a = np.linspace(0, np.pi, n)
    for rad, z in ((hb, bed), (ht, top)):  # the round head: half a cone frustum beyond y1
        pts += [[CREST_X - rad * np.cos(t), y1 + rad * np.sin(t), z] for t in a]
    return trimesh.convex.convex_hull(np.array(pts))


def armour(core: trimesh.Trimesh, rng: np.random.Generator, unit: trimesh.Trimesh, layers: int = 2):
    """Copies of ``unit`` over the core's surface above the sea bed: per layer, points spread on the
    surface at about UNIT_SPACING (a jittered grid over the faces by area), each unit centred a layer
    out along the surface normal, at a random turn. Returns a list of 4×4 placements."""
    placements = []
    normals = core.face_normals
    areas = core.area_faces
    keep = normals[:, 2] > -0.5                          # not the bottom
    for layer in range(layers):
        total = areas[keep].sum()
        n = int(total / UNIT_SPACING ** 2)
        # Three times the draws, thinned to points at least 0.92 spacings apart (trimesh says how many it kept).
        pts, fid = trimesh.sample.sample_surface_even(core, n * 3, radius=UNIT_SPACING * 0.92,
                                                      seed=int(rng.integers(1 << 30)))
        ok = keep[fid]
        pts, fid = pts[ok], fid[ok]
        offset = UNIT_SIZE * (0.28 + 0.42 * layer)
        for p, f in zip(pts, fid):
            c = p + normals[f] * offset + rng.normal(0, 0.006, 3)
            if c[2] < -0.02:
                continue
            M = np.eye(4)
            M[:3, :3] = _rot(rng)
            M[:3, 3] = c
            placements.append(M)
    return placements


def breakwater(rng: np.random.Generator):
    """The render mesh (core plus units) and the unit."""
    unit = tetrapod()
    bed = float(terrain_z(CREST_X - 0.3, 0.0)) - 0.03
    core = core_mesh(ROOT_Y, HEAD_Y, bed)
    places = armour(core, rng, unit)
    V = [core.vertices]
    F = [core.faces]
    nv = len(core.vertices)
    for M in places:
        V.append(unit.vertices @ M[:3, :3].T + M[:3, 3])
        F.append(unit.faces + nv)
        nv += len(unit.vertices)
    render = trimesh.Trimesh(np.concatenate(V), np.concatenate(F), process=False)
    return render, unit, core, len(places)


def collision_solid(render: trimesh.Trimesh, x0: float, x1: float, y0: float, y1: float, base: float):
    """The highest surface of ``render`` over [x0, x1] × [y0, y1] (a ground plane at ``floor`` where
    it covers nothing), closed down to ``base``: a watertight solid."""
    floor = base + 0.01
    plane = trimesh.Trimesh([[x0, y0, floor], [x1, y0, floor], [x1, y1, floor], [x0, y1, floor]],
                            [[0, 1, 2], [0, 2, 3]], process=False)
    hf = heightfield_from_mesh(trimesh.util.concatenate([render, plane]), COLLISION_SPACING)
    V, F, shape = grid_surface(hf, x0, x1, y0, y1, COLLISION_SPACING)
    Vs, Fs = closed_solid(V, F, shape, base)
    return trimesh.Trimesh(Vs, Fs, process=True)


# --------------------------------------------------------------------------- rocks
#: Boulders: (x, y, radius [m]); their z is set so that about a third is buried.
ROCKS = [(2.02, 1.0, 0.065), (2.17, 0.94, 0.045), (2.32, 1.13, 0.055), (2.12, 1.26, 0.04), (2.5, 1.03, 0.05),
         (1.62, 1.08, 0.04)]


def rock(rng: np.random.Generator, radius: float, subdiv: int = 3) -> trimesh.Trimesh:
    """A boulder: an icosphere squashed a little and displaced by noise (watertight)."""
    m = trimesh.creation.icosphere(subdivisions=subdiv, radius=1.0)
    v = m.vertices
    n = np.zeros(len(v))
    for k, amp in ((1.5, 0.22), (3.5, 0.09), (8.0, 0.035)):
        d = rng.standard_normal(3)
        d /= np.linalg.norm(d)
        ph = rng.uniform(0, 2 * np.pi, 3)
        n += amp * (np.sin(k * v @ d + ph[0]) + 0.5 * np.sin(k * 1.7 * v[:, [1, 2, 0]] @ d + ph[1]))
    v = v * (1.0 + n)[:, None] * radius * np.array([1.15, 0.95, 0.7])
    m = trimesh.Trimesh(v @ _rot_z(rng.uniform(0, np.pi)).T, m.faces, process=False)
    return m


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rocks(rng: np.random.Generator):
    render, collision = [], []
    for x, y, rad in ROCKS:
        m = rock(rng, rad)
        m.apply_translation([x, y, float(terrain_z(x, y)) + 0.2 * rad])  # about a third buried
        render.append(m)
        collision.append(trimesh.convex.convex_hull(m.vertices))
    return trimesh.util.concatenate(render), trimesh.util.concatenate(collision)


# --------------------------------------------------------------------------- a quay (README's recipe)
#: The quay of the README's recipe that sets an imported DualSPHysics case (the shared dam break, its
#: tank from x = 0 to 1.6 m, its floor at z = -0.01 m) by the sea: a flat concrete apron a few mm above
#: the tank's floor, a rock-armoured quay wall down to the sea bed beyond x = QUAY_EDGE, grass inland.
QUAY_LOWER, QUAY_SIZE, QUAY_HEIGHT, QUAY_PX = (-6.0, -5.0), (14.0, 11.0), (-1.0, 0.3), (560, 440)
QUAY_TOP, QUAY_EDGE, QUAY_SEA_LEVEL = -0.005, -2.2, -0.45


def quay_heights(seed: int = 3) -> np.ndarray:
    """Heights in [0, 1] of the quay's heightmap (rows from +y down)."""
    rng = np.random.default_rng(seed)
    w, h = QUAY_PX
    x = QUAY_LOWER[0] + np.linspace(0, 1, w)[None, :] * QUAY_SIZE[0]
    y = QUAY_LOWER[1] + np.linspace(1, 0, h)[:, None] * QUAY_SIZE[1]
    x, y = np.broadcast_to(x, (h, w)), np.broadcast_to(y, (h, w))
    edge = QUAY_EDGE + 0.15 * np.sin(y * 0.35) * np.clip(np.abs(y - 0.3) - 2.5, 0, 1)
    wall = np.clip((edge - x) / 0.5, 0, 1)                           # the armoured slope, 0.5 m wide
    z = QUAY_TOP - (QUAY_TOP + 0.9) * wall ** 1.5 + 0.06 * smooth_noise((h, w), 3, rng) * wall * (1 - wall) * 4
    z = z + 0.25 * np.clip((x - 4.0) / 1.5, 0, 1) ** 2                # a grassy bank inland
    lo, hi = QUAY_HEIGHT
    return np.clip((z - lo) / (hi - lo), 0.0, 1.0)


# --------------------------------------------------------------------------- sky
SKY_PX = (1024, 512)                     # the storm sky's equirectangular image, width × height
SUN_DIR = (-0.8, 0.45, 0.35)             # where the sun glows through the clouds (toward the sea, low)


def fbm(u: np.ndarray, v: np.ndarray, rng: np.random.Generator, octaves: int = 6) -> np.ndarray:
    """Fractal value noise at (u, v) (any shape), in about [0, 1]: octaves of bilinearly sampled random
    lattices, each twice as fine and half as strong."""
    from scipy.ndimage import map_coordinates

    out = np.zeros_like(u)
    amp, total = 1.0, 0.0
    for k in range(octaves):
        n = 8 * 2 ** k
        lattice = rng.random((n, n))
        out += amp * map_coordinates(lattice, [(v * n) % n, (u * n) % n], order=1, mode="grid-wrap")
        total += amp
        amp *= 0.5
    return out / total


def storm_sky(seed: int = 11) -> np.ndarray:
    """A storm sky (linear RGB radiance, rows from the zenith down, equirectangular: azimuth along x as
    Blender's Environment Texture maps it): low, dark, broken cloud over a paler band at the horizon,
    a brighter patch where the sun is behind the clouds, and a dim grey below the horizon."""
    rng = np.random.default_rng(seed)
    w, h = SKY_PX
    az = (np.arange(w) + 0.5) / w * 2 * np.pi - np.pi          # Blender: u = atan2(y, -x)/(2π) + 0.5
    el = np.pi / 2 - (np.arange(h) + 0.5) / h * np.pi
    AZ, EL = np.meshgrid(az, el)
    d = np.stack([-np.cos(EL) * np.cos(AZ), np.cos(EL) * np.sin(AZ), np.sin(EL)], -1)
    # Clouds: a layer seen in perspective, noise over its plane (x/z, y/z); toward the horizon they
    # fade into a pale haze (and the noise, ever finer there, is not drawn).
    up = np.maximum(d[..., 2], 0.05)
    px, py = d[..., 0] / up * 0.35, d[..., 1] / up * 0.35
    wind = fbm(px * 0.5 + 0.3, py * 0.5, rng, 3)
    cloud = fbm(px + 0.5 * wind, py * 1.8 + 0.5 * wind, rng, 6)
    haze = np.exp(-np.clip(d[..., 2], 0, 1) / 0.1)
    cover = np.clip((cloud - 0.45) / 0.14, 0, 1) * (1 - haze)
    sun = np.asarray(SUN_DIR, float) / np.linalg.norm(SUN_DIR)
    glow = np.clip(d @ sun, 0, 1)
    thin = np.array([0.34, 0.37, 0.40])                        # the lighter cloud between the dark masses
    thick = np.array([0.085, 0.09, 0.1])                      # rain-heavy cloud
    pale = np.array([0.42, 0.43, 0.44])                       # haze at the horizon
    sky = thin * (1 - cover[..., None]) + thick * cover[..., None]
    sky = sky * (1 - haze[..., None]) + pale * haze[..., None]
    sky = sky + (glow ** 20)[..., None] * (1 - 0.8 * cover[..., None]) * np.array([1.3, 1.25, 1.1])
    sky = sky + (glow ** 3)[..., None] * np.array([0.08, 0.08, 0.07])
    below = d[..., 2] < 0
    sky[below] = pale * 0.45
    return sky.astype(np.float32)


def save_exr(path: Path, rgb: np.ndarray) -> bool:
    """Write an OpenEXR image (half float, ZIP) through Blender's Python module; False without bpy."""
    try:
        import bpy
    except ImportError:
        return False
    h, w, _ = rgb.shape
    img = bpy.data.images.new("coast_sky", w, h, alpha=True, float_buffer=True)
    rgba = np.concatenate([rgb[::-1], np.ones((h, w, 1), np.float32)], -1)  # Blender's rows run bottom up
    img.pixels.foreach_set(rgba.ravel())
    sc = bpy.context.scene
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.exr_codec = "ZIP"
    sc.render.image_settings.color_depth = "16"
    sc.render.image_settings.color_mode = "RGB"
    img.save_render(str(path), scene=sc)
    bpy.data.images.remove(img)
    return True


# --------------------------------------------------------------------------- files
def save(name: str, m: trimesh.Trimesh) -> Path:
    p = ASSETS / name
    p.write_bytes(trimesh.exchange.ply.export_ply(m, encoding="binary", include_attributes=False))
    return p


def main() -> None:
    rng = np.random.default_rng(32)
    ASSETS.mkdir(parents=True, exist_ok=True)
    write_heightmap(ASSETS / "coast.png", coast_heights())
    write_heightmap(ASSETS / "coast_quay.png", quay_heights())
    render, unit, core, count = breakwater(rng)
    assert unit.is_watertight and unit.is_winding_consistent and unit.volume > 0
    save("coast_unit.ply", unit)
    save("coast_breakwater_render.ply", render)
    # Collision: inside the domain (plus the kernel support) only.
    lo, hi = render.bounds
    col = collision_solid(render, max(lo[0], DOMAIN_LOWER[0]), min(hi[0], DOMAIN_UPPER[0]),
                          DOMAIN_LOWER[1] - 0.05, min(hi[1], DOMAIN_UPPER[1]) + 0.01, base=-0.05)
    assert col.is_watertight and col.volume > 0
    save("coast_breakwater.ply", col)
    rr, rc = rocks(rng)
    assert rc.is_watertight
    save("coast_rocks_render.ply", rr)
    save("coast_rocks.ply", rc)
    if not save_exr(ASSETS / "coast_sky.exr", storm_sky()):
        print("no bpy: scenes/assets/coast_sky.exr not written (pip install bpy)")
    paddle = trimesh.creation.box(extents=[0.04, DOMAIN_UPPER[1] + 0.1, 0.6])
    save("coast_wavemaker.ply", paddle)
    # The paddle stands in for the storm's swell coming in from the open sea, so it is not drawn: its
    # render mesh is a 1 cm cube 0.6 m below it, under the sea bed.
    below = trimesh.transformations.translation_matrix([0, 0, -0.6])
    save("coast_wavemaker_render.ply", trimesh.creation.box(extents=[0.01] * 3, transform=below))
    print(f"tetrapod: {len(unit.faces)} faces, {unit.volume * 1e6:.0f} cm³, "
          f"height {np.ptp(unit.vertices[:, 2]) * 100:.1f} cm; "
          f"{count} units; breakwater render mesh {len(render.faces)} faces; collision {len(col.faces)} faces")
    for f in sorted(ASSETS.glob("coast*")):
        print(f"  {f}: {f.stat().st_size / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
