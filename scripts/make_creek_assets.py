"""The heightmap of scenes/creek.toml: a mountain creek cut into a grassy hillside (no downloads).

    python scripts/make_creek_assets.py          # writes scenes/assets/creek.png

The creek runs along +x down the middle of the simulated domain (-0.3..2 m in x, 0..0.8 m in y).
It runs along the flat floor of a notch in a crag (a rock headwall curving round the head of the
channel, its face broken by ledges and buttresses, not a straight wall), falls from the notch's lip
on to a cobbled bed, tumbles over a rock step with boulders in the rapids, fills a pool at
x = 1.3-1.75 m held by a lip at x = 1.82 m, and runs on downhill beyond the domain. The channel is
carved into a hillside that falls smoothly down the valley (its banks do not repeat the bed's
steps) and rises to hills on either side and behind the crag; angular blocks lie scattered over it.
Heights are built in metres over the image's footprint (``LOWER``, ``SIZE``) and stored over
``HEIGHT``; the scene's [terrain] repeats these constants, and tests/test_creek_scene.py checks the
scene against them.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from whitecap.terrain import smooth_noise, write_heightmap  # noqa: E402

LOWER = (-3.0, -1.6)  # x, y of the image's lower corner [m]
SIZE = (7.0, 4.0)  # its extent [m]
HEIGHT = (-0.3, 2.1)  # heights of pixel values 0 and 65535 [m]
PIXELS = (700, 400)  # columns, rows: 1 cm a pixel
SEED = 11

#: The channel bed along the creek's axis: (x [m], z [m]), joined by a monotone cubic. Upstream of
#: x = 0 it runs into the crag (the headwall covers it).
BED = [(-0.3, 0.46), (0.0, 0.44), (0.12, 0.4), (0.2, 0.345), (0.28, 0.36), (0.33, 0.36), (0.43, 0.29),
       (0.68, 0.25), (0.78, 0.18), (1.05, 0.15), (1.2, 0.12), (1.35, 0.03), (1.55, 0.02), (1.72, 0.05),
       (1.82, 0.11), (1.92, 0.08), (2.2, 0.03), (4.0, -0.2)]
#: The valley floor the hillside falls along (no steps): (x [m], z [m]).
VALLEY = [(-3.0, 1.75), (-1.0, 1.35), (-0.2, 0.98), (0.3, 0.62), (0.9, 0.42), (1.5, 0.27), (2.2, 0.17),
          (4.0, -0.05)]
#: Cobbles on the channel's bed: their mean spacing and greatest height [m].
COBBLE = 0.05
COBBLE_HEIGHT = 0.022
POOL = (1.25, 1.78)  # x range where the channel widens into the pool [m]
LIP = 0.11  # the pool's lip: the water's level there [m]
#: The crag at the head: where its face's top edge crosses the creek's axis [m], its height above
#: the bed there [m], how the edge curves back round the channel's head [1/m], its face's slope [-].
CRAG_EDGE = 0.0
CRAG_HEIGHT = 0.5
CRAG_CURVE = 0.9
CRAG_SLOPE = 4.0
#: The notch the creek falls from: its lip's height [m], its half-width [m] and where its lip is [m].
NOTCH = (0.6, 0.15, 0.08)
#: Its floor is flat for this far behind the lip (the inflow enters there, out of sight below
#: the lip) [m], then rises at this slope [-].
NOTCH_FLAT = 0.45
NOTCH_RISE = 0.8
#: Boulders: (x, offset from the axis in y, radius, height above the bed) [m]: in the rapids and
#: at the pool's edges.
BOULDERS = [(0.24, -0.05, 0.05, 0.07), (0.47, 0.06, 0.06, 0.08), (0.6, -0.07, 0.045, 0.06),
            (0.88, 0.03, 0.055, 0.075), (1.1, -0.06, 0.05, 0.06), (1.3, 0.2, 0.08, 0.13),
            (1.68, -0.24, 0.07, 0.11), (0.18, 0.12, 0.07, 0.12), (0.95, 0.12, 0.06, 0.09),
            (0.35, 0.09, 0.045, 0.07), (0.72, 0.09, 0.045, 0.07), (1.2, -0.12, 0.055, 0.08),
            (1.5, 0.27, 0.06, 0.09), (1.78, 0.2, 0.05, 0.07), (0.15, -0.11, 0.06, 0.1),
            (1.62, 0.25, 0.045, 0.06), (1.4, -0.26, 0.05, 0.07)]
#: Angular blocks strewn over the banks and the hillside: how many, and their size range [m].
SCREE = (40, 0.06, 0.2)


def axis_y(x):
    """y of the creek's axis [m]: a gentle meander about the domain's middle."""
    return 0.4 + 0.04 * np.sin(2.2 * np.asarray(x))


def _pchip(points, x):
    from scipy.interpolate import PchipInterpolator

    xs, zs = zip(*points)
    return PchipInterpolator(xs, zs, extrapolate=True)(np.asarray(x, np.float64))


def bed_z(x):
    return _pchip(BED, x)


def valley_z(x):
    return _pchip(VALLEY, x)


def half_width(x):
    """Half the channel's width at its bed [m]: 0.12 in the rapids, 0.27 in the pool."""
    x = np.asarray(x, np.float64)
    s = np.clip((x - POOL[0]) / 0.12, 0, 1) * np.clip((POOL[1] - x) / 0.08, 0, 1)
    return 0.12 + 0.15 * s * s * (3 - 2 * s)


