"""whitecap sequences: a Blender add-on that plays back simulation frame sequences.

*Load* takes a whitecap run directory (the fluid surface, one object per
diffuse type, the obstacles, the run's frame range and rate), a folder (each
numbered sequence in it) or one numbered file (DualSPHysics ``PartFluid_0000.vtk``,
splashsurf meshes, SPlisHSPlasH ``.bgeo``...). Each sequence is an object whose
mesh is refilled in place when the frame changes, with every point array of
the file as a mesh attribute (``velocity``, ``density``, ``pressure``, ``id``,
``Type``, ``Mk``, ``lifetime``...). No import operator runs while the frame
changes, so the selection, the active object and the materials stay.

Blender has no whitecap inside, so the add-on carries its own readers
(formats.py, Python and numpy only); ``diffuse_types.py`` is whitecap's own
module, copied into the extension by ``whitecap blender-addon``.
"""

import json
import math
import os

import bpy
import numpy as np
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from . import formats, looks, sequences
from .formats import read_vtk_legacy  # noqa: F401  (kept as the add-on's public reader)

try:  # inside the extension: whitecap.io.diffuse_types, copied in by build_addon
    from .diffuse_types import COUNT_NAMES
except ImportError:  # run from whitecap's source tree
    from whitecap.io.diffuse_types import COUNT_NAMES

# Point-array names, lower case, that become the standard attributes: copies of
# whitecap.io.registry's tables (tests/test_addon.py checks they agree).
VELOCITY_NAMES = ("vel", "velocity", "v")
DENSITY_NAMES = ("rhop", "rho", "density")
ID_NAMES = ("idp", "id")
PRESSURE_NAMES = ("press", "pressure")
STANDARD = (("velocity", VELOCITY_NAMES), ("density", DENSITY_NAMES), ("id", ID_NAMES), ("pressure", PRESSURE_NAMES))
RESERVED = ("position", "sharp_face", "material_index", "sharp_edge")  # Blender's own attribute names
KINDS = [("FLUID", "Fluid", "a surface mesh (water material)"), ("PARTICLES", "Particles", "points shown as spheres"),
         ("FOAM", "Foam", "diffuse foam"), ("SPRAY", "Spray", "diffuse spray"),
         ("BUBBLES", "Bubbles", "diffuse air bubbles"), ("OTHER", "Other", "")]
POINT_KINDS = ("PARTICLES", "FOAM", "SPRAY", "BUBBLES")
DIFFUSE_KINDS = ("SPRAY", "FOAM", "BUBBLES")  # by type code, as COUNT_NAMES
SPACING_SAMPLES = 256  # points whose nearest-neighbour distance estimates the particle spacing


# ----------------------------------------------------------------------------- geometry -> mesh
def attribute_arrays(geom):
    """[(name, array)] of a file's point arrays: the standard names for velocity, density,
    id and pressure (whatever the solver called them), every other array by its own name."""
    out, taken = [], set()
    low = {k.lower(): k for k in geom.arrays}
    for std, names in STANDARD:
        key = next((low[n] for n in names if n in low), None)
        if key is not None:
            out.append((std, geom.arrays[key]))
            taken |= {key, std}
    for k, a in geom.arrays.items():
        if k not in taken and not k.startswith(".") and k.lower() not in RESERVED and k.lower() not in taken:
            out.append((k, a))
            taken.add(k.lower())
    return out


def _y_up(a):
    """(x, y, z) of y-up data -> (x, -z, y), z up (whitecap.io.axes.to_z_up)."""
    return np.stack([a[:, 0], -a[:, 2], a[:, 1]], axis=1)


