"""A camera that follows a body or a point, and the low "over the water" preset (pure numpy).

``[render] camera_follow = "body:K"`` tracks obstacle K: its centre (the
middle of its rest-placed mesh's box) carried by the pose ``run.json``
records per frame (``frames[i].bodies[K]``). The track is smoothed by a
critically damped spring of time constant ``camera_smoothing`` [s]
(:func:`smooth_track`): it starts at rest on the first frame's point, never
overshoots, and lags a body moving at a steady speed v by 2·τ·v. The
smoothing always runs from the run's first frame, so a frame's camera is
the same whichever frame range is rendered. The camera keeps a fixed offset
from the smoothed point and looks at it. ``camera_follow = [x, y, z]``
looks at a fixed point.

``camera_preset = "over_water"`` puts the camera ``camera_height`` above the
still-water level (:func:`whitecap.render.sea.still_level`), in front of
the framed point and far enough back to frame it, looking across the water
at the point's place on the sea surface (a body's centre when it follows one):
nearly horizontal, with the horizon in the upper part of the image.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..config import Render
from ..errors import InputError
from ..geometry import obstacle_transform, unit_quat_matrix
from ..io.record import Obstacle
from ..io.run import RunInfo, obstacle_path
from . import stage
from .sea import still_level

#: The framed box around a followed body: its rest box scaled by this about its centre (water around it).
BODY_FRAME = 3.0
#: over_water: the camera's height above the sea as a share of the framed box's larger horizontal side.
OVER_WATER_HEIGHT = 0.04


def active(cfg: Render) -> bool:
    """Whether the camera follows something or uses a preset (else stage.camera_keys' path)."""
    return cfg.camera_follow is not None or cfg.camera_preset is not None


def smooth_track(points, dt: float, tau: float) -> np.ndarray:
    """Critically damped smoothing of a track sampled every ``dt`` seconds: x'' = ω²(p − x) − 2ω x',
    ω = 1/τ, integrated exactly with each sample held over the step that ends at it; starts at
    rest on the first point. τ = 0 returns the points."""
    p = np.asarray(points, float)
    if tau <= 0 or len(p) == 0:
        return p.copy()
    w = 1.0 / tau
    out = np.empty_like(p)
    x, v = p[0].copy(), np.zeros_like(p[0])
    out[0] = x
    decay = math.exp(-w * dt)
    for i in range(1, len(p)):
        e0 = x - p[i]
        c = v + w * e0
        e = (e0 + c * dt) * decay
        v = (v - w * c * dt) * decay
        x = p[i] + e
        out[i] = x
    return out


def body_index(cfg: Render, info: RunInfo) -> int | None:
    f = cfg.camera_follow
    if not isinstance(f, str):
        return None
    k = int(f.split(":", 1)[1])
    if k >= len(info.obstacles):
        raise InputError(f"render.camera_follow = '{f}': the run has {len(info.obstacles)} obstacle(s) "
                         f"(indices 0 to {len(info.obstacles) - 1})")
    return k


def body_rest_box(entry: Obstacle, info: RunInfo, run_dir: Path | None) -> tuple[np.ndarray, np.ndarray]:
    """The box of an obstacle's rest-placed collision mesh (its translate alone where the file is missing)."""
    import trimesh

    M = obstacle_transform(entry)
    src = entry.mesh or entry.render_mesh
    path = obstacle_path(src, info, run_dir) if src else None
    if path is None:
        c = M[:3, 3]
        return c, c
    m = trimesh.load_mesh(str(path))
    v = np.asarray(m.vertices, float) @ M[:3, :3].T + M[:3, 3]
    return v.min(0), v.max(0)


def body_track(info: RunInfo, k: int, centre, frames) -> np.ndarray:
    """Obstacle k's rest centre carried by its recorded pose at each of ``frames`` (at rest where none)."""
    c = np.asarray(centre, float)
    out = []
    for i in frames:
        pose = info.body_pose(i, k)
        if pose is None:
            out.append(c)
        else:
            out.append(unit_quat_matrix(pose.quaternion) @ c + np.asarray(pose.position, float))
    return np.array(out)


def follow_keys(cfg: Render, info: RunInfo, bounds, first: int, last: int, aspect: float,
                run_dir: Path | None = None) -> tuple[dict[int, list[float]], dict[int, list[float]]]:
    """Camera position and look-at point at every frame first..last (see the module docstring)."""
    lo, hi = (np.asarray(b, float) for b in (bounds if bounds is not None else
                                               (info.domain["lower"], info.domain["upper"])))
    start = min([f.index for f in info.frames] + [first])
    frames = list(range(start, last + 1))
    k = body_index(cfg, info)
    if k is not None:
        blo, bhi = body_rest_box(info.obstacles[k], info, run_dir)
        centre = (blo + bhi) / 2
        raw = body_track(info, k, centre, frames)
        half = np.maximum(BODY_FRAME * (bhi - blo) / 2, 2 * info.particle_radius)
        frame_lo, frame_hi = centre - half, centre + half
    else:
        if isinstance(cfg.camera_follow, list):
            point = np.asarray(cfg.camera_follow, float)
        elif cfg.camera_target:
            point = np.asarray(cfg.camera_target, float)
        else:
            point = (lo + hi) / 2
        raw = np.tile(point, (len(frames), 1))
        frame_lo, frame_hi = lo, hi
        centre = point
    track = smooth_track(raw, 1.0 / info.frame_rate, cfg.camera_smoothing)
    if cfg.camera_preset == "over_water":
        level = still_level(cfg, info, run_dir)
        width = float(max(frame_hi[0] - frame_lo[0], frame_hi[1] - frame_lo[1]))
        height = cfg.camera_height if cfg.camera_height is not None else OVER_WATER_HEIGHT * width
        if k is None:  # look at the sea surface below the point
            track[:, 2] = level
        look = np.array([centre[0], centre[1], track[0, 2]])
        if cfg.camera_offset is not None:
            offset = np.asarray(cfg.camera_offset, float)
        else:
            v = np.array(stage.VIEW_DIRECTION[:2], float)
            v /= np.linalg.norm(v)
            dist = stage.frame_box(frame_lo, frame_hi, look, [v[0], v[1], 0.05], cfg.lens, aspect)
            offset = np.array([dist * v[0], dist * v[1], 0.0])
        pos = track + offset
        pos[:, 2] = level + height
    else:
        if cfg.camera_offset is not None:
            offset = np.asarray(cfg.camera_offset, float)
        elif cfg.camera_start and cfg.camera_target:
            offset = np.asarray(cfg.camera_start, float) - np.asarray(cfg.camera_target, float)
        else:
            u = np.asarray(stage.VIEW_DIRECTION, float) / np.linalg.norm(stage.VIEW_DIRECTION)
            offset = stage.frame_box(frame_lo, frame_hi, centre, u, cfg.lens, aspect) * u
        pos = track + offset
    keep = [j for j, f in enumerate(frames) if f >= first]
    return ({frames[j]: pos[j].tolist() for j in keep}, {frames[j]: track[j].tolist() for j in keep})