def cobbles(x, y, rng) -> np.ndarray:
    """Packed rounded stones [m]: a dome over each cell of a Voronoi diagram of random centres
    (``COBBLE`` apart, up to ``COBBLE_HEIGHT`` high), 2 f1 / (f1 + f2) being 0 at a centre and 1 on a
    cell's border (f1, f2: distances to the nearest two centres)."""
    from scipy.spatial import cKDTree

    x0, x1, y0, y1 = x.min(), x.max(), y.min(), y.max()
    n = int((x1 - x0) * (y1 - y0) / COBBLE ** 2)
    centres = np.stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)], 1)
    size = rng.uniform(0.6, 1.0, n)
    dist, near = cKDTree(centres).query(np.stack([x.ravel(), y.ravel()], 1), k=2)
    s = (2 * dist[:, 0] / (dist.sum(1) + 1e-12)).reshape(x.shape)
    return COBBLE_HEIGHT * size[near[:, 0]].reshape(x.shape) * np.sqrt(np.clip(1 - s * s, 0, 1))


def heights_m(x, y, rng) -> np.ndarray:
    """The terrain's height [m] at world (x, y) grids."""
    shape = x.shape
    zb = bed_z(x)
    w = half_width(x)
    d = np.abs(y - axis_y(x))
    e = np.maximum(d - w, 0.0)
    channel = zb + 0.03 * np.minimum(d / w, 1.0) ** 2  # a rounded bed
    channel += cobbles(x, y, rng) * np.clip(1.5 - e / 0.06, 0, 1)  # of stones, into the banks' feet
    # The hillside: the valley's smooth fall, rising away from the creek to hills.
    hills = 0.16 * smooth_noise(shape, 45, rng) + 0.05 * smooth_noise(shape, 12, rng)
    a = np.maximum(d - 0.12, 0.0)  # from the rapids' edge, so the pool's widening leaves no seam
    hill = valley_z(x) + 0.15 * a + 0.35 * (a / 1.2) ** 2 + hills * np.clip(a / 0.4, 0, 1)
    hill = np.maximum(hill, zb + 0.2)
    z = channel + (hill - channel) * (1 - np.exp(-e / 0.07))  # banks out of the channel
    # The crag: a headwall whose top edge curves round the channel's head, its line and height
    # broken by buttresses and ledges; ground above it rises on to the hills. The creek falls from a
    # flat-bottomed notch in it.
    dy = y - axis_y(0.0)
    notch = np.exp(-(dy / NOTCH[1]) ** 4)
    edge = CRAG_EDGE + CRAG_CURVE * dy ** 2 + 0.05 * smooth_noise(shape, 6, rng)
    edge = edge * (1 - notch) + NOTCH[2] * notch
    top = bed_z(0.0) + CRAG_HEIGHT + 0.12 * smooth_noise(shape, 20, rng) + valley_z(x) - valley_z(0.0)
    gully = NOTCH[0] + NOTCH_RISE * np.maximum(NOTCH[2] - NOTCH_FLAT - x, 0.0)  # the notch's floor
    top = top * (1 - notch) + np.minimum(top, gully) * notch
    drop = np.maximum(x - edge, 0.0)
    ledges = 0.025 * np.round(drop * CRAG_SLOPE / 0.07 + 0.5 * smooth_noise(shape, 4, rng))
    crag = top - CRAG_SLOPE * drop - ledges * (1 - notch)
    z = np.maximum(z, crag)
    crag_here = crag >= z - 1e-9
    z += 0.004 * smooth_noise(shape, 2.5, rng)  # stones and tufts
    bank = np.exp(-e / 0.12) * np.clip(e / 0.02, 0, 1) + crag_here * (x < 0.3) * (1 - notch)
    relief = 0.008 * smooth_noise(shape, 3, rng) + 0.014 * smooth_noise(shape, 8, rng)
    z += relief * np.clip(bank, 0, 1)  # rock relief
    z += 0.01 * smooth_noise(shape, 8, rng) * np.clip(e / 0.1, 0, 1)  # rougher ground off the bed
    for bx, by, br, bh in BOULDERS:  # water-worn: an ellipse of random aspect and heading,
        # rising to a blunt peak (so that all of it is steeper than grass grows on), lumpy
        by = axis_y(bx) + by
        ang, asp = rng.uniform(0, np.pi), rng.uniform(0.65, 1.0)
        u = (x - bx) * np.cos(ang) + (y - by) * np.sin(ang)
        v = -(x - bx) * np.sin(ang) + (y - by) * np.cos(ang)
        q = (u / br) ** 2 + (v / (br * asp)) ** 2
        lumpy = 1 + 0.25 * smooth_noise(shape, 3, rng)
        top_b = bed_z(bx) + 0.02 + bh * (1 - np.sqrt(np.clip(q, 0, 1))) ** 0.7 * lumpy
        z = np.where(q < 1, np.maximum(z, top_b), z)
    n, rmin, rmax = SCREE
    for _ in range(n):  # scree: angular blocks off the channel, half sunk into the slope
        bx, by = rng.uniform(-1.5, 3.5), rng.uniform(-1.0, 1.8)
        br = rng.uniform(rmin, rmax)
        if abs(by - axis_y(bx)) < half_width(bx) + 0.08 + 1.4 * br or (bx < 0.3 and abs(by - axis_y(0.0)) < 0.3):
            continue
        near = (np.abs(x - bx) < 2 * br) & (np.abs(y - by) < 2 * br)
        # A convex block: the lowest of a few planes, each falling from its ridge at 37-47 degrees.
        k = rng.integers(4, 7)
        phi = np.sort(rng.uniform(0, 2 * np.pi, k))
        reach = br * rng.uniform(0.6, 1.0, k)
        slope = np.tan(np.radians(rng.uniform(37, 47, k)))
        px, py = x[near] - bx, y[near] - by
        h = np.min([(r - (px * np.cos(f) + py * np.sin(f))) * t for f, r, t in zip(phi, reach, slope)]
                   + [(1.4 * br - np.hypot(px, py)) * slope.max()], axis=0)
        base = np.percentile(z[near], 35) - 0.25 * br
        z[near] = np.maximum(z[near], base + h)
    return z


def creek_heights() -> np.ndarray:
    """Heights in [0, 1] over ``HEIGHT``, (rows, cols), rows from +y down."""
    rng = np.random.default_rng(SEED)
    cols, rows = PIXELS
    x = LOWER[0] + np.arange(cols)[None, :] / (cols - 1) * SIZE[0] + np.zeros((rows, 1))
    y = LOWER[1] + (1 - np.arange(rows)[:, None] / (rows - 1)) * SIZE[1] + np.zeros((1, cols))
    z = heights_m(x, y, rng)
    return np.clip((z - HEIGHT[0]) / (HEIGHT[1] - HEIGHT[0]), 0, 1)


def main() -> None:
    out = ROOT / "scenes" / "assets"
    out.mkdir(parents=True, exist_ok=True)
    write_heightmap(out / "creek.png", creek_heights())
    print(f"wrote {out / 'creek.png'}")


if __name__ == "__main__":
    main()