def fill_mesh(me, geom, smooth=True, up="Z", keep=None):
    """Replace a mesh's geometry and attributes in place with ``geom`` (its materials stay).
    ``keep`` selects points (a diffuse type); polygons then drop out."""
    pts, arrays = geom.points, attribute_arrays(geom)
    loops, starts = geom.loops, geom.starts
    if keep is not None:
        pts, arrays = pts[keep], [(k, a[keep]) for k, a in arrays]
        loops = starts = np.zeros(0, np.int32)
    if up == "Y":
        pts = _y_up(pts)
        arrays = [(k, _y_up(a) if k == "velocity" else a) for k, a in arrays]
    me.clear_geometry()  # removes the previous frame's attributes too
    n = len(pts)
    if n:
        me.vertices.add(n)
        me.vertices.foreach_set("co", np.ascontiguousarray(pts, np.float32).ravel())
    if len(starts) and n:
        me.loops.add(len(loops))
        me.loops.foreach_set("vertex_index", np.ascontiguousarray(loops, np.int32))
        me.polygons.add(len(starts))
        me.polygons.foreach_set("loop_start", np.ascontiguousarray(starts, np.int32))
    if n:
        for name, a in arrays:
            _attribute(me, name, a)
    me.update()
    if len(me.polygons):
        me.shade_smooth() if smooth else me.shade_flat()
    return me


def _attribute(me, name, a):
    a = np.asarray(a)
    comps = 1 if a.ndim == 1 else a.shape[1]
    if a.dtype.kind in "iub" and comps == 1:
        me.attributes.new(name, "INT", "POINT").data.foreach_set("value", a.astype(np.int32))
    elif comps == 1:
        me.attributes.new(name, "FLOAT", "POINT").data.foreach_set("value", a.astype(np.float32))
    elif comps in (2, 3):
        kind = "FLOAT_VECTOR" if comps == 3 else "FLOAT2"
        me.attributes.new(name, kind, "POINT").data.foreach_set("vector", np.ascontiguousarray(a, np.float32).ravel())
    else:  # one float attribute per component
        for c in range(comps):
            _attribute(me, f"{name}_{c}", a[:, c].astype(np.float32))


# ----------------------------------------------------------------------------- paths
def resolve(path, scene=None):
    """An absolute folder from a stored one: ``//x`` is relative to the .blend, a plain
    relative path to the scene's root directory (whitecap_root)."""
    if path.startswith("//"):
        return os.path.normpath(bpy.path.abspath(path))
    if not os.path.isabs(path):
        scene = scene or bpy.context.scene
        root = scene.whitecap_root if scene is not None else ""
        base = bpy.path.abspath(root) if root else (os.path.dirname(bpy.data.filepath) or os.getcwd())
        return os.path.normpath(os.path.join(base, path))
    return os.path.normpath(path)


def stored(path, scene=None, blend=None):
    """How a folder is stored: relative to the root directory where one is set and the
    folder lies inside it, else ``//``-relative to the .blend once it has been saved."""
    path = os.path.normpath(os.path.abspath(path))
    scene = scene or bpy.context.scene
    root = scene.whitecap_root if scene is not None else ""
    if root:
        r = os.path.normpath(bpy.path.abspath(root))
        if os.path.commonpath([r, path]) == r:
            return os.path.relpath(path, r)
    blend = blend if blend is not None else bpy.data.filepath
    if blend:
        try:
            return "//" + os.path.relpath(path, os.path.dirname(os.path.abspath(blend))).replace(os.sep, "/")
        except ValueError:  # another drive
            pass
    return path


# ----------------------------------------------------------------------------- sequences
_FRAMES = {}  # (folder, prefix, suffix, run kind) -> {frame: path}; cleared by Refresh


def frame_table(seq, scene=None):
    """{frame number: file} of a sequence: the run's current files (run.json) for a run's
    sequence, else the numbered files in its folder."""
    d = resolve(seq.directory, scene)
    key = (d, seq.prefix, seq.suffix, seq.run_kind)
    if key not in _FRAMES:
        if not os.path.isdir(d):
            raise ValueError(f"{d}: no such folder (set the sequence's folder in the whitecap panel)")
        if seq.run_kind:
            run = os.path.dirname(d)
            _FRAMES[key] = {i: os.path.join(run, rel) for i, rel in run_files(run, seq.run_kind)}
        else:
            _FRAMES[key] = {i: os.path.join(d, f) for i, f in sequences.frames_of(d, seq.prefix, seq.suffix).items()}
    frames = _FRAMES[key]
    if not frames:
        raise ValueError(f"{d}: no files {seq.prefix}*{seq.suffix}")
    return frames


