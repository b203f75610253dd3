"""Wavefront OBJ surface meshes (trimesh's exporter/loader).

OBJ stores positions, normals and faces only: the velocity attribute is
dropped on write.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import atomic_path
from .mesh import SurfaceMesh
from .registry import MESH, register


def write_mesh_obj(path: Path, mesh: SurfaceMesh) -> None:
    import trimesh

    with atomic_path(path) as tmp:
        if len(mesh.faces) == 0:
            # trimesh refuses to export an empty mesh; an OBJ with no
            # statements is a valid empty mesh.
            tmp.write_text("# whitecap: empty surface\n")
            return
        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_normals=mesh.normals, process=False)
        text = trimesh.exchange.obj.export_obj(tm, include_normals=mesh.normals is not None,
                                               include_color=False, include_texture=False)
        tmp.write_text(text)


def read_mesh_obj(path: Path) -> SurfaceMesh:
    import trimesh

    try:
        tm = trimesh.load_mesh(str(path), file_type="obj", process=False)
    except Exception as exc:
        raise InputError(f"{path}: not a readable OBJ file ({exc})") from None
    if len(tm.vertices) == 0:
        return SurfaceMesh.empty()
    return SurfaceMesh(np.asarray(tm.vertices), np.asarray(tm.faces), np.asarray(tm.vertex_normals),
                       source=str(path))


register("obj", (".obj",), read_mesh_obj, write_mesh_obj, kind=MESH)
