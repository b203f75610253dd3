"""Loading a run into a Blender scene: the parts ``whitecap render`` and the add-on share
(bpy inside functions).

- :func:`current_files`: a kind's files made from the run's current simulation;
- :func:`obstacle_mesh_file`: where an obstacle's mesh is (io/run.obstacle_path: the
  scene's folder, else the run's own folder);
- :func:`add_stage`: what a scene needs to render a run: the camera, lights, world and
  the stage's objects (ground, container...) with the render settings of the run's
  ``render/scene.blend`` when ``whitecap render`` saved one, else a sky, a sun and a
  camera that frames the domain.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from ..io.record import Obstacle
from ..io.run import RunInfo, obstacle_path

#: The run's own objects in render/scene.blend, which the add-on makes itself (per frame).
RUN_OBJECTS = re.compile(r"^(fluid|spray|foam|bubbles|obstacle_\d+)(\.\d+)?$")
#: Default stage without a scene.blend: sun elevation and strength, the sky's colour and strength.
SUN_ANGLE = (40.0, 0.0, 30.0)  # degrees, as [render] sun_angle
SUN_STRENGTH = 3.0  # W/m^2, [render] sun_strength
SKY_COLOR = (0.6, 0.75, 0.95)
SKY_STRENGTH = 0.6
#: The default camera looks at the domain from this direction (front, right, above), as render/stage.
VIEW_DIRECTION = (0.35, -1.0, 0.55)
#: The default camera's distance in domain diagonals.
VIEW_DISTANCE = 1.4


def current_files(info: RunInfo, kind: str) -> list[tuple[int, str]]:
    """(frame, relative path) of a kind's files made from the run's current simulation (an
    entry from an earlier simulation is stale: RunInfo.load left it out)."""
    return sorted(info.files(kind))


def obstacle_mesh_file(entry: Obstacle, info: RunInfo, run_dir) -> Path | None:
    """An obstacle's render mesh (else its collision mesh) file, or None when missing."""
    src = entry.render_file
    return obstacle_path(src, info, run_dir) if src else None


def _copy_settings(dst, src) -> None:
    """Copy every writable plain property of one RNA struct onto another (render settings)."""
    for p in src.bl_rna.properties:
        if p.is_readonly or p.identifier == "rna_type" or p.type in ("POINTER", "COLLECTION"):
            continue
        try:
            setattr(dst, p.identifier, getattr(src, p.identifier))
        except (AttributeError, TypeError, ValueError):
            pass


def add_stage(sc, run_dir, info: RunInfo) -> list:
    """Camera, lights, world and stage objects for ``sc``; returns the objects made."""
    blend = Path(run_dir) / "render" / "scene.blend"
    if blend.is_file():
        return _stage_from_blend(sc, blend)
    return _default_stage(sc, info)


def _stage_from_blend(sc, blend: Path) -> list:
    """The stage of ``whitecap render``'s saved scene: its objects other than the run's own, its
    world and camera, and its render, Cycles and colour settings."""
    import bpy

    with bpy.data.libraries.load(str(blend), link=False) as (src, dst):
        dst.scenes = src.scenes[:1]
    saved = dst.scenes[0]
    made = []
    for obj in list(saved.objects):
        if RUN_OBJECTS.match(obj.name):
            continue
        sc.collection.objects.link(obj)
        made.append(obj)
    sc.world = saved.world
    sc.camera = saved.camera
    fps, fps_base, first, last = sc.render.fps, sc.render.fps_base, sc.frame_start, sc.frame_end
    _copy_settings(sc.render, saved.render)
    _copy_settings(sc.render.image_settings, saved.render.image_settings)
    _copy_settings(sc.cycles, saved.cycles)
    _copy_settings(sc.view_settings, saved.view_settings)
    sc.render.fps, sc.render.fps_base, sc.frame_start, sc.frame_end = fps, fps_base, first, last
    sc.render.filepath = "//render/"
    if getattr(saved, "compositing_node_group", None) is not None:
        sc.compositing_node_group = saved.compositing_node_group
        for node in sc.compositing_node_group.nodes:  # its Render Layers read the saved scene, which goes
            if node.bl_idname == "CompositorNodeRLayers":
                node.scene = sc
    leftovers = [o for o in saved.objects if o not in made]
    bpy.data.scenes.remove(saved)
    for o in leftovers:
        if o.users == 0:
            data = o.data
            bpy.data.objects.remove(o)
            if data is not None and data.users == 0 and isinstance(data, bpy.types.Mesh):
                bpy.data.meshes.remove(data)
    return made


def _default_stage(sc, info: RunInfo) -> list:
    """A sky-coloured world, a sun, and a camera looking at the domain's centre."""
    import bpy
    from mathutils import Vector

    world = bpy.data.worlds.new("whitecap_sky")
    world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    bg.inputs["Color"].default_value = (*SKY_COLOR, 1.0)
    bg.inputs["Strength"].default_value = SKY_STRENGTH
    sc.world = world
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = SUN_STRENGTH
    sun.rotation_euler = [math.radians(a) for a in SUN_ANGLE]
    sc.collection.objects.link(sun)
    lo, hi = Vector(info.domain["lower"]), Vector(info.domain["upper"])
    centre, size = (lo + hi) / 2, max((hi - lo).length, 1e-3)
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    cam.location = centre + Vector(VIEW_DIRECTION).normalized() * size * VIEW_DISTANCE
    cam.rotation_mode = "QUATERNION"
    cam.rotation_quaternion = (centre - cam.location).to_track_quat("-Z", "Y")
    cam.data.clip_start, cam.data.clip_end = size * 1e-3, size * 100
    sc.collection.objects.link(cam)
    sc.camera = cam
    return [sun, cam]