def file_index(frames, number):
    """The file shown at a (whole) sequence frame number: the last one at or before it."""
    have = [i for i in frames if i <= number]
    return max(have) if have else min(frames)


def index_at(seq, frames, frame, subframe):
    """The file index shown at scene frame ``frame + subframe``. A sub-frame (a motion-blur
    shutter step) keeps the frame's mesh: the file already shown stays while it is the
    file of the frame before or after, so the ``velocity`` attribute does the blur."""
    lo = file_index(frames, frame - seq.frame_offset)
    if subframe > 1e-6:
        hi = file_index(frames, frame + 1 - seq.frame_offset)
        if seq.current in (lo, hi):
            return seq.current
    return lo


def update_object(obj, scene, force=False):
    """Show the scene frame's file in ``obj``; True when the mesh changed."""
    seq = obj.whitecap_seq
    frames = frame_table(seq, scene)
    i = index_at(seq, frames, scene.frame_current, scene.frame_subframe)
    if i == seq.current and not force:
        return False
    geom = formats.read(frames[i])
    keep = None
    if seq.type_code >= 0:
        low = {k.lower(): k for k in geom.arrays}
        types = geom.arrays.get(low.get("type", ""), np.zeros(len(geom), np.int32))
        keep = np.asarray(types).astype(np.int64) == seq.type_code
    fill_mesh(obj.data, geom, seq.smooth, seq.up, keep)
    seq.current = i
    return True


def update_all(scene, force=False):
    for obj in scene.objects:
        seq = getattr(obj, "whitecap_seq", None)
        if obj.type == "MESH" and seq is not None and seq.directory and seq.enabled:
            try:
                update_object(obj, scene, force)
            except Exception as exc:  # keep playback going; say why
                print(f"whitecap: {obj.name}: {exc}")


@persistent
def on_frame_change(scene, depsgraph=None):
    update_all(scene)


@persistent
def on_save(filepath="", *args):
    """Store every sequence's folder relative to the .blend being written."""
    if not isinstance(filepath, str) or not filepath:
        return
    for scene in bpy.data.scenes:
        for obj in scene.objects:
            seq = getattr(obj, "whitecap_seq", None)
            if seq is not None and seq.directory and (os.path.isabs(seq.directory) or seq.directory.startswith("//")):
                new = stored(resolve(seq.directory, scene), scene, filepath)
                if new != seq.directory:
                    seq["directory"] = new  # no reload: the folder is the same


def _reload(seq, context):
    obj = seq.id_data
    if obj.type == "MESH" and seq.directory and seq.enabled:
        try:
            update_object(obj, context.scene, force=True)
        except Exception as exc:
            print(f"whitecap: {obj.name}: {exc}")


def _on_path(seq, context):
    _FRAMES.clear()
    _reload(seq, context)


def _on_root(scene, context):
    _FRAMES.clear()
    update_all(scene, force=True)


def _on_smooth(seq, context):
    me = seq.id_data.data
    if me is not None and len(me.polygons):
        me.shade_smooth() if seq.smooth else me.shade_flat()


def _on_motion_blur(seq, context):
    obj = seq.id_data
    obj.cycles.use_motion_blur = seq.motion_blur
    if seq.motion_blur:  # the per-object flag does nothing while the scene's is off
        context.scene.render.use_motion_blur = True


def _on_kind(seq, context):
    """Points get the sphere modifier and the kind's material; a mesh loses the spheres."""
    obj = seq.id_data
    ours = [m for m in obj.modifiers if m.name == "whitecap_spheres"]
    if seq.kind in POINT_KINDS and not ours:
        ng, _ = looks.sphere_nodes(f"{obj.name}_spheres", looks.material(seq.kind))
        obj.modifiers.new("whitecap_spheres", "NODES").node_group = ng
        _on_radius(seq, context)
    elif seq.kind not in POINT_KINDS:
        for m in ours:
            obj.modifiers.remove(m)


def _on_radius(seq, context):
    for mod in seq.id_data.modifiers:
        if mod.type == "NODES" and mod.node_group is not None and "Radius" in mod.node_group.interface.items_tree:
            mod[mod.node_group.interface.items_tree["Radius"].identifier] = seq.radius
            seq.id_data.update_tag()


