"""Derive the demo's bunny meshes from the watertight Stanford bunny in the pymeshlab wheel.

    python scripts/make_bunny_assets.py        (needs: pip install pymeshlab)

Writes scenes/assets/bunny_collision.ply (low poly, for the simulation's SDF)
and scenes/assets/bunny_render.ply (high poly, for Blender). Both are
watertight, binary PLY, in the source's units and y-up orientation; the
scene rotates them to z-up. Source: the Stanford 3D Scanning Repository.
"""

from __future__ import annotations

from pathlib import Path

import pymeshlab
import trimesh

SRC = Path(pymeshlab.__file__).parent / "tests" / "sample_meshes" / "bunny.obj"
OUT = Path(__file__).resolve().parents[1] / "scenes" / "assets"


def decimate(target_faces: int, out: Path) -> None:
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(SRC))
    ms.meshing_decimation_quadric_edge_collapse(
        targetfacenum=target_faces, preservetopology=True, preserveboundary=True, preservenormal=True, qualitythr=0.5
    )
    m = ms.current_mesh()
    t = trimesh.Trimesh(m.vertex_matrix(), m.face_matrix(), process=True)
    if not t.is_watertight:
        trimesh.repair.fill_holes(t)
    assert t.is_watertight, f"{out.name}: decimation opened the mesh"
    t.export(str(out), encoding="binary")
    print(f"{out}: {len(t.faces)} faces, {out.stat().st_size / 1024:.0f} KiB")


if __name__ == "__main__":
    OUT.mkdir(parents=True, exist_ok=True)
    decimate(3000, OUT / "bunny_collision.ply")
    decimate(30000, OUT / "bunny_render.ply")
