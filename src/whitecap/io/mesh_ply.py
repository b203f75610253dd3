"""Binary little-endian PLY surface meshes (plyfile).

Vertex element: ``x y z nx ny nz vx vy vz`` (float32); face element:
``vertex_indices`` (uchar count, int32 indices). Blender's PLY importer and
ParaView read this layout directly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from ..errors import InputError
from .atomic import atomic_path
from .mesh import SurfaceMesh, register_mesh


def write_mesh_ply(path: Path, mesh: SurfaceMesh) -> None:
    n = len(mesh.vertices)
    normals = mesh.normals if mesh.normals is not None else np.zeros((n, 3), np.float32)
    vel = mesh.arrays.get("velocity", np.zeros((n, 3), np.float32))
    cols = [("x", mesh.vertices[:, 0]), ("y", mesh.vertices[:, 1]), ("z", mesh.vertices[:, 2]),
            ("nx", normals[:, 0]), ("ny", normals[:, 1]), ("nz", normals[:, 2]),
            ("vx", vel[:, 0]), ("vy", vel[:, 1]), ("vz", vel[:, 2])]
    vert = np.empty(n, dtype=[(k, "<f4") for k, _ in cols])
    for k, a in cols:
        vert[k] = a
    face = np.empty(len(mesh.faces), dtype=[("vertex_indices", "<i4", (3,))])
    face["vertex_indices"] = mesh.faces
    elements = [PlyElement.describe(vert, "vertex"),
                PlyElement.describe(face, "face", len_types={"vertex_indices": "u1"})]
    with atomic_path(path) as tmp:
        PlyData(elements, byte_order="<").write(str(tmp))


def read_mesh_ply(path: Path) -> SurfaceMesh:
    try:
        ply = PlyData.read(str(path))
    except Exception as exc:  # plyfile raises a variety of types on garbage
        raise InputError(f"{path}: not a readable PLY file ({exc})") from None
    if "vertex" not in ply:
        raise InputError(f"{path}: PLY has no 'vertex' element")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    for k in ("x", "y", "z"):
        if k not in names:
            raise InputError(f"{path}: PLY vertex element has no '{k}' property")

    def vec(a, b, c):
        return np.stack([v[a], v[b], v[c]], axis=1) if all(k in names for k in (a, b, c)) else None

    faces = np.zeros((0, 3), np.int32)
    if "face" in ply and ply["face"].count:
        lists = ply["face"].data["vertex_indices"]
        try:
            faces = np.stack([np.asarray(f) for f in lists]).astype(np.int32)
        except ValueError:
            raise InputError(f"{path}: only triangle faces are supported") from None
        if faces.shape[1] != 3:
            raise InputError(f"{path}: only triangle faces are supported")
    vel = vec("vx", "vy", "vz")
    return SurfaceMesh(vec("x", "y", "z"), faces, vec("nx", "ny", "nz"),
                       {"velocity": vel} if vel is not None else {}, source=str(path))


register_mesh("ply", (".ply",), read_mesh_ply, write_mesh_ply)