class WhitecapSequence(bpy.types.PropertyGroup):
    enabled: BoolProperty(name="Enabled", default=False, update=_reload,
                          description="follow the timeline (off: the mesh stays as it is)")
    directory: StringProperty(name="Folder", subtype="DIR_PATH", update=_on_path,
                              description="the sequence's folder; //… is relative to the .blend")
    prefix: StringProperty(name="Prefix", update=_on_path)
    suffix: StringProperty(name="Extension", update=_on_path)
    run_kind: StringProperty(description="file kind in the run's run.json, for a run's sequence")
    type_code: IntProperty(default=-1, description="diffuse type code to show (-1: all points)")
    kind: EnumProperty(name="Type", items=KINDS, default="FLUID", update=_on_kind)
    frame_offset: IntProperty(name="Frame offset", default=0, update=_reload,
                              description="scene frame at which file 0 shows")
    smooth: BoolProperty(name="Smooth shading", default=True, update=_on_smooth)
    motion_blur: BoolProperty(name="Motion blur", default=False, update=_on_motion_blur,
                              description="blur by the velocity attribute (turns on the scene's motion blur)")
    up: EnumProperty(name="Up axis", items=[("Z", "Z up", "z up, as whitecap and DualSPHysics"),
                                            ("Y", "Y up", "y up, as SPlisHSPlasH: rotated to z up")],
                     default="Z", update=_reload)
    radius: FloatProperty(name="Particle radius", default=0.01, min=0.0, precision=4, subtype="DISTANCE",
                          update=_on_radius, description="sphere radius of points without a radius attribute")
    current: IntProperty(default=-1)


