"""Make the assets of scenes/boat.toml: a painted, UV-mapped boat hull and a wave maker (no downloads).

    python scripts/make_boat_assets.py

writes into scenes/assets/:

- ``boat_render.obj``: the hull for Blender, with UVs (about 6k triangles). Stations along the
  length (x, bow at +x) and girth lines from the keel to the sheer; the sheer and the keel rise
  toward the bow, the sides flare, the bow is a sharp stem and the stern a flat transom.
- ``boat_hull.obj``: the collision mesh, the convex hull of the same surface (watertight by
  construction; the hull's sections and waterplane are convex, so it differs from the render
  surface by less than a millimetre).
- ``boat_paint.png``: the texture, painted with NumPy: antifouling red below a white boot stripe
  at the waterline the hull floats at in the simulation (FLOAT_DRAFT, TRIM; Archimedes' draft at
  the scene's density, found by bisection on the displaced volume, is printed beside it), a dark
  blue topside with a white sheer stripe and a thin gold cove line, the name in
  block letters of a 5 × 7 pixel font drawn here, a teak-coloured deck with planking and a transom
  with the name again.
- ``boat_wavemaker.obj``: the piston paddle, a 4 cm thick board wider than the tank.

The texture's bands (v from the top of the image): starboard side, port side, transom, deck. The
port side's u runs from bow to stern, so its lettering reads left to right from outside as on the
starboard side.
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import trimesh

ASSETS = Path(__file__).resolve().parents[1] / "scenes" / "assets"

LENGTH, BEAM, DEPTH = 0.50, 0.17, 0.10   # [m] overall length, beam, depth amidships at the sheer
DENSITY = 260.0                          # [kg/m³] the hull's density in scenes/boat.toml (paints the waterline)
WATER = 1000.0                           # [kg/m³]
NAME = "PETREL"
NS, NT = 64, 20                          # stations along the length, girth points keel to sheer
TEX_W, TEX_H = 1024, 1024                # texture size [px]; four bands of TEX_H / 4
#: Where the hull floats in the simulation, measured in scenes/boat.toml's still water (r = 8 mm, frames 20-35,
#: before the waves arrive): the contact coupling floats it deeper than Archimedes' draft (printed)
#: and a little down by the bow (its fine bow carries less volume than its centre of mass asks for).
FLOAT_DRAFT = 0.062                      # [m] amidships
TRIM = 3.5                               # [deg] bow down
DECK_Z_DROP = 0.004                      # the deck sits this far below the sheer (a low bulwark) [m]

# 5 × 7 block letters ('#' = ink), enough for boat names and numbers.
FONT = {
    "A": [" ### ", "#   #", "#   #", "#####", "#   #", "#   #", "#   #"],
    "B": ["#### ", "#   #", "#   #", "#### ", "#   #", "#   #", "#### "],
    "C": [" ####", "#    ", "#    ", "#    ", "#    ", "#    ", " ####"],
    "E": ["#####", "#    ", "#    ", "#### ", "#    ", "#    ", "#####"],
    "G": [" ####", "#    ", "#    ", "#  ##", "#   #", "#   #", " ### "],
    "H": ["#   #", "#   #", "#   #", "#####", "#   #", "#   #", "#   #"],
    "I": ["#####", "  #  ", "  #  ", "  #  ", "  #  ", "  #  ", "#####"],
    "K": ["#   #", "#  # ", "# #  ", "##   ", "# #  ", "#  # ", "#   #"],
    "L": ["#    ", "#    ", "#    ", "#    ", "#    ", "#    ", "#####"],
    "N": ["#   #", "##  #", "# # #", "#  ##", "#   #", "#   #", "#   #"],
    "O": [" ### ", "#   #", "#   #", "#   #", "#   #", "#   #", " ### "],
    "P": ["#### ", "#   #", "#   #", "#### ", "#    ", "#    ", "#    "],
    "R": ["#### ", "#   #", "#   #", "#### ", "# #  ", "#  # ", "#   #"],
    "S": [" ####", "#    ", "#    ", " ### ", "    #", "    #", "#### "],
    "T": ["#####", "  #  ", "  #  ", "  #  ", "  #  ", "  #  ", "  #  "],
    "W": ["#   #", "#   #", "#   #", "# # #", "# # #", "## ##", "#   #"],
    "0": [" ### ", "#   #", "#  ##", "# # #", "##  #", "#   #", " ### "],
    "1": ["  #  ", " ##  ", "  #  ", "  #  ", "  #  ", "  #  ", " ### "],
    "2": [" ### ", "#   #", "    #", "   # ", "  #  ", " #   ", "#####"],
    "7": ["#####", "    #", "   # ", "  #  ", " #   ", " #   ", " #   "],
    " ": ["     "] * 7,
}


# --------------------------------------------------------------------------- hull geometry
def keel_z(s: np.ndarray) -> np.ndarray:
    """Height of the keel line at s = (x - stern) / LENGTH in [0, 1]: flat aft, rising to the stem."""
    t = np.clip((s - 0.55) / 0.45, 0.0, 1.0)
    return 0.55 * DEPTH * t ** 2.2


def sheer_z(s: np.ndarray) -> np.ndarray:
    """Height of the sheer line: a gentle spring, highest at the bow."""
    return DEPTH * (0.97 + 0.03 * (1 - s) ** 2 + 0.22 * s ** 3)


def plan(s: np.ndarray) -> np.ndarray:
    """Half-breadth at the sheer as a share of BEAM / 2: a slightly narrower transom, full amidships,
    a fine entry to a sharp stem (concave-down, so the waterplane is convex)."""
    aft = 0.86 + 0.14 * np.sin(np.clip(s / 0.4, 0.0, 1.0) * np.pi / 2)
    fwd = 1.0 - np.clip((s - 0.5) / 0.5, 0.0, 1.0) ** 1.8
    return np.minimum(aft, fwd)


def section(t: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Half-breadth along the girth parameter t (0 keel, 1 sheer) as a share of the sheer's: a round
    bilge aft that sharpens into a V toward the bow."""
    p = 0.35 + 0.45 * np.clip((s - 0.4) / 0.6, 0.0, 1.0)
    return t ** p


