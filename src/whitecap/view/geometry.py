"""Geometry for the viewer: obstacle meshes (at rest, and moved by their pose) and the domain box."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..geometry import obstacle_transform, pose_matrix
from ..io.record import OBSTACLE_COLOR, Obstacle, Pose

log = logging.getLogger("whitecap.view")


def load_obstacle_meshes(entries: list[Obstacle],
                         bases: list[Path]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, tuple, int]]:
    """(vertices (V,3) f32, faces (F,3) i32, vertex normals (V,3) f32, colour, obstacle index) per
    obstacle, in its rest placement (:func:`posed` moves it to a frame's pose).

    Relative mesh paths are looked for in ``bases`` in order (the scene directory, then the run
    directory for playback), then the working directory. Missing or unreadable meshes are skipped
    with a warning: the viewer still shows the fluid. Glass obstacles (a closed tank around the
    fluid) are not drawn: opaque, they would hide the water; the domain box's edges outline them.
    """
    import trimesh

    out = []
    for k, e in enumerate(entries):
        if e.material == "glass":
            continue
        path = Path(e.render_file)
        cands = [path] if path.is_absolute() else [b / path for b in bases] + [Path.cwd() / path]
        found = next((c for c in cands if c.is_file()), None)
        if found is None:
            log.warning("obstacle mesh %s not found; not shown", path)
            continue
        try:
            m = trimesh.load_mesh(found)
        except Exception as exc:  # a bad mesh must not stop the viewer
            log.warning("obstacle mesh %s unreadable (%s); not shown", found, exc)
            continue
        m.apply_transform(obstacle_transform(e))
        color = tuple(float(c) for c in e.color or OBSTACLE_COLOR)
        out.append((m.vertices.astype(np.float32), m.faces.astype(np.int32), m.vertex_normals.astype(np.float32),
                    color, k))
    return out


def posed(vertices: np.ndarray, normals: np.ndarray, body: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Rest-placement vertices and normals carried by a body pose from run.json: ``geometry.pose_matrix``."""
    M = pose_matrix(body)
    R, T = M[:3, :3], M[:3, 3]
    return (vertices @ R.T + T).astype(np.float32), (normals @ R.T).astype(np.float32)


def box_lines(lower, upper) -> np.ndarray:
    """The 12 edges of an axis-aligned box as 24 line-segment end points."""
    lo, hi = np.asarray(lower, np.float32), np.asarray(upper, np.float32)
    c = np.array([[(hi if (k >> a) & 1 else lo)[a] for a in range(3)] for k in range(8)], np.float32)
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return np.array([c[i] for e in edges for i in e], np.float32)
