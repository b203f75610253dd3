"""Build and update the Blender scene of a run (bpy calls only).

Everything here runs inside a process that imported ``bpy``. The scene is
built once per process by :func:`build_scene`; :func:`load_frame` swaps in
the meshes and point clouds of one frame, so each rendered frame is a pure
function of the run's files and the render settings.

Motion blur: fluid meshes change topology every frame, so Blender cannot
match vertices between frames. Each fluid mesh carries the velocity that
splashsurf interpolated onto its vertices as a FLOAT_VECTOR point attribute
named ``velocity`` (m/s); Cycles turns that attribute into per-vertex motion
over the shutter interval when the topology is not stable. Foam points carry
the same attribute. Camera and obstacle motion blur come from keyframes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Render
from ..geometry import obstacle_transform
from ..errors import InputError
from ..io import read, read_mesh
from ..io.diffuse_types import COUNT_NAMES
from ..io.run import RunInfo
from .terrain import dress_terrain
from . import camera_follow, sea, stage



@dataclass
class SceneHandles:
    """The objects that change per frame."""

    fluid: object
    diffuse: dict  # type index -> object
    camera: object
    water: object
    sea: object = None  # sea.Sea with [render] sea = true


# ---------------------------------------------------------------------------- meshes
def read_surface(path: Path):
    """Vertices (N,3), faces (M,3), velocities (N,3) or None, from a mesh in any
    registered mesh format (PLY or OBJ, chosen by the io registry from the extension)."""
    m = read_mesh(path)
    return m.vertices, m.faces, m.arrays.get("velocity")


def make_mesh(name: str, verts: np.ndarray, faces: np.ndarray, velocity: np.ndarray | None = None, ids=None):
    """A new bpy mesh filled with foreach_set (fast for 100k+ elements)."""
    import bpy

    return fill_mesh(bpy.data.meshes.new(name), verts, faces, velocity, ids)


def fill_mesh(me, verts: np.ndarray, faces: np.ndarray, velocity: np.ndarray | None = None, ids=None):
    """Replace a mesh's geometry in place (its materials and identity stay)."""
    me.clear_geometry()
    for name in ("velocity", "id"):
        if name in me.attributes:
            me.attributes.remove(me.attributes[name])
    nv, nf = len(verts), len(faces)
    if nv:
        me.vertices.add(nv)
        me.vertices.foreach_set("co", np.ascontiguousarray(verts, np.float32).ravel())
    if nf:
        me.loops.add(3 * nf)
        me.loops.foreach_set("vertex_index", np.ascontiguousarray(faces, np.int32).ravel())
        me.polygons.add(nf)
        me.polygons.foreach_set("loop_start", np.arange(0, 3 * nf, 3, dtype=np.int32))
    if velocity is not None and nv:
        a = me.attributes.new("velocity", "FLOAT_VECTOR", "POINT")
        a.data.foreach_set("vector", np.ascontiguousarray(velocity, np.float32).ravel())
    if ids is not None and nv:
        a = me.attributes.new("id", "INT", "POINT")
        a.data.foreach_set("value", np.ascontiguousarray(ids, np.int64).astype(np.int32).ravel())
    me.update()
    if nf:
        me.shade_smooth()
    return me


# ---------------------------------------------------------------------------- materials
def _principled(mat):
    mat.use_nodes = True
    nt = mat.node_tree
    return nt, nt.nodes.get("Principled BSDF")


def water_material(cfg: Render):
    import bpy

    mat = bpy.data.materials.new("whitecap_water")
    nt, bsdf = _principled(mat)
    bsdf.inputs["Base Color"].default_value = (*cfg.water_color, 1.0)
    bsdf.inputs["Transmission Weight"].default_value = 1.0
    bsdf.inputs["IOR"].default_value = 1.33
    bsdf.inputs["Roughness"].default_value = cfg.water_roughness
    out = nt.nodes.get("Material Output")
    absorb = nt.nodes.new("ShaderNodeVolumeAbsorption")
    absorb.inputs["Color"].default_value = (*cfg.water_color, 1.0)
    absorb.inputs["Density"].default_value = cfg.water_absorption
    nt.links.new(absorb.outputs[0], out.inputs["Volume"])
    return mat