def hull_points(ns: int = NS, nt: int = NT) -> tuple[np.ndarray, np.ndarray]:
    """Grid of the starboard side (y <= 0): points (ns, nt, 3) and the station parameters s."""
    s = np.linspace(0.0, 1.0, ns)
    t = np.linspace(0.0, 1.0, nt)
    S, T = np.meshgrid(s, t, indexing="ij")
    z0, z1 = keel_z(S), sheer_z(S)
    z = z0 + T * (z1 - z0)
    y = -0.5 * BEAM * plan(S) * section(T, S)
    x = -0.5 * LENGTH + S * LENGTH
    return np.stack([x, y, z], -1), s


def grid_faces(ni: int, nj: int, offset: int = 0, flip: bool = False) -> np.ndarray:
    i, j = np.meshgrid(np.arange(ni - 1), np.arange(nj - 1), indexing="ij")
    a = (i * nj + j).ravel() + offset
    b, c, d = a + nj, a + nj + 1, a + 1
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return f[:, ::-1] if flip else f


def render_hull() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, UVs (one per vertex) and outward-wound triangles of the painted hull."""
    P, s = hull_points()
    ns, nt = P.shape[:2]
    zmax = float(P[..., 2].max())
    verts, uvs, faces = [], [], []

    def add(v, uv, f):
        base = sum(len(a) for a in verts)
        verts.append(np.asarray(v, float))
        uvs.append(np.asarray(uv, float))
        faces.append(np.asarray(f, int) + base)

    band = 0.25
    # Starboard side: u from stern (0) to bow (1), v by height in the top band.
    sb = P.reshape(-1, 3)
    u = (sb[:, 0] + 0.5 * LENGTH) / LENGTH
    add(sb, np.stack([u, 1 - band + band * sb[:, 2] / zmax], 1), grid_faces(ns, nt, flip=False))
    # Port side: mirrored, u from bow (0) to stern (1) so the name reads left to right from outside.
    ps = sb * [1, -1, 1]
    add(ps, np.stack([1 - u, 1 - 2 * band + band * ps[:, 2] / zmax], 1), grid_faces(ns, nt, flip=True))
    # Transom (s = 0): a fan from the keel across the section, u across the beam.
    tr_sb = P[0]                       # (nt, 3), keel to sheer, y <= 0
    tr = np.concatenate([tr_sb[::-1] * [1, -1, 1], tr_sb[1:]])  # port sheer ... keel ... starboard sheer
    tu = 0.5 - tr[:, 1] / BEAM
    tv = 2 * band * 0.5 + band * tr[:, 2] / zmax * 0.999
    n = len(tr)
    keel = nt - 1
    fan = [[keel, i + 1, i] for i in range(keel)] + [[keel, i + 1, i] for i in range(keel, n - 1)]
    add(tr, np.stack([tu, tv], 1), fan)
    # Deck: strips between port and starboard sheer points at each station, a little below the sheer.
    sheer = P[:, -1]
    deck_sb = sheer - [0, 0, DECK_Z_DROP]
    deck_ps = deck_sb * [1, -1, 1]
    dv = np.concatenate([deck_ps, deck_sb])
    du = (dv[:, 0] + 0.5 * LENGTH) / LENGTH
    dvv = 0.5 * band + dv[:, 1] / BEAM * band * 0.98
    f = []
    for i in range(ns - 1):
        a, b, c, d = i, i + 1, ns + i + 1, ns + i
        f += [[a, c, b], [a, d, c]]
    add(dv, np.stack([du, dvv], 1), f)
    # Bulwark top: a thin strip from the sheer down to the deck, inside, both sides (same texture as the deck edge).
    for side in (1, -1):
        top = sheer * [1, side, 1]
        low = deck_sb * [1, side, 1] * [1, 0.97, 1]
        v = np.concatenate([top, low])
        uv = np.stack([(v[:, 0] + 0.5 * LENGTH) / LENGTH, np.full(len(v), 1 - band + band * 0.995)], 1)
        f = []
        for i in range(ns - 1):
            a, b, c, d = i, i + 1, ns + i + 1, ns + i
            f += [[a, b, c], [a, c, d]] if side == 1 else [[a, c, b], [a, d, c]]
        add(v, uv, f)
    V, UV, F = np.concatenate(verts), np.concatenate(uvs), np.concatenate(faces)
    # Wind every face outward from the hull's centre line (the fans and strips above are built by hand).
    c = V[F].mean(1)
    nrm = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    axis = np.stack([c[:, 0] * 0, c[:, 1], c[:, 2] - 0.5 * DEPTH], 1)
    out = np.einsum("ij,ij->i", nrm, axis) < 0
    deck = np.abs(c[:, 2] - sheer_z((c[:, 0] + 0.5 * LENGTH) / LENGTH)) < 1.5 * DECK_Z_DROP
    out[deck] = nrm[deck, 2] < 0       # deck faces look up
    F[out] = F[out][:, ::-1]
    return V, UV, F


def collision_hull(V: np.ndarray) -> trimesh.Trimesh:
    return trimesh.convex.convex_hull(V)


def convex_below(m: trimesh.Trimesh, z: float) -> float:
    """Volume of a convex mesh below the plane at height z: the hull of its vertices below and of
    its edges' crossings of the plane."""
    v = np.asarray(m.vertices)
    e = v[m.edges_unique]
    za, zb = e[:, 0, 2], e[:, 1, 2]
    cross = (za - z) * (zb - z) < 0
    t = ((z - za[cross]) / (zb[cross] - za[cross]))[:, None]
    pts = np.concatenate([v[v[:, 2] <= z], e[cross, 0] + t * (e[cross, 1] - e[cross, 0])])
    if len(pts) < 4:
        return 0.0
    try:
        return float(trimesh.convex.convex_hull(pts).volume)
    except Exception:  # a flat sliver at the keel
        return 0.0


