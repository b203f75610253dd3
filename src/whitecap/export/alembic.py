"""Alembic: a whole run as one ``.abc`` archive, through Blender's own Alembic exporter (``bpy``).

No maintained Alembic package is on the package registry, and bpy is
already a dependency. The content is the USD stage's (:mod:`whitecap.export.usd`):
the stage is written to a temporary directory, Blender imports it (its
importer reads the per-frame layers through USD's value clips, so the fluid
mesh, its ``velocity`` attribute and the particles follow the frame), and
Blender's Alembic exporter writes every frame from first to last into one
archive, which is renamed into place when complete.

What Alembic gets:

- the fluid mesh per frame with ``.velocities`` (Blender writes them from the
  mesh's ``velocity`` attribute), so renderers motion-blur it;
- each diffuse type (and the fluid particles of a run without a surface) as
  a mesh of vertices only, with velocities: Blender's exporter writes no
  point clouds, and a vertex-only mesh keeps positions and velocities. Alembic
  meshes hold no per-point widths or ids, so each of these objects carries
  its sphere radius range as custom properties (``whitecap_radius_min`` and
  ``_max`` [m]) in the archive's user properties;
- obstacles with their transform per frame, and the camera.

Blender runs in a child process, like the renderer, so a caller holding a
Taichi runtime never loads it.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

from ..errors import InputError, MissingDependency
from ..io.atomic import atomic_path
from ..io.cache import SceneCache
from ..io.registry import SCENE, register

INSTALL_HINT = "install it with: pip install bpy==5.0.1 (needs Python 3.11 and numpy<2)"


def require_bpy() -> None:
    try:
        import importlib.util

        found = importlib.util.find_spec("bpy") is not None
    except (ImportError, ValueError):
        found = False
    if not found:
        raise MissingDependency(
            f"Alembic export needs Blender's Python module 'bpy', which is not installed; {INSTALL_HINT}"
        )


def write_abc(path: str | Path, cache: SceneCache, advance: Callable[[str], None] | None = None) -> None:
    """Write ``cache`` as one Alembic archive at ``path`` (see the module docstring)."""
    from ..workers import child_env
    from .usd import point_path, require_pxr, write_usd

    require_bpy()
    require_pxr()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".abc-", dir=path.parent) as work:
        usd = Path(work) / "scene.usd"
        write_usd(usd, cache, advance)
        # Blender names each point cloud after its prim: the radius range goes to that object.
        radii = {point_path(n).rsplit("/", 1)[1]: list(r) for n, r in cache.radii.items()}
        job = {"usd": str(usd), "first": cache.first, "last": cache.last, "fps": cache.frame_rate, "radii": radii}
        with atomic_path(path) as tmp:
            job["abc"] = str(tmp)
            res = subprocess.run([sys.executable, "-m", "whitecap.export.alembic", json.dumps(job)],
                                 capture_output=True, text=True, env=child_env())
            if res.returncode != 0 or not tmp.stat().st_size:
                last = (res.stderr.strip().splitlines() or ["no output"])[-1]
                raise InputError(f"{path}: Blender's Alembic export failed: {last}")
    if advance:
        advance(path.name)


# ---------------------------------------------------------------------------- in Blender
def _vertex_object(bpy, cloud, radius: list[float] | None):
    """A mesh object whose geometry is ``cloud``'s points as vertices (attributes, velocity
    included, carried over by Points to Vertices), with the cloud's name and parent."""
    name = cloud.name
    cloud.name = f"{name}_cloud"
    ng = bpy.data.node_groups.new(f"{name}_vertices", "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    info = ng.nodes.new("GeometryNodeObjectInfo")
    info.transform_space = "RELATIVE"
    info.inputs["Object"].default_value = cloud
    to_vertices = ng.nodes.new("GeometryNodePointsToVertices")
    out = ng.nodes.new("NodeGroupOutput")
    ng.nodes.new("NodeGroupInput")
    ng.links.new(info.outputs["Geometry"], to_vertices.inputs["Points"])
    ng.links.new(to_vertices.outputs["Mesh"], out.inputs[0])
    obj = bpy.data.objects.new(name, bpy.data.meshes.new(name))
    obj.parent = cloud.parent
    obj.matrix_parent_inverse = cloud.matrix_parent_inverse.copy()
    obj.matrix_basis = cloud.matrix_basis.copy()
    obj.modifiers.new("points_to_vertices", "NODES").node_group = ng
    if radius:
        obj["whitecap_radius_min"], obj["whitecap_radius_max"] = float(radius[0]), float(radius[1])
    for c in cloud.users_collection:
        c.objects.link(obj)
    return obj


def export_in_blender(job: dict) -> None:
    """Import the USD stage, turn point clouds into vertex meshes, export Alembic (runs inside bpy)."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    # Alembic stores seconds: frame i is at i / fps (fractional rates through fps_base).
    fps = float(job["fps"])
    sc.render.fps = max(1, int(round(fps)))
    sc.render.fps_base = sc.render.fps / fps
    bpy.ops.wm.usd_import(filepath=job["usd"])
    sc.frame_start, sc.frame_end = int(job["first"]), int(job["last"])
    clouds = [o for o in bpy.data.objects if o.type == "POINTCLOUD"]
    for cloud in clouds:
        _vertex_object(bpy, cloud, job["radii"].get(cloud.name))
    bpy.ops.object.select_all(action="DESELECT")
    for o in bpy.data.objects:
        o.select_set(o.type != "POINTCLOUD")
    ok = bpy.ops.wm.alembic_export(filepath=job["abc"], start=sc.frame_start, end=sc.frame_end, selected=True,
                                   export_custom_properties=True, as_background_job=False,
                                   evaluation_mode="RENDER", init_scene_frame_range=False)
    if "FINISHED" not in ok:
        raise SystemExit(f"alembic_export returned {ok}")


def main() -> None:
    from ..workers import die_with_parent, run_then_end

    die_with_parent()
    run_then_end(lambda: export_in_blender(json.loads(sys.argv[1])))  # without Blender's teardown (end_process)


register("abc", (".abc",), writer=write_abc, kind=SCENE)

if __name__ == "__main__":
    main()
