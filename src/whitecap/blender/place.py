"""Obstacles and moving bodies placed as whitecap places them (bpy inside functions).

An obstacle's rest placement is run.json's ``scale``, ``rotate`` (degrees about x, then y,
then z) and ``translate`` (geometry.placement_matrix: T Rz Ry Rx S). Blender's XYZ Euler
is the same Rz Ry Rx, so a static obstacle is an object with that location, rotation and
scale over its mesh in its own coordinates. A moving body's mesh takes the rest placement
and the object is keyed with run.json's pose per frame (position, quaternion w x y z):
world = T(p) R(q) placement, as geometry.obstacle_matrix.
"""

from __future__ import annotations

import math

from ..io.record import Frame, Obstacle, Pose


def place_obstacle(obj, entry: Obstacle) -> None:
    """Set ``obj``'s transform to the obstacle's rest placement."""
    obj.location = entry.translate
    obj.rotation_mode = "XYZ"
    obj.rotation_euler = [math.radians(a) for a in entry.rotate]
    s = float(entry.scale)
    obj.scale = (s, s, s)


def body_poses(frames: list[Frame], k: int, first: int | None = None,
               last: int | None = None) -> list[tuple[int, Pose]]:
    """(frame index, pose) of body ``k`` from run.json's frames (within first..last where given)."""
    out = []
    for f in frames:
        b = f.bodies or []
        if k < len(b) and (first is None or f.index >= first) and (last is None or f.index <= last):
            out.append((f.index, b[k]))
    return sorted(out, key=lambda p: p[0])


def key_body(obj, poses) -> None:
    """A moving body: the rest placement moves into the mesh, and the object is keyed with each
    pose; linear keys (no overshoot between frames), so motion blur comes from the keys."""
    if not poses:
        return
    obj.data.transform(obj.matrix_basis.copy())
    obj.data.update()
    obj.location, obj.scale = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    obj.rotation_mode = "QUATERNION"
    for i, pose in poses:
        obj.location = pose.position
        obj.rotation_quaternion = pose.quaternion
        obj.keyframe_insert("location", frame=i)
        obj.keyframe_insert("rotation_quaternion", frame=i)
    linear_keys(obj.animation_data.action)


def linear_keys(action) -> None:
    """Linear interpolation between an action's keys."""
    curves = getattr(action, "fcurves", None)
    if curves is None:  # Blender 5: layered actions
        curves = [c for layer in action.layers for strip in layer.strips for bag in strip.channelbags
                  for c in bag.fcurves]
    for c in curves:
        for kp in c.keyframe_points:
            kp.interpolation = "LINEAR"


def obstacle_object(name: str, me, entry: Obstacle, frames: list[Frame], k: int, collection, first=None, last=None):
    """An obstacle object over mesh ``me`` (in the obstacle's own coordinates), placed, keyed
    when it moves, and linked into ``collection``."""
    import bpy

    obj = bpy.data.objects.new(name, me)
    place_obstacle(obj, entry)
    collection.objects.link(obj)
    key_body(obj, body_poses(frames, k, first, last))
    return obj
