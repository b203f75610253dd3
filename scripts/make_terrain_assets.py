"""Procedural 16-bit heightmaps for the terrain scenes (no downloads).

    python scripts/make_terrain_assets.py            # writes scenes/assets/beach_slope.png

``beach_heights`` is a beach seen from above, x across the image (sea on the
left, land on the right): a flat sea bed, a concave sandy slope rising out of
the water, a berm and low dunes, with gentle ripples and a few rocks. The
heights are in [0, 1]; the scene maps them to metres (``terrain.height``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from whitecap.terrain import smooth_noise, write_heightmap  # noqa: E402


def beach_heights(width: int = 512, height: int = 256, seed: int = 7, toe: float = 0.35, top: float = 0.8,
                  rocks: int = 5) -> np.ndarray:
    """Heights in [0, 1], (height, width): the sea bed at 0.1 up to x = ``toe`` (a fraction of the
    width), a beach rising to 0.75 at x = ``top``, then dunes; ripples and ``rocks`` boulders."""
    rng = np.random.default_rng(seed)
    u = np.linspace(0.0, 1.0, width)[None, :].repeat(height, 0)
    v = np.linspace(0.0, 1.0, height)[:, None].repeat(width, 1)
    # The shoreline wanders a little along y, so the beach is not a ruled surface.
    wander = 0.03 * smooth_noise((height, 1), height / 8, rng).repeat(width, 1)
    s = np.clip((u - toe - wander) / (top - toe), 0.0, 1.0)
    profile = 0.1 + 0.65 * (s ** 1.3)  # concave: steeper towards the berm, as a real beach
    dunes = np.clip((u - top) / (1 - top), 0, 1) * (0.75 + 0.12 * smooth_noise((height, width), width / 16, rng))
    z = np.maximum(profile, dunes)
    z += 0.012 * smooth_noise((height, width), width / 40, rng)  # gentle undulation
    z += 0.003 * np.sin(2 * np.pi * (u * 40 + 2 * smooth_noise((height, width), width / 20, rng)))  # ripples
    for _ in range(rocks):  # boulders on the upper beach
        cx, cy = rng.uniform(top - 0.15, top + 0.05), rng.uniform(0.1, 0.9)
        rad = rng.uniform(0.02, 0.05)
        d2 = ((u - cx) / rad) ** 2 + ((v - cy) * height / width / rad) ** 2
        bump = np.interp(cx, u[0], z[int(cy * (height - 1))]) + 0.06 * np.sqrt(np.clip(1 - d2, 0, 1))
        z = np.where(d2 < 1, np.maximum(z, bump), z)
    return np.clip(z, 0.0, 1.0)


def main() -> None:
    out = ROOT / "scenes" / "assets"
    out.mkdir(parents=True, exist_ok=True)
    write_heightmap(out / "beach_slope.png", beach_heights())
    print(f"wrote {out / 'beach_slope.png'}")


if __name__ == "__main__":
    main()
