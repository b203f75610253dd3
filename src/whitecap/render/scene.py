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
from typing import Any

import numpy as np

from ..blender import looks, mesh as blender_mesh, place
from ..blender.mesh import polygons_of
from ..config import Render
from ..errors import InputError
from ..io import read, read_mesh
from ..io.record import Obstacle
from ..io.run import RunInfo
from . import camera_follow, sea, stage
from .sea import Sea
from .terrain import dress_terrain, scene_terrain


@dataclass
class SceneHandles:
    """The objects that change per frame."""

    fluid: Any  # Blender objects
    diffuse: dict[int, Any]  # type index -> object
    camera: Any
    water: Any
    sea: Sea | None = None  # with [render] sea = true
    droplet_volume: float = 0.0  # fluid-mesh pieces smaller than this [m³] get the spray material


# ---------------------------------------------------------------------------- meshes
def read_surface(path: Path):
    """Vertices (N,3), faces (M,3), velocities (N,3) or None and normals (N,3) or None, from a
    mesh in any registered mesh format (PLY or OBJ, chosen by the io registry from the extension)."""
    m = read_mesh(path)
    return m.vertices, m.faces, m.arrays.get("velocity"), m.normals


def make_mesh(name: str, verts: np.ndarray, faces: np.ndarray, velocity: np.ndarray | None = None, ids=None):
    """A new bpy mesh filled with foreach_set (fast for 100k+ elements)."""
    import bpy

    return fill_mesh(bpy.data.meshes.new(name), verts, faces, velocity, ids)


def fill_mesh(me, verts: np.ndarray, faces: np.ndarray, velocity: np.ndarray | None = None, ids=None,
              normals: np.ndarray | None = None):
    """Replace a mesh's geometry in place with triangles (its materials and identity stay):
    the shared mesh fill (blender/mesh.py) with the ``velocity`` and ``id`` attributes and the
    file's normals (splashsurf's smoothed ones) as custom split normals, as the add-on shows them."""
    loops, starts = polygons_of(faces)
    arrays = [("velocity", velocity), ("id", None if ids is None else np.asarray(ids, np.int64))]
    return blender_mesh.fill_mesh(me, verts, loops, starts, arrays, normals)


def small_pieces(verts: np.ndarray, faces: np.ndarray, volume: float) -> np.ndarray:
    """Per face, whether it belongs to a connected piece of the mesh enclosing less than
    ``volume`` [m³] (the divergence theorem over the piece's triangles; a piece cut open by
    open_walls is a large one anyway)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return np.zeros(0, bool)
    n = len(verts)
    a = np.concatenate([f[:, 0], f[:, 1]])
    b = np.concatenate([f[:, 1], f[:, 2]])
    _, label = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)
    v = np.asarray(verts, float)[f]
    six_v = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2]))
    piece = label[f[:, 0]]
    enclosed = np.abs(np.bincount(piece, six_v, minlength=label.max() + 1)) / 6
    return enclosed[piece] < volume


def diffuse_radius(cfg: Render, t: int, r: float) -> tuple[float, float]:
    """[min, max] sphere radius of type t (0 spray, 1 foam, 2 bubbles) in metres: [render]'s
    own range, else io/diffuse_types.DIFFUSE_RADIUS x r (blender/looks.diffuse_radius)."""
    return looks.diffuse_radius(t, r, (cfg.spray_radius, cfg.foam_radius, cfg.bubble_radius)[t])


# ---------------------------------------------------------------------------- stage
def _look_at(obj, target) -> Any:
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
    water = looks.material("FLUID", color=cfg.water_color, absorption=cfg.water_absorption,
                           roughness=cfg.water_roughness)
    fluid = bpy.data.objects.new("fluid", bpy.data.meshes.new("fluid_empty"))
    fluid.data.materials.append(water)
    sc.collection.objects.link(fluid)
    droplet_volume = cfg.droplet_particles * info.particle_mass / info.rest_density
    if droplet_volume > 0:
        fluid.data.materials.append(looks.material("SPRAY"))  # material index 1: small_pieces
    open_sea = sea.add_sea(sc, cfg, info, water, run_dir) if cfg.sea else None
    diffuse = _add_diffuse_objects(sc, cfg, info)
    extra = scene_terrain(info, run_dir)  # an imported run's scene.toml [terrain]
    for k, entry in enumerate([*info.obstacles, *extra]):
        _add_obstacle(entry, k, info, run_dir, first, last)
    dress_terrain(sc, info, run_dir, quality == "preview", extra)  # [terrain]: its material (render/terrain.py)
    cam = _add_camera(sc, cfg, info, first, last, run_dir)
    _compositing(sc, cfg)
    return SceneHandles(fluid=fluid, diffuse=diffuse, camera=cam, water=water, sea=open_sea,
                        droplet_volume=droplet_volume)


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
    """One point-cloud object per diffuse type, drawn as spheres (blender/looks); type code -> object."""
    return looks.diffuse_objects(sc.collection, info.particle_radius,
                                 (cfg.spray_radius, cfg.foam_radius, cfg.bubble_radius), cfg.diffuse_copies)


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


def _add_obstacle(entry: Obstacle, k: int, info: RunInfo, run_dir: Path | None, first: int, last: int):
    """The high-poly render mesh of an obstacle, placed and (a moving body) keyed as the add-on
    places it (blender/place.py)."""
    import bpy

    m = stage.obstacle_render_mesh(entry, info, run_dir)
    if m is None:
        return None
    me = make_mesh(f"obstacle_{k}", m.vertices, m.faces)
    me.materials.append(looks.obstacle_material(entry))
    obj = place.obstacle_object(f"obstacle_{k}", me, entry, info.frames, k, bpy.context.scene.collection, first, last)
    stage.apply_texture(obj, m, entry, k, info, run_dir or Path("."))
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
    files = frame.files
    stats: dict[str, Any] = {"triangles": 0, "diffuse": [0, 0, 0]}
    if "mesh" in files:
        verts, faces, vel, normals = read_surface(run_dir / files["mesh"])
        if h.sea is not None:  # one open sheet with the sea: the faces on the walls and floor go
            faces = sea.open_walls(verts, faces, info.domain["lower"], info.domain["upper"], info.particle_radius)
            if normals is not None:
                normals = sea.wall_normals(verts, normals, info.domain["lower"], info.domain["upper"],
                                           sea.WALL_NORMAL_REACH * info.particle_radius)
        fill_mesh(h.fluid.data, verts, faces, vel, normals=normals)
        if h.droplet_volume > 0:
            spray = small_pieces(verts, faces, h.droplet_volume)
            h.fluid.data.polygons.foreach_set("material_index", spray.astype(np.int32))
            stats["droplet_faces"] = int(spray.sum())
        stats["triangles"] = len(faces)
    if h.sea is not None:
        sea.update_sea(h.sea, verts if "mesh" in files else np.zeros((0, 3)), info.time(index))
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
