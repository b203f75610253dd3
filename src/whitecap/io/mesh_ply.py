"""Binary little-endian PLY surface meshes (plyfile).

Vertex element: ``x y z nx ny nz vx vy vz`` (float32); face element:
``vertex_indices`` (uchar count, int32 indices). Blender's PLY importer and
ParaView read this layout directly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import atomic_path
from .mesh import SurfaceMesh
from .registry import MESH, register

_VERTEX = ("x", "y", "z", "nx", "ny", "nz", "vx", "vy", "vz")
_FACE_DTYPE = np.dtype([("n", "u1"), ("i", "<i4", (3,))])  # packed: 13 bytes per triangle
_TRIANGLES = {"face": {"vertex_indices": 3}}  # plyfile maps such lists from the file in one go


def write_mesh_ply(path: Path, mesh: SurfaceMesh) -> None:
    # Written with numpy rather than plyfile: plyfile packs list properties
    # (the face indices) row by row in Python, about 3 us per triangle, which
    # was as slow as the reconstruction itself. A binary PLY of fixed-size
    # records is just a header plus two packed arrays; plyfile reads it back.
    n = len(mesh.vertices)
    normals = mesh.normals if mesh.normals is not None else np.zeros((n, 3), np.float32)
    vel = mesh.arrays.get("velocity", np.zeros((n, 3), np.float32))
    vert = np.concatenate([mesh.vertices, normals, vel], axis=1).astype("<f4", copy=False)
    face = np.empty(len(mesh.faces), dtype=_FACE_DTYPE)
    face["n"] = 3
    face["i"] = mesh.faces
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0", "comment whitecap surface mesh", f"element vertex {n}"]
        + [f"property float {k}" for k in _VERTEX]
        + [f"element face {len(face)}", "property list uchar int vertex_indices", "end_header"]
    ) + "\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(np.ascontiguousarray(vert).tobytes())
            fh.write(face.tobytes())


def read_mesh_ply(path: Path) -> SurfaceMesh:
    from .ply import read_vertices

    ply, v, names = read_vertices(path, _TRIANGLES)

    def vec(a, b, c):
        return np.stack([v[a], v[b], v[c]], axis=1) if all(k in names for k in (a, b, c)) else None

    faces = np.zeros((0, 3), np.int32)
    if "face" in ply and ply["face"].count:
        lists = ply["face"].data["vertex_indices"]
        if lists.dtype != object:  # binary: mapped as fixed-length triangles
            faces = np.array(lists, np.int32)
        else:  # ASCII PLY: one list per row
            try:
                faces = np.stack([np.asarray(f) for f in lists]).astype(np.int32)
            except ValueError:
                raise InputError(f"{path}: only triangle faces are supported") from None
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise InputError(f"{path}: only triangle faces are supported")
    vel = vec("vx", "vy", "vz")
    return SurfaceMesh(vec("x", "y", "z"), faces, vec("nx", "ny", "nz"),
                       {"velocity": vel} if vel is not None else {}, source=str(path))


register("ply", (".ply",), read_mesh_ply, write_mesh_ply, kind=MESH)
