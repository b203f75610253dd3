"""The heightmap of scenes/creek.toml: a mountain creek cut into a grassy hillside (no downloads).

    python scripts/make_creek_assets.py          # writes scenes/assets/creek.png

The creek runs along +x down the middle of the simulated domain (0..2 m in x, 0..0.8 m in y):
it leaves a rock face at x = 0, falls over two rock steps with boulders in the rapids, fills a
pool at x = 1.3-1.75 m held by a lip at x = 1.82 m, and runs on downhill beyond the domain. Banks
rise steeply out of the channel to rolling ground. Heights are built in metres over the image's
footprint (``LOWER``, ``SIZE``) and stored over ``HEIGHT``; the scene's [terrain] repeats these
constants, and tests/test_creek_scene.py checks the scene against them.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from whitecap.terrain import write_heightmap  # noqa: E402

LOWER = (-1.5, -1.2)  # x, y of the image's lower corner [m]
SIZE = (5.0, 3.2)  # its extent [m]
HEIGHT = (-0.2, 1.4)  # heights of pixel values 0 and 65535 [m]
PIXELS = (500, 320)  # columns, rows: 1 cm a pixel
SEED = 11

#: The channel bed along the creek's axis: (x [m], z [m]), joined by a monotone cubic.
BED = [(-1.5, 1.15), (-0.3, 0.98), (-0.08, 0.9), (0.0, 0.44), (0.1, 0.4), (0.33, 0.36), (0.43, 0.29),
       (0.68, 0.25), (0.78, 0.18), (1.05, 0.15), (1.2, 0.12), (1.35, 0.03), (1.55, 0.02), (1.72, 0.05),
       (1.82, 0.11), (1.92, 0.08), (2.2, 0.03), (3.5, -0.15)]
POOL = (1.25, 1.78)  # x range where the channel widens into the pool [m]
LIP = 0.11  # the pool's lip: the water's level there [m]
#: Boulders: (x, offset from the axis in y, radius, height above the bed) [m].
BOULDERS = [(0.24, -0.05, 0.05, 0.07), (0.47, 0.06, 0.06, 0.08), (0.6, -0.07, 0.045, 0.06),
            (0.88, 0.03, 0.055, 0.075), (1.1, -0.06, 0.05, 0.06), (1.3, 0.2, 0.08, 0.13),
            (1.68, -0.24, 0.07, 0.11), (0.05, 0.16, 0.08, 0.15), (0.95, 0.15, 0.07, 0.1)]


def axis_y(x):
    """y of the creek's axis [m]: a gentle meander about the domain's middle."""
    return 0.4 + 0.04 * np.sin(2.2 * np.asarray(x))


def bed_z(x):
    from scipy.interpolate import PchipInterpolator

    xs, zs = zip(*BED)
    return PchipInterpolator(xs, zs)(np.asarray(x, np.float64))


def half_width(x):
    """Half the channel's width at its bed [m]: 0.12 in the rapids, 0.27 in the pool."""
    x = np.asarray(x, np.float64)
    s = np.clip((x - POOL[0]) / 0.12, 0, 1) * np.clip((POOL[1] - x) / 0.08, 0, 1)
    return 0.12 + 0.15 * s * s * (3 - 2 * s)


def smooth_noise(shape, scale, rng):
    from scipy.ndimage import gaussian_filter

    n = gaussian_filter(rng.standard_normal(shape), scale, mode="wrap")
    return n / (np.abs(n).max() + 1e-12)


def heights_m(x, y, rng) -> np.ndarray:
    """The terrain's height [m] at world (x, y) grids."""
    zb = bed_z(x)
    w = half_width(x)
    d = np.abs(y - axis_y(x))
    e = np.maximum(d - w, 0.0)
    z = zb + 0.03 * np.minimum(d / w, 1.0) ** 2  # a rounded bed
    z += 0.22 * (1 - np.exp(-e / 0.1)) + 0.18 * e  # steep banks, then rolling ground rising away
    shape = x.shape
    z += 0.05 * smooth_noise(shape, 40, rng) * np.clip(e / 0.3, 0, 1)  # hills, none in the channel
    z += 0.006 * smooth_noise(shape, 2.5, rng)  # stones and tufts
    for bx, by, br, bh in BOULDERS:
        cy = axis_y(bx) + by
        q = ((x - bx) ** 2 + (y - cy) ** 2) / br ** 2
        lumpy = 1 + 0.15 * smooth_noise(shape, 3, rng)
        top = bed_z(bx) + 0.02 + bh * np.sqrt(np.clip(1 - q, 0, 1)) * lumpy
        z = np.where(q < 1, np.maximum(z, top), z)
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