def spacing(geom):
    """Half the median nearest-neighbour distance of a sample of points (a particle radius)."""
    from mathutils import kdtree

    pts = geom.points
    if len(pts) < 2:
        return 0.0
    tree = kdtree.KDTree(len(pts))
    for k, p in enumerate(pts):
        tree.insert(p, k)
    tree.balance()
    step = max(1, len(pts) // SPACING_SAMPLES)
    d = [tree.find_n(pts[k], 2)[1][2] for k in range(0, len(pts), step)]
    return float(np.median(d)) / 2


def new_sequence(context, made, name, directory, prefix, suffix, kind, *, run_kind="", type_code=-1,
                 radius=None, offset=0):
    """A sequence object showing the current frame; ``made`` collects what was created."""
    me = bpy.data.meshes.new(name)
    made.append(me)
    obj = bpy.data.objects.new(name, me)
    made.append(obj)
    context.scene.collection.objects.link(obj)
    seq = obj.whitecap_seq
    seq["directory"], seq["prefix"], seq["suffix"], seq["run_kind"] = stored(directory, context.scene), prefix, suffix, run_kind
    seq["type_code"], seq["frame_offset"] = type_code, offset
    seq["kind"] = [k[0] for k in KINDS].index(kind)
    frames = frame_table(seq, context.scene)
    if kind in POINT_KINDS:
        if radius is None:
            radius = spacing(formats.read(frames[min(frames)])) or 0.01
        ng, _ = looks.sphere_nodes(f"{name}_spheres", looks.material(kind))
        made.append(ng)
        obj.modifiers.new("whitecap_spheres", "NODES").node_group = ng
        seq.radius = radius
    elif kind == "FLUID":
        me.materials.append(looks.material("FLUID"))
    seq["enabled"] = True
    update_object(obj, context.scene, force=True)
    return obj


def guess_kind(prefix, suffix):
    p = prefix.lower()
    if p.startswith(("rb_", "rigid")):  # SPlisHSPlasH's rigid-body meshes
        return "OTHER"
    if suffix.lower() in (".bgeo",) or p.startswith(("part", "particle", "fluid_particles")) or "diffuse" in p:
        return "PARTICLES"
    return "FLUID"


def load_path(context, path):
    """Load a run directory, a folder of sequences or one numbered file; returns the objects."""
    made = []
    try:
        objs = _load(context, path, made)
        # Renders replace mesh data on every frame change: keep the interface off the scene meanwhile
        context.scene.render.use_lock_interface = True
        return objs
    except Exception:
        for idb in reversed(made):  # a failed load leaves nothing behind
            coll = {bpy.types.Object: bpy.data.objects, bpy.types.Mesh: bpy.data.meshes}.get(type(idb),
                                                                                            bpy.data.node_groups)
            try:
                coll.remove(idb)
            except (ReferenceError, RuntimeError):
                pass
        raise


def _load(context, path, made):
    p = os.path.normpath(bpy.path.abspath(path))
    if not os.path.exists(p):
        raise ValueError(f"{p}: no such file or folder")
    run = p if os.path.isdir(p) else os.path.dirname(p)
    if os.path.isfile(os.path.join(run, "run.json")) and (os.path.isdir(p) or os.path.basename(p) == "run.json"):
        return load_run(context, run, made)
    if os.path.isdir(p):
        objs = []
        for prefix, suffix in sequences.sequences_in(p):
            frames = sequences.frames_of(p, prefix, suffix)
            objs.append(new_sequence(context, made, prefix.rstrip("_-. ") or "sequence", p, prefix, suffix,
                                     guess_kind(prefix, suffix), offset=context.scene.frame_start - min(frames)))
        return objs
    d, prefix, suffix = sequences.sequence_of(p)
    frames = sequences.frames_of(d, prefix, suffix)
    return [new_sequence(context, made, prefix.rstrip("_-. ") or "sequence", d, prefix, suffix, guess_kind(prefix, suffix),
                         offset=context.scene.frame_start - min(frames))]


# ----------------------------------------------------------------------------- runs
def run_json(run):
    path = os.path.join(run, "run.json")
    try:
        with open(path) as fh:
            info = json.load(fh)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not readable ({exc})") from None
    if not isinstance(info, dict) or not isinstance(info.get("frames", []), list):
        raise ValueError(f"{path}: not a whitecap run.json")
    return info


def run_files(run, kind):
    """(frame, relative path) of a kind's files made from the run's current simulation
    (an entry from an earlier simulation is stale: left out, as whitecap does)."""
    info = run_json(run)
    sim = info.get("simulation", "")
    out = []
    for f in info.get("frames", []):
        rel = f.get("files", {}).get(kind)
        if rel and f.get("made_from", {}).get(kind, "") == sim:
            out.append((int(f["index"]), rel))
    return sorted(out)


def load_run(context, run, made):
    """The fluid (surface mesh, else particles), one object per diffuse type, the obstacles,
    and the timeline set to the run's frames and frame rate."""
    info = run_json(run)
    radius = float(info.get("particle_radius", 0.01))
    objs = []

    def seq_of(kind):
        files = run_files(run, kind)
        if not files:
            return None
        d = os.path.dirname(os.path.join(run, files[0][1]))
        return d, files

    mesh, fluid, diffuse = seq_of("mesh"), seq_of("fluid"), seq_of("diffuse")
    if mesh is None and fluid is None:
        raise ValueError(f"{run}: the run has no fluid frames yet; run `whitecap simulate` first")
    indices = [i for _, files in filter(None, (mesh, fluid, diffuse)) for i, _ in files]
    sc = context.scene
    fps = float(info.get("frame_rate", 24.0))
    sc.render.fps = max(1, int(round(fps)))
    sc.render.fps_base = sc.render.fps / fps
    sc.frame_start, sc.frame_end = min(indices), max(indices)
    if sc.frame_current < sc.frame_start or sc.frame_current > sc.frame_end:
        sc.frame_current = sc.frame_start
    if mesh is not None:
        objs.append(new_sequence(context, made, "fluid", mesh[0], "", "", "FLUID", run_kind="mesh"))
    else:
        objs.append(new_sequence(context, made, "fluid_particles", fluid[0], "", "", "PARTICLES", run_kind="fluid",
                                 radius=radius))
    if diffuse is not None:
        for t, name in enumerate(COUNT_NAMES):
            objs.append(new_sequence(context, made, name, diffuse[0], "", "", DIFFUSE_KINDS[t], run_kind="diffuse",
                                     type_code=t, radius=radius))
    for k, entry in enumerate(info.get("obstacles", [])):
        obj = add_obstacle(context, made, run, info, entry, k)
        if obj is not None:
            objs.append(obj)
    return objs


def add_obstacle(context, made, run, info, entry, k):
    """An obstacle's render mesh (else its collision mesh), placed as whitecap places it
    (geometry.obstacle_transform: scale, rotate about x then y then z, translate)."""
    if not isinstance(entry, dict):
        return None
    base = info.get("extra", {}).get("scene_dir") or run
    src = entry.get("render_mesh") or entry.get("mesh")
    if not src:
        return None
    path = src if os.path.isabs(src) else os.path.join(base, src)
    if not os.path.isfile(path):
        print(f"whitecap: obstacle {k}: {path}: file not found, left out")
        return None
    geom = formats.read(path)
    me = bpy.data.meshes.new(f"obstacle_{k}")
    made.append(me)
    fill_mesh(me, geom, smooth=True)
    me.materials.append(looks.obstacle_material(entry))
    obj = bpy.data.objects.new(f"obstacle_{k}", me)
    made.append(obj)
    obj.location = entry.get("translate", [0.0, 0.0, 0.0])
    obj.rotation_mode = "XYZ"  # Blender's XYZ Euler is Rz @ Ry @ Rx: x first, as whitecap
    obj.rotation_euler = [math.radians(a) for a in entry.get("rotate", [0.0, 0.0, 0.0])]
    s = float(entry.get("scale", 1.0))
    obj.scale = (s, s, s)
    context.scene.collection.objects.link(obj)
    poses = [(int(f["index"]), f["bodies"][k]) for f in info.get("frames", [])
             if isinstance(f.get("bodies"), list) and k < len(f["bodies"]) and f["bodies"][k]]
    if poses:
        key_body(obj, poses)
    return obj


def key_body(obj, poses):
    """A moving body: its rest placement goes into the mesh, and the object is keyed with the
    pose run.json records per frame (position, quaternion w x y z): world = T(p) R(q) placement,
    as whitecap's geometry.obstacle_matrix. Linear keys: no overshoot between frames."""
    context_matrix = obj.matrix_basis.copy()
    obj.data.transform(context_matrix)
    obj.data.update()
    obj.location, obj.scale = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    obj.rotation_mode = "QUATERNION"
    for i, pose in sorted(poses):
        obj.location = pose["position"]
        obj.rotation_quaternion = pose["quaternion"]
        obj.keyframe_insert("location", frame=i)
        obj.keyframe_insert("rotation_quaternion", frame=i)
    action = obj.animation_data.action
    curves = getattr(action, "fcurves", None)
    if curves is None:  # Blender 5: layered actions
        curves = [c for layer in action.layers for strip in layer.strips for bag in strip.channelbags
                  for c in bag.fcurves]
    for c in curves:
        for kp in c.keyframe_points:
            kp.interpolation = "LINEAR"


# ----------------------------------------------------------------------------- operators
class WHITECAP_OT_load(bpy.types.Operator):
    """Load a whitecap run directory, a folder of numbered files or one numbered file"""

    bl_idname = "whitecap.load"
    bl_label = "Load sequence"
    bl_options = {"REGISTER", "UNDO"}
    filepath: StringProperty(subtype="FILE_PATH")
    directory: StringProperty(subtype="DIR_PATH")

    def execute(self, context):
        path = self.filepath or self.directory  # the file browser gives a folder as directory
        try:
            load_path(context, path)
        except Exception as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}