def waterline(m: trimesh.Trimesh, density: float = DENSITY) -> float:
    """Height z at which the upright hull displaces its own mass of water (bisection)."""
    target = density / WATER * m.volume
    lo, hi = float(m.bounds[0, 2]), float(m.bounds[1, 2])
    for _ in range(40):
        z = 0.5 * (lo + hi)
        if convex_below(m, z) < target:
            lo = z
        else:
            hi = z
    return 0.5 * (lo + hi)


# --------------------------------------------------------------------------- paint
def text_mask(text: str, height_px: int) -> np.ndarray:
    """The text in the block font, ``height_px`` tall, as a boolean image."""
    cols = []
    for ch in text.upper():
        g = np.array([[c == "#" for c in row] for row in FONT.get(ch, FONT[" "])])
        cols += [g, np.zeros((7, 1), bool)]
    glyphs = np.concatenate(cols[:-1], 1)
    k = max(1, height_px // 7)
    return np.kron(glyphs, np.ones((k, k), bool))


def stamp(img: np.ndarray, mask: np.ndarray, top: int, left: int, colour, stretch_x: float = 1.0) -> None:
    """Paint ``colour`` where ``mask`` is set, its top-left corner at (top, left); ``stretch_x`` widens it
    (the side bands map fewer metres per pixel along u than along v)."""
    if stretch_x != 1.0:
        idx = (np.arange(int(mask.shape[1] * stretch_x)) / stretch_x).astype(int)
        mask = mask[:, idx]
    h, w = mask.shape
    region = img[top:top + h, left:left + w]
    region[mask[: region.shape[0], : region.shape[1]]] = colour


def paint(zmax: float, z_water: float) -> np.ndarray:
    """The hull's texture (TEX_H, TEX_W, 3) uint8 (see the module docstring for its layout)."""
    rng = np.random.default_rng(17)
    img = np.zeros((TEX_H, TEX_W, 3), np.uint8)
    bh = TEX_H // 4
    red, white, navy, gold = (150, 38, 30), (236, 234, 226), (22, 42, 78), (196, 160, 70)
    # Metres per pixel: along u the side band spans LENGTH over TEX_W, along v zmax over bh.
    stretch = (zmax / bh) / (LENGTH / TEX_W)

    def row(z: float) -> int:  # pixel row within a side band of height z (row 0 = the sheer)
        return int(round((1 - z / zmax) * (bh - 1)))

    for band in (0, 1):
        y0 = band * bh
        side = img[y0:y0 + bh]
        side[:] = navy
        xs = (np.arange(TEX_W) + 0.5) / TEX_W * LENGTH - 0.5 * LENGTH
        xs = xs if band == 0 else -xs                           # x along the band (port: bow at the left)
        zw = z_water + np.tan(np.radians(TRIM)) * xs            # the waterline with the hull's trim
        rows = np.arange(bh)[:, None]
        side[rows >= np.array([row(z) for z in zw + 0.007])[None, :]] = white   # boot stripe above it
        side[rows >= np.array([row(z) for z in zw - 0.002])[None, :]] = red     # antifouling below
        side[: row(zmax - 0.012)] = white                      # sheer stripe
        side[row(zmax - 0.017):row(zmax - 0.015)] = gold       # cove line
        # The name near the bow on both sides: the bow is at the right of band 0, the left of band 1.
        text = text_mask(NAME, int(0.018 / zmax * bh))
        tw = int(text.shape[1] * stretch)
        top = row(zmax - 0.024)
        margin = int(0.07 / LENGTH * TEX_W)
        left = TEX_W - margin - tw if band == 0 else margin
        stamp(side, text, top, left, white, stretch)
        # A hull number aft, small.
        num = text_mask("W 17", int(0.010 / zmax * bh))
        nw = int(num.shape[1] * stretch)
        left = int(0.10 / LENGTH * TEX_W) if band == 0 else TEX_W - int(0.10 / LENGTH * TEX_W) - nw
        stamp(side, num, row(z_water + 0.022), left, white, stretch)
    # Transom: navy with the name, red below the waterline.
    tr = img[2 * bh:3 * bh]
    tr[:] = navy
    zrow = lambda z: int(round(bh - 1 - (z / zmax * 0.999 * bh - 0.0)))  # noqa: E731 (v = 0.5 + band·z/zmax)
    zt = z_water - np.tan(np.radians(TRIM)) * 0.5 * LENGTH
    tr[zrow(zt + 0.007):] = white
    tr[zrow(zt - 0.002):] = red
    tr[: zrow(zmax - 0.012)] = white
    text = text_mask(NAME, int(0.016 / zmax * bh))
    sx = (zmax / bh) / (BEAM / TEX_W)                              # transom: u spans the beam
    tw = int(text.shape[1] * sx)
    stamp(tr, text, zrow(zmax - 0.020), (TEX_W - tw) // 2, gold, sx)
    # Deck: teak planks along the length with dark seams, a little grain.
    dk = img[3 * bh:]
    base = np.array([150, 104, 62], float)
    plank = (np.arange(bh) // max(1, bh // 12))[:, None]
    shade = 0.9 + 0.12 * np.random.default_rng(3).random(13)[plank]
    grain = 1 + 0.06 * np.sin(np.arange(TEX_W)[None, :] * 0.15 + rng.random((bh, 1)) * 6)
    dk[:] = np.clip(base * (shade * grain)[..., None], 0, 255).astype(np.uint8)
    dk[(np.arange(bh) % max(1, bh // 12)) < 2] = (52, 36, 24)
    return img


# --------------------------------------------------------------------------- files
def write_obj(path: Path, V, F, UV=None, header: str = "") -> None:
    lines = [f"# {header}"] if header else []
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in V]
    if UV is not None:
        lines += [f"vt {u:.6f} {v:.6f}" for u, v in UV]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in F]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F]
    path.write_text("\n".join(lines) + "\n")


def wavemaker(width: float = 0.88) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=[0.04, width, 0.5])


def main() -> None:
    ASSETS.mkdir(parents=True, exist_ok=True)
    V, UV, F = render_hull()
    col = collision_hull(V)
    assert col.is_watertight and col.is_winding_consistent and col.volume > 0
    zw = waterline(col)
    zmax = float(V[:, 2].max())
    write_obj(ASSETS / "boat_render.obj", V, F, UV,
              "scenes/boat.toml's painted hull (UVs for boat_paint.png), made by scripts/make_boat_assets.py. "
              "z is up, bow +x.")
    write_obj(ASSETS / "boat_hull.obj", col.vertices, col.faces, None,
              "scenes/boat.toml's collision hull (convex hull of boat_render.obj), "
              "made by scripts/make_boat_assets.py.")
    iio.imwrite(ASSETS / "boat_paint.png", paint(zmax, FLOAT_DRAFT), optimize=True)
    wm = wavemaker()
    write_obj(ASSETS / "boat_wavemaker.obj", wm.vertices, wm.faces, None,
              "scenes/boat.toml's piston wave maker: a 4 x 88 x 50 cm board centred on the origin, "
              "made by scripts/make_boat_assets.py.")
    mass = DENSITY * col.volume
    print(f"boat_render.obj: {len(F)} faces; boat_hull.obj: {len(col.faces)} faces, volume {col.volume * 1e6:.0f} cm³, "
          f"{mass:.2f} kg at {DENSITY:.0f} kg/m³, Archimedes' draft {zw * 100:.1f} cm of {zmax * 100:.1f} cm; "
          f"painted at {FLOAT_DRAFT * 100:.1f} cm, {TRIM:.1f}° down by the bow")
    for f in ("boat_render.obj", "boat_hull.obj", "boat_paint.png", "boat_wavemaker.obj"):
        print(f"  {ASSETS / f}: {(ASSETS / f).stat().st_size / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