def foam_material():
    """Transparent + Emission mixed by a noise texture: soft, broken-up foam."""
    import bpy

    mat = bpy.data.materials.new("whitecap_foam")
    mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    mix = nt.nodes.new("ShaderNodeMixShader")
    transp = nt.nodes.new("ShaderNodeBsdfTransparent")
    emit = nt.nodes.new("ShaderNodeEmission")
    emit.inputs["Color"].default_value = (0.95, 0.97, 1.0, 1.0)
    emit.inputs["Strength"].default_value = 1.2
    # The glow is the foam's own brightness, not a light for the scene:
    # sampling thousands of tiny emitters as lights only adds noise and time.
    mat.cycles.emission_sampling = "NONE"
    noise = nt.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 40.0
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].position = 0.35
    ramp.color_ramp.elements[1].position = 0.65
    nt.links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
    nt.links.new(ramp.outputs["Color"], mix.inputs["Fac"])
    nt.links.new(transp.outputs[0], mix.inputs[1])
    nt.links.new(emit.outputs[0], mix.inputs[2])
    nt.links.new(mix.outputs[0], out.inputs["Surface"])
    return mat


def spray_material():
    import bpy

    mat = bpy.data.materials.new("whitecap_spray")
    _, bsdf = _principled(mat)
    bsdf.inputs["Base Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bsdf.inputs["Transmission Weight"].default_value = 0.6
    bsdf.inputs["Roughness"].default_value = 0.3
    return mat


def bubble_material():
    import bpy

    mat = bpy.data.materials.new("whitecap_bubbles")
    _, bsdf = _principled(mat)
    bsdf.inputs["Base Color"].default_value = (0.9, 0.97, 1.0, 1.0)
    bsdf.inputs["Transmission Weight"].default_value = 1.0
    bsdf.inputs["IOR"].default_value = 1.0 / 1.33  # air inside water
    bsdf.inputs["Roughness"].default_value = 0.05
    return mat


def thin_glass_material(color) -> "object":
    """A pane without thickness (an imported tank's wall that encloses the fluid): light passes
    straight through, tinted by ``color``, and glass's Fresnel share is reflected. A refracting
    glass would need walls with two faces (see stage.glass_material). The node graph is the
    add-on's (addon/looks.thin_glass), so a run looks the same in both; the add-on ships alone
    inside Blender, so it is the one that holds it."""
    import bpy

    from .addon import looks

    mat = bpy.data.materials.new("whitecap_obstacle_glass")
    looks.thin_glass(mat, color)
    return mat


def obstacle_material(entry: dict):
    import bpy

    if entry.get("material") == "glass":
        return thin_glass_material(entry.get("color", [0.93, 0.97, 0.96]))
    mat = bpy.data.materials.new(f"whitecap_obstacle_{entry.get('material', 'stone')}")
    _, bsdf = _principled(mat)
    bsdf.inputs["Base Color"].default_value = (*entry.get("color", [0.8, 0.78, 0.72]), 1.0)
    preset = entry.get("material", "stone")
    rough, metal = {"stone": (0.8, 0.0), "clay": (0.6, 0.0), "metal": (0.3, 1.0), "plastic": (0.35, 0.0)}.get(
        preset, (0.7, 0.0)
    )
    bsdf.inputs["Roughness"].default_value = rough
    bsdf.inputs["Metallic"].default_value = metal
    return mat


# ---------------------------------------------------------------------------- geometry nodes
# Render-time copies of a diffuse particle ([render] diffuse_copies) scatter within this many
# fluid particle radii of it: about where the particle's own generation cylinder spreads them.
COPY_JITTER = 1.0


def sphere_nodes(name: str, rmin: float, rmax: float, material, seed: int, copies: int = 1, jitter: float = 0.0):
    """Mesh to Points with a radius from Random Value seeded by the particle id; with
    ``copies`` > 1, each point is duplicated and the copies moved by a random offset in
    [−jitter, jitter]³ seeded by (id, copy), so they keep their place from frame to frame."""
    import bpy

    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin = ng.nodes.new("NodeGroupInput")
    gout = ng.nodes.new("NodeGroupOutput")
    m2p = ng.nodes.new("GeometryNodeMeshToPoints")
    m2p.mode = "VERTICES"
    rnd = ng.nodes.new("FunctionNodeRandomValue")
    rnd.data_type = "FLOAT"
    mins = [s for s in rnd.inputs if s.name == "Min" and s.enabled]
    maxs = [s for s in rnd.inputs if s.name == "Max" and s.enabled]
    mins[0].default_value = rmin
    maxs[0].default_value = rmax
    rnd.inputs["Seed"].default_value = seed
    pid = ng.nodes.new("GeometryNodeInputNamedAttribute")
    pid.data_type = "INT"
    pid.inputs["Name"].default_value = "id"
    ng.links.new(pid.outputs["Attribute"], rnd.inputs["ID"])
    val = [s for s in rnd.outputs if s.enabled][0]
    setm = ng.nodes.new("GeometryNodeSetMaterial")
    setm.inputs["Material"].default_value = material
    ng.links.new(gin.outputs[0], m2p.inputs["Mesh"])
    ng.links.new(val, m2p.inputs["Radius"])
    points = m2p.outputs["Points"]
    if copies > 1:
        points = _jittered_copies(ng, points, pid.outputs["Attribute"], copies, jitter, seed)
    ng.links.new(points, setm.inputs["Geometry"])
    ng.links.new(setm.outputs["Geometry"], gout.inputs[0])
    return ng


def _jittered_copies(ng, points, pid, copies: int, jitter: float, seed: int):
    """Duplicate Elements (copies − 1 more per point), then Set Position by a Random Value
    vector whose ID is id·copies + copy index: the same offsets every frame."""
    dup = ng.nodes.new("GeometryNodeDuplicateElements")
    dup.domain = "POINT"
    dup.inputs["Amount"].default_value = copies - 1
    ng.links.new(points, dup.inputs["Geometry"])
    join = ng.nodes.new("GeometryNodeJoinGeometry")
    ng.links.new(points, join.inputs[0])
    mul = ng.nodes.new("ShaderNodeMath")
    mul.operation = "MULTIPLY_ADD"
    ng.links.new(pid, mul.inputs[0])
    mul.inputs[1].default_value = float(copies)
    ng.links.new(dup.outputs["Duplicate Index"], mul.inputs[2])
    one = ng.nodes.new("ShaderNodeMath")
    one.operation = "ADD"
    ng.links.new(mul.outputs[0], one.inputs[0])
    one.inputs[1].default_value = 1.0  # copy 0 is the particle itself
    rnd = ng.nodes.new("FunctionNodeRandomValue")
    rnd.data_type = "FLOAT_VECTOR"
    vmin = [s_ for s_ in rnd.inputs if s_.name == "Min" and s_.enabled][0]
    vmax = [s_ for s_ in rnd.inputs if s_.name == "Max" and s_.enabled][0]
    vmin.default_value = (-jitter, -jitter, -jitter)
    vmax.default_value = (jitter, jitter, jitter)
    rnd.inputs["Seed"].default_value = seed + 100
    ng.links.new(one.outputs[0], rnd.inputs["ID"])
    setp = ng.nodes.new("GeometryNodeSetPosition")
    ng.links.new(dup.outputs["Geometry"], setp.inputs["Geometry"])
    ng.links.new([s_ for s_ in rnd.outputs if s_.enabled][0], setp.inputs["Offset"])
    ng.links.new(setp.outputs["Geometry"], join.inputs[0])
    return join.outputs[0]


# Sphere radius ranges of spray, foam and bubbles when [render] leaves them unset, as
# multiples of the fluid particle radius r: spray is small droplets, foam many small
# bubbles (not cotton balls), air bubbles in between.
DIFFUSE_RADIUS = ((0.1, 0.25), (0.15, 0.35), (0.1, 0.3))


def diffuse_radius(cfg: Render, t: int, r: float) -> tuple[float, float]:
    """[min, max] sphere radius of type t (0 spray, 1 foam, 2 bubbles) in metres."""
    own = (cfg.spray_radius, cfg.foam_radius, cfg.bubble_radius)[t]
    if own is not None:
        return float(own[0]), float(own[1])
    return DIFFUSE_RADIUS[t][0] * r, DIFFUSE_RADIUS[t][1] * r


# ---------------------------------------------------------------------------- stage
def _look_at(obj, target) -> None:
    import bpy

    empty = bpy.data.objects.new("camera_target", None)
    empty.location = target
    bpy.context.scene.collection.objects.link(empty)
    c = obj.constraints.new("TRACK_TO")
    c.target = empty
    c.track_axis = "TRACK_NEGATIVE_Z"
    c.up_axis = "UP_Y"
    return empty


GPU_BACKENDS = ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL")  # Cycles' GPU back-ends, preferred first


def cycles_device(want: str) -> str:
    """Enable the GPUs of the first back-end that has any and return "GPU", or "CPU".

    ``want`` is ``[render].device``: "cpu" never looks, "auto" falls back to the
    CPU, "gpu" without a GPU is an error.
    """
    import bpy

    if want == "cpu":
        return "CPU"
    prefs = bpy.context.preferences.addons["cycles"].preferences
    for backend in GPU_BACKENDS:
        try:
            devices = prefs.get_devices_for_type(backend)
        except (TypeError, ValueError, RuntimeError):  # back-end not built into this Blender
            continue
        gpus = [d for d in devices if d.type != "CPU"]
        if gpus:
            prefs.compute_device_type = backend
            for d in devices:
                d.use = d.type != "CPU"
            return "GPU"
    if want == "gpu":
        raise InputError(f"render.device = 'gpu': Cycles found no GPU ({', '.join(GPU_BACKENDS)}); use 'auto' or 'cpu'")
    return "CPU"


def build_scene(info: RunInfo, cfg: Render, quality: str, first: int, last: int,
                run_dir: Path | None = None) -> SceneHandles:
    """A fresh Blender scene for frames first..last of a run: Cycles settings, the
    stage (sky or HDRI and sun, ground, container: render/stage.py), the fluid and
    diffuse objects (filled per frame), obstacles, the camera path and compositing.
    ``run_dir`` lets the camera frame the fluid's bounds over the run and resolves
    relative image paths (without it the camera frames the domain)."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    _configure_cycles(sc, cfg, quality == "preview")
    _configure_output(sc, info.frame_rate, first, last)
    stage.set_exposure(sc, cfg)
    stage.add_environment(sc, cfg, stage.environment_path(cfg, info, run_dir or Path(".")), quality == "preview")
    if cfg.ground:
        stage.add_ground(sc, cfg, info, quality == "preview")
    stage.add_container(sc, cfg, info, quality == "preview")
    water = water_material(cfg)
    fluid = bpy.data.objects.new("fluid", bpy.data.meshes.new("fluid_empty"))
    fluid.data.materials.append(water)
    sc.collection.objects.link(fluid)
    open_sea = sea.add_sea(sc, cfg, info, water, run_dir) if cfg.sea else None
    diffuse = _add_diffuse_objects(sc, cfg, info)
    for k, entry in enumerate(info.obstacles):
        keyframe_body(_add_obstacle(entry, k, info, run_dir), k, info, first, last)
    dress_terrain(sc, info, run_dir, quality == "preview")  # [terrain]: its material (render/terrain.py)
    cam = _add_camera(sc, cfg, info, first, last, run_dir)
    _compositing(sc, cfg)
    return SceneHandles(fluid=fluid, diffuse=diffuse, camera=cam, water=water, sea=open_sea)


def _configure_cycles(sc, cfg: Render, preview: bool) -> None:
    """Cycles on the chosen device; resolution, samples, bounces and denoising for the quality."""
    sc.render.engine = "CYCLES"
    sc.cycles.device = cycles_device(cfg.device)
    w, h = cfg.preview_resolution if preview else cfg.resolution
    sc.render.resolution_x, sc.render.resolution_y = int(w), int(h)
    sc.render.resolution_percentage = 100
    sc.cycles.samples = cfg.preview_samples if preview else cfg.samples
    sc.cycles.use_adaptive_sampling = True
    sc.cycles.use_denoising = bool(cfg.denoise)
    sc.render.use_persistent_data = True  # keep static geometry (ground, obstacles) between frames
    # The stage is lit by one sun and the sky, and the foam's emission is not
    # sampled as a light (foam_material), so a light tree has nothing to sort:
    # without it a preview frame is about 0.25 s faster at the same noise.
    sc.cycles.use_light_tree = False
    if preview:
        # Fewer light bounces: enough for water seen through one surface.
        sc.cycles.max_bounces = 6
        sc.cycles.transmission_bounces = 6
        sc.cycles.glossy_bounces = 2
        sc.cycles.diffuse_bounces = 2
        # No reflective caustics, and OpenImageDenoise's fast network. The
        # albedo/normal prefilter stays accurate: without it foam seen through
        # the water turns to grain. Refractive caustics stay on: without them
        # the sun cannot light anything under the water surface, and water
        # seen from above (an imported open tank) renders black; with them the
        # DualSPHysics preview frame took the same 1.46 s.
        sc.cycles.caustics_reflective = False
        sc.cycles.denoising_quality = "FAST"
        # Adaptive sampling may stop a pixel after 4 samples once its noise is
        # below 5% (Cycles' default 1% suits final frames): the denoiser
        # smooths the rest, and smooth sky, ground and glass stop early.
        sc.cycles.adaptive_threshold = 0.05
        sc.cycles.adaptive_min_samples = 4
    sc.render.use_motion_blur = bool(cfg.motion_blur)
    sc.render.motion_blur_shutter = cfg.shutter


def _configure_output(sc, fps: float, first: int, last: int) -> None:
    """Frame rate (fractional rates through fps_base), frame range and PNG output."""
    sc.render.fps = max(1, int(round(fps)))
    sc.render.fps_base = sc.render.fps / fps
    sc.frame_start, sc.frame_end = first, last
    sc.render.image_settings.file_format = "PNG"
    sc.render.film_transparent = False
    # No metadata in the PNGs: Blender stamps the date and Cycles' render times into
    # text chunks, so the same frame rendered twice (or on another worker) would differ
    # in its bytes. With every stamp field off no text chunk is written at all.
    for name in _STAMP_FIELDS:
        setattr(sc.render, f"use_stamp_{name}", False)


#: Blender's per-image metadata fields (RenderSettings.use_stamp_*), all turned off
_STAMP_FIELDS = ("date", "time", "render_time", "frame", "frame_range", "memory", "hostname", "camera", "lens",
                 "scene", "marker", "filename", "sequencer_strip", "note")


def _add_diffuse_objects(sc, cfg: Render, info: RunInfo) -> dict:
    """One point-cloud object per diffuse type, drawn as spheres; type code -> object."""
    import bpy

    r = info.particle_radius
    diffuse = {}
    mats = (spray_material(), foam_material(), bubble_material())
    for t, name in enumerate(COUNT_NAMES):
        rmin, rmax = diffuse_radius(cfg, t, r)
        obj = bpy.data.objects.new(name, bpy.data.meshes.new(f"{name}_empty"))
        mod = obj.modifiers.new(name, "NODES")
        mod.node_group = sphere_nodes(f"{name}_spheres", rmin, rmax, mats[t], seed=t + 1,
                                      copies=cfg.diffuse_copies, jitter=COPY_JITTER * r)
        sc.collection.objects.link(obj)
        diffuse[t] = obj
    return diffuse


def _add_camera(sc, cfg: Render, info: RunInfo, first: int, last: int, run_dir: Path | None):
    """The camera, keyframed from start to end (and around the orbit) over first..last;
    without camera keys it frames the fluid and the obstacles (stage.camera_path)."""
    import bpy
    from mathutils import Vector

    cam_data = bpy.data.cameras.new("camera")
    cam_data.lens = cfg.lens
    cam = bpy.data.objects.new("camera", cam_data)
    sc.collection.objects.link(cam)
    sc.camera = cam
    boxes = [np.array([tuple(o.matrix_world @ Vector(c)) for c in o.bound_box])
             for o in sc.objects if o.name.startswith("obstacle_")]
    bounds = stage.scene_bounds(run_dir, info, boxes)
    aspect = sc.render.resolution_x / sc.render.resolution_y
    targets = None
    if camera_follow.active(cfg):  # a follow camera or preset: its look-at point moves too
        keys, targets = camera_follow.follow_keys(cfg, info, bounds, first, last, aspect, run_dir)
        target = targets[first]
    else:
        keys, target = stage.camera_keys(cfg, info, bounds, first, last, aspect)
    cam_data.clip_start, cam_data.clip_end = stage.camera_clip(keys[first], target)
    empty = _look_at(cam, target)
    stage.depth_of_field(cam, cfg, empty)
    for frame, p in (targets or {}).items():
        empty.location = p
        empty.keyframe_insert("location", frame=frame)
    for frame, p in keys.items():
        cam.location = p
        cam.keyframe_insert("location", frame=frame)
    return cam


def _add_obstacle(entry: dict, k: int, info: RunInfo, run_dir: Path | None) -> None:
    """The high-poly render mesh of an obstacle, with the scene's transform."""
    import bpy

    m = stage.obstacle_render_mesh(entry, info, run_dir)
    if m is None:
        return
    m.apply_transform(obstacle_transform(entry))
    obj = bpy.data.objects.new(f"obstacle_{k}", make_mesh(f"obstacle_{k}", m.vertices, m.faces))
    obj.data.materials.append(obstacle_material(entry))
    stage.apply_texture(obj, m, entry, k, info, run_dir or Path("."))
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _compositing(sc, cfg: Render) -> None:
    """Denoise (when the build has OpenImageDenoise) and a light glare, through the 5.x compositor."""
    import bpy

    if cfg.glare <= 0:
        return
    try:
        ng = bpy.data.node_groups.new("whitecap_compositing", "CompositorNodeTree")
        ng.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        rl = ng.nodes.new("CompositorNodeRLayers")
        glare = ng.nodes.new("CompositorNodeGlare")
        glare.inputs["Strength"].default_value = cfg.glare
        glare.inputs["Threshold"].default_value = 1.0
        out = ng.nodes.new("NodeGroupOutput")
        ng.links.new(rl.outputs["Image"], glare.inputs["Image"])
        ng.links.new(glare.outputs["Image"], out.inputs[0])
        sc.compositing_node_group = ng
    except Exception:  # older/newer compositor API: render without glare rather than fail
        pass


# ---------------------------------------------------------------------------- per frame
def load_frame(h: SceneHandles, run_dir: Path, info: RunInfo, index: int) -> dict:
    """Replace the fluid mesh and diffuse point clouds with frame ``index``'s files."""
    import bpy

    frame = info.frame(index)
    files = frame["files"]
    stats = {"triangles": 0, "diffuse": [0, 0, 0]}
    if "mesh" in files:
        verts, faces, vel = read_surface(run_dir / files["mesh"])
        if h.sea is not None:  # one open sheet with the sea: the faces on the walls and floor go
            faces = sea.open_walls(verts, faces, info.domain["lower"], info.domain["upper"], info.particle_radius)
        fill_mesh(h.fluid.data, verts, faces, vel)
        stats["triangles"] = len(faces)
    if h.sea is not None:
        sea.update_sea(h.sea, verts if "mesh" in files else np.zeros((0, 3)), frame["time"])
    if "diffuse" in files:
        d = read(run_dir / files["diffuse"])
        types = d.arrays.get("type", np.zeros(len(d), np.uint8))
        for t, obj in h.diffuse.items():
            sel = types == t
            fill_mesh(
                obj.data, d.positions[sel], np.zeros((0, 3), np.int32),
                d.velocities[sel] if d.velocities is not None else None, ids=d.ids[sel],
            )
            stats["diffuse"][t] = int(sel.sum())
    bpy.context.scene.frame_set(index)
    return stats


def keyframe_body(obj, k: int, info: RunInfo, first: int, last: int) -> None:
    """Keyframe a moving obstacle's pose from run.json on every frame first..last.

    The mesh holds the rest placement; the object's location and quaternion are the
    body's pose (``frames[i].bodies[k]``, w x y z as Blender orders it), so the world
    placement is ``geometry.obstacle_matrix`` and object motion blur comes from the keys."""
    if obj is None:
        return
    keyed = False
    for f in info.frames:
        i = f["index"]
        body = info.body_pose(i, k)
        if body is None or not (first <= i <= last):
            continue
        obj.rotation_mode = "QUATERNION"
        obj.location = body["position"]
        obj.rotation_quaternion = body["quaternion"]
        obj.keyframe_insert("location", frame=i)
        obj.keyframe_insert("rotation_quaternion", frame=i)
        keyed = True
    if keyed and obj.animation_data and obj.animation_data.action:
        _linear_keys(obj.animation_data.action)


def _linear_keys(action) -> None:
    """Linear interpolation between the per-frame keys (no Bézier overshoot between frames)."""
    curves = getattr(action, "fcurves", None)
    if curves is None:  # Blender 5 layered actions
        curves = [c for layer in action.layers for strip in layer.strips for bag in strip.channelbags
                  for c in bag.fcurves]
    for c in curves:
        for kp in c.keyframe_points:
            kp.interpolation = "LINEAR"