class WHITECAP_OT_material(bpy.types.Operator):
    """Give the active sequence object the material of its type (made once, then reused)"""

    bl_idname = "whitecap.material"
    bl_label = "Apply material"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        obj = context.object
        if obj is None or obj.type != "MESH":
            cls.poll_message_set("select a sequence object first")
            return False
        return True

    def execute(self, context):
        obj = context.object
        kind = obj.whitecap_seq.kind
        mat = looks.material(kind)
        spheres = [m for m in obj.modifiers if m.type == "NODES" and m.node_group is not None]
        if kind in POINT_KINDS and spheres:
            for node in spheres[0].node_group.nodes:
                if node.bl_idname == "GeometryNodeSetMaterial":
                    node.inputs["Material"].default_value = mat
        obj.data.materials.clear()
        obj.data.materials.append(mat)
        return {"FINISHED"}


class WHITECAP_OT_refresh(bpy.types.Operator):
    """Look for new or removed files of every sequence and reload the current frame"""

    bl_idname = "whitecap.refresh"
    bl_label = "Refresh"
    bl_options = {"REGISTER"}

    def execute(self, context):
        _FRAMES.clear()
        update_all(context.scene, force=True)
        return {"FINISHED"}


# ----------------------------------------------------------------------------- panels
class WHITECAP_UL_sequences(bpy.types.UIList):
    """The scene's sequence objects, each with its enable switch."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        seq = item.whitecap_seq
        row = layout.row(align=True)
        row.prop(seq, "enabled", text="")
        row.label(text=item.name, icon="MESH_DATA")
        row.label(text=f"{seq.prefix}#{seq.suffix}" if not seq.run_kind else seq.run_kind)

    def filter_items(self, context, data, propname):
        objs = getattr(data, propname)
        flags = [self.bitflag_filter_item if getattr(o, "whitecap_seq", None) is not None and o.whitecap_seq.directory
                 else 0 for o in objs]
        return flags, []


def _seq_panel(layout, obj):
    seq = obj.whitecap_seq
    layout.prop(seq, "directory")
    if not seq.run_kind:
        row = layout.row(align=True)
        row.prop(seq, "prefix")
        row.prop(seq, "suffix")
    layout.label(text=f"showing file {seq.current}")
    layout.prop(seq, "kind")
    layout.prop(seq, "smooth")
    layout.prop(seq, "frame_offset")
    layout.prop(seq, "up")
    layout.prop(seq, "motion_blur")
    if seq.kind in POINT_KINDS:
        layout.prop(seq, "radius")
    layout.operator("whitecap.material", icon="MATERIAL")


class WHITECAP_PT_sequences(bpy.types.Panel):
    bl_label = "whitecap sequences"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "whitecap"

    def draw(self, context):
        layout = self.layout
        row = layout.row(align=True)
        row.operator("whitecap.load", icon="FILE_FOLDER")
        row.operator("whitecap.refresh", icon="FILE_REFRESH")
        layout.prop(context.scene, "whitecap_root")
        layout.template_list("WHITECAP_UL_sequences", "", bpy.data, "objects", context.scene, "whitecap_active")
        objs = bpy.data.objects
        k = context.scene.whitecap_active
        if 0 <= k < len(objs) and objs[k].whitecap_seq.directory:
            _seq_panel(layout, objs[k])


class WHITECAP_PT_object(bpy.types.Panel):
    bl_label = "whitecap sequence"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"

    def draw(self, context):
        layout = self.layout
        layout.operator("whitecap.load", icon="FILE_FOLDER")
        obj = context.object
        if obj is not None and obj.whitecap_seq.directory:
            layout.prop(obj.whitecap_seq, "enabled")
            _seq_panel(layout, obj)


CLASSES = (WhitecapSequence, WHITECAP_OT_load, WHITECAP_OT_material, WHITECAP_OT_refresh, WHITECAP_UL_sequences,
           WHITECAP_PT_sequences, WHITECAP_PT_object)


def register():
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Object.whitecap_seq = PointerProperty(type=WhitecapSequence)
    bpy.types.Scene.whitecap_root = StringProperty(
        name="Root folder", subtype="DIR_PATH", update=_on_root,
        description="relative sequence folders are taken from here (empty: from the .blend's folder)")
    bpy.types.Scene.whitecap_active = IntProperty(default=0)
    if on_frame_change not in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.append(on_frame_change)
    if on_save not in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.append(on_save)


def unregister():
    if on_frame_change in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.remove(on_frame_change)
    if on_save in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.remove(on_save)
    del bpy.types.Object.whitecap_seq
    del bpy.types.Scene.whitecap_root
    del bpy.types.Scene.whitecap_active
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
