"""Make scenes/assets/hull.obj: a small boat hull for scenes/floating.toml.

The hull is the convex hull of two outlines: the deck (z = 7 cm), 30 cm long and
12 cm in beam with a pointed bow, and a narrower keel outline at z = 0 whose bow
is drawn back, so the sides flare and the stem rakes forward. Convex, so
watertight and consistently wound by construction. Origin at the middle of the
keel, x forward, z up.

    python scripts/make_hull.py
"""

from pathlib import Path

import numpy as np
import trimesh

DECK = [(-0.15, -0.06), (0.05, -0.06), (0.11, -0.035), (0.15, 0.0), (0.11, 0.035), (0.05, 0.06), (-0.15, 0.06)]
KEEL = [(-0.14, -0.035), (0.02, -0.035), (0.07, -0.018), (0.10, 0.0), (0.07, 0.018), (0.02, 0.035), (-0.14, 0.035)]
DEPTH = 0.07  # [m]


def hull() -> trimesh.Trimesh:
    pts = np.array([(x, y, DEPTH) for x, y in DECK] + [(x, y, 0.0) for x, y in KEEL])
    return trimesh.convex.convex_hull(pts)


def main() -> None:
    m = hull()
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    out = Path(__file__).resolve().parents[1] / "scenes" / "assets" / "hull.obj"
    text = trimesh.exchange.obj.export_obj(m, include_normals=False, include_texture=False, header=None)
    out.write_text("# A small boat hull for scenes/floating.toml, made by scripts/make_hull.py. z is up.\n" + text)
    print(f"{out}: {len(m.faces)} faces, volume {m.volume * 1e6:.0f} cm³")


if __name__ == "__main__":
    main()
