"""Mesh fill: a bpy mesh's geometry and point attributes replaced in place (bpy only)."""

from __future__ import annotations

import numpy as np

#: Blender's own attribute names, never written from a file's arrays.
RESERVED = ("position", "sharp_face", "material_index", "sharp_edge")


def polygons_of(faces) -> tuple[np.ndarray, np.ndarray]:
    """(loops, starts) of an (M, k) face array: flat vertex indices and each face's first loop."""
    faces = np.asarray(faces, np.int64)
    if faces.size == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int32)
    k = faces.shape[1]
    return faces.astype(np.int32).ravel(), np.arange(0, k * len(faces), k, dtype=np.int32)


def fill_mesh(me, points, loops=None, starts=None, arrays=(), normals=None, smooth: bool = True):
    """Replace ``me``'s geometry and attributes with ``points`` (N, 3), polygons given as
    ``loops`` (flat vertex indices) and ``starts`` (each polygon's first loop), and point
    ``arrays`` [(name, (N,) or (N, k) array)]. ``normals`` (N, 3), where given, become custom
    split normals. The mesh's materials and identity stay; the previous frame's attributes go."""
    pts = np.ascontiguousarray(points, np.float32).reshape(-1, 3)
    loops = np.zeros(0, np.int32) if loops is None else np.ascontiguousarray(loops, np.int32).ravel()
    starts = np.zeros(0, np.int32) if starts is None else np.ascontiguousarray(starts, np.int32).ravel()
    me.clear_geometry()  # removes every attribute of the previous frame too
    n = len(pts)
    if n:
        me.vertices.add(n)
        me.vertices.foreach_set("co", pts.ravel())
    if len(starts) and n:
        me.loops.add(len(loops))
        me.loops.foreach_set("vertex_index", loops)
        me.polygons.add(len(starts))
        me.polygons.foreach_set("loop_start", starts)
    if n:
        for name, a in (arrays.items() if isinstance(arrays, dict) else arrays):
            if a is not None and name.lower() not in RESERVED:
                attribute(me, name, a)
    me.update()
    if len(me.polygons):
        me.shade_smooth() if smooth else me.shade_flat()
        if normals is not None and len(normals) == n:
            me.normals_split_custom_set_from_vertices(np.asarray(normals, np.float32).reshape(-1, 3).tolist())
    return me


def attribute(me, name: str, a) -> None:
    """One point attribute: INT for whole numbers, FLOAT, FLOAT2 or FLOAT_VECTOR, else a FLOAT per component."""
    a = np.asarray(a)
    comps = 1 if a.ndim == 1 else a.shape[1]
    if a.dtype.kind in "iub" and comps == 1:
        me.attributes.new(name, "INT", "POINT").data.foreach_set("value", a.astype(np.int32))
    elif comps == 1:
        me.attributes.new(name, "FLOAT", "POINT").data.foreach_set("value", a.astype(np.float32))
    elif comps in (2, 3):
        kind = "FLOAT_VECTOR" if comps == 3 else "FLOAT2"
        me.attributes.new(name, kind, "POINT").data.foreach_set("vector", np.ascontiguousarray(a, np.float32).ravel())
    else:
        for c in range(comps):
            attribute(me, f"{name}_{c}", a[:, c].astype(np.float32))
