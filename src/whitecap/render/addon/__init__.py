"""whitecap sequences: a Blender add-on that plays back frame sequences.

Loads a whitecap run directory (surface meshes, diffuse particles) or any
numbered VTK/PLY/OBJ sequence (DualSPHysics PartVTK or IsoSurface output,
splashsurf meshes, ...) as objects whose mesh data is replaced when the
frame changes. Per object: type (fluid / foam / other), smooth shading,
frame offset, motion blur and one-click materials.

This file must stand alone inside Blender, where whitecap itself is not
installed, so it carries its own small legacy-VTK reader; PLY and OBJ go
through Blender's own importers.
"""

import os
import re
import struct

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, PointerProperty, StringProperty

NUMBERED = re.compile(r"^(.*?)(\d+)(\.(?:vtk|ply|obj))$", re.IGNORECASE)
# Names of a velocity array, lower case: a copy of whitecap.io.registry.VELOCITY_NAMES,
# since the add-on runs where whitecap is not installed (tests/test_render.py checks they agree).
VELOCITY_NAMES = ("vel", "velocity", "v")


# ----------------------------------------------------------------------------- sequences
def find_sequence(path):
    """(directory, prefix, suffix, {index: filename}) of the numbered sequence containing path."""
    d, name = os.path.split(os.path.abspath(path))
    m = NUMBERED.match(name)
    if not m:
        raise ValueError(f"{name}: not a numbered file (expected e.g. PartFluid_0001.vtk)")
    prefix, suffix = m.group(1), m.group(3)
    frames = {}
    for f in os.listdir(d):
        mm = NUMBERED.match(f)
        if mm and mm.group(1) == prefix and mm.group(3).lower() == suffix.lower():
            frames[int(mm.group(2))] = f
    return d, prefix, suffix, frames


# ----------------------------------------------------------------------------- readers
def read_vtk_legacy(path):
    """Points, triangles and a velocity array from legacy VTK POLYDATA/UNSTRUCTURED_GRID.

    Handles ASCII and BINARY (big-endian, as the format prescribes) files with
    POINTS, optional POLYGONS (triangulated as fans) and POINT_DATA arrays; a
    velocity is taken from an array named Vel, velocity or v.
    """
    with open(path, "rb") as fh:
        data = fh.read()
    lines = data.split(b"\n", 4)
    binary = lines[2].strip().upper() == b"BINARY"
    pos = data.index(b"\n", data.index(lines[2])) + 1
    points, tris, vel, npts = [], [], None, 0
    sizes = {"float": (">f", 4), "double": (">d", 8), "int": (">i", 4), "unsigned_int": (">I", 4),
             "char": (">b", 1), "unsigned_char": (">B", 1), "short": (">h", 2), "unsigned_short": (">H", 2),
             "long": (">q", 8), "vtktypeint64": (">q", 8), "vtkidtype": (">i", 4)}

    def next_line():
        nonlocal pos
        end = data.index(b"\n", pos) if b"\n" in data[pos:] else len(data)
        line = data[pos:end].strip()
        pos = end + 1
        return line

    def truncated(got, count):
        return ValueError(f"{path}: the file ends after {got} of {count} values (truncated?)")

    def read_values(count, typ):
        nonlocal pos
        if binary:
            fmt, size = sizes.get(typ.lower(), (">f", 4))
            chunk = data[pos:pos + size * count]
            if len(chunk) < size * count:
                raise truncated(len(chunk) // size, count)
            pos += size * count
            return list(struct.unpack(">" + fmt[1] * count, chunk))
        vals = []
        while len(vals) < count:
            if pos >= len(data):  # without this, a truncated file loops here for ever
                raise truncated(len(vals), count)
            vals += [float(t) for t in next_line().split()]
        return vals

    in_point_data = False
    while pos < len(data):
        line = next_line()
        if not line:
            continue
        parts = line.decode("latin-1").split()
        key = parts[0].upper()
        if key == "POINTS":
            npts = int(parts[1])
            v = read_values(3 * npts, parts[2])
            points = [tuple(v[3 * i:3 * i + 3]) for i in range(npts)]
        elif key in ("POLYGONS", "CELLS", "VERTICES", "LINES", "TRIANGLE_STRIPS"):
            n, size = int(parts[1]), int(parts[2])
            if len(parts) > 3 or (pos < len(data) and data[pos:pos + 7] == b"OFFSETS"):
                raise ValueError("VTK 5.1 offset/connectivity cells are not supported; write legacy 4.2")
            v = [int(x) for x in read_values(size, "int")]
            if key in ("POLYGONS", "CELLS"):
                k = 0
                for _ in range(n):
                    c = v[k]
                    ids = v[k + 1:k + 1 + c]
                    for j in range(1, c - 1):
                        tris.append((ids[0], ids[j], ids[j + 1]))
                    k += c + 1
        elif key == "CELL_TYPES":
            read_values(int(parts[1]), "int")
        elif key == "POINT_DATA":
            in_point_data = True
        elif key == "CELL_DATA":
            in_point_data = False
        elif key in ("SCALARS", "VECTORS", "NORMALS"):
            ncomp = 3 if key != "SCALARS" else (int(parts[3]) if len(parts) > 3 else 1)
            if key == "SCALARS":
                look = next_line()
                if not look.upper().startswith(b"LOOKUP_TABLE"):
                    pos -= len(look) + 1
            count = (npts if in_point_data else 0) * ncomp
            v = read_values(count, parts[2])
            if parts[1].lower() in VELOCITY_NAMES and ncomp == 3:
                vel = [tuple(v[3 * i:3 * i + 3]) for i in range(npts)]
        elif key == "FIELD":
            for _ in range(int(parts[2])):
                hdr = next_line().decode("latin-1").split()
                while not hdr:
                    hdr = next_line().decode("latin-1").split()
                name, ncomp, ntup, typ = hdr[0], int(hdr[1]), int(hdr[2]), hdr[3]
                v = read_values(ncomp * ntup, typ)
                if name.lower() in VELOCITY_NAMES and ncomp == 3:
                    vel = [tuple(v[3 * i:3 * i + 3]) for i in range(ntup)]
    return points, tris, vel


def _import_with_blender(path):
    """Mesh data from Blender's PLY/OBJ importer (the temporary object is removed)."""
    before = set(bpy.data.objects)
    if path.lower().endswith(".ply"):
        bpy.ops.wm.ply_import(filepath=path)
    else:
        bpy.ops.wm.obj_import(filepath=path, forward_axis="Y", up_axis="Z")
    new = [o for o in bpy.data.objects if o not in before]
    me = new[0].data if new else bpy.data.meshes.new("empty")
    for o in new:
        bpy.data.objects.remove(o)
    return me


def load_mesh(path, name):
    if path.lower().endswith(".vtk"):
        points, tris, vel = read_vtk_legacy(path)
        me = bpy.data.meshes.new(name)
        me.from_pydata(points, [], tris)
        if vel:
            a = me.attributes.new("velocity", "FLOAT_VECTOR", "POINT")
            a.data.foreach_set("vector", [c for t in vel for c in t])
        me.update()
        return me
    me = _import_with_blender(path)
    me.name = name
    # splashsurf/whitecap meshes carry vx, vy, vz: combine them into the velocity
    # attribute that Cycles uses for motion blur of changing topology.
    names = {a.name for a in me.attributes}
    if {"vx", "vy", "vz"} <= names and "velocity" not in names:
        n = len(me.vertices)
        comps = []
        for k in ("vx", "vy", "vz"):
            buf = [0.0] * n
            me.attributes[k].data.foreach_get("value", buf)
            comps.append(buf)
        a = me.attributes.new("velocity", "FLOAT_VECTOR", "POINT")
        a.data.foreach_set("vector", [c for t in zip(*comps) for c in t])
    return me


# ----------------------------------------------------------------------------- state
class WhitecapSequence(bpy.types.PropertyGroup):
    enabled: BoolProperty(default=False)
    directory: StringProperty(subtype="DIR_PATH")
    prefix: StringProperty()
    suffix: StringProperty()
    kind: EnumProperty(
        name="Type",
        items=[("FLUID", "Fluid", "a surface mesh"), ("FOAM", "Foam", "diffuse particles"), ("OTHER", "Other", "")],
        default="FLUID",
    )
    frame_offset: IntProperty(name="Frame offset", default=0, description="scene frame at which file 0 shows")
    smooth: BoolProperty(name="Smooth shading", default=True)
    motion_blur: BoolProperty(name="Motion blur", default=True)
    current: IntProperty(default=-1)


def _frames(seq):
    _, _, _, frames = find_sequence(os.path.join(seq.directory, _first_name(seq)))
    return frames


def _first_name(seq):
    for f in sorted(os.listdir(seq.directory)):
        m = NUMBERED.match(f)
        if m and m.group(1) == seq.prefix and m.group(3).lower() == seq.suffix.lower():
            return f
    raise FileNotFoundError(f"no files {seq.prefix}*{seq.suffix} in {seq.directory}")


def update_object(obj, scene_frame):
    seq = obj.whitecap_seq
    frames = _frames(seq)
    idx = scene_frame - seq.frame_offset
    have = [i for i in frames if i <= idx]
    i = max(have) if have else min(frames)
    if i == seq.current and obj.data is not None:
        return False
    old = obj.data
    me = load_mesh(os.path.join(seq.directory, frames[i]), f"{obj.name}_{i:05d}")
    for m in old.materials:
        me.materials.append(m)
    if seq.smooth and len(me.polygons):
        me.shade_smooth()
    obj.data = me
    if old is not None and old.users == 0:
        bpy.data.meshes.remove(old)
    obj.cycles.use_motion_blur = seq.motion_blur
    seq.current = i
    return True


@bpy.app.handlers.persistent
def on_frame_change(scene, depsgraph=None):
    for obj in scene.objects:
        if obj.type == "MESH" and obj.whitecap_seq.enabled:
            try:
                update_object(obj, scene.frame_current)
            except Exception as exc:  # keep playback going; report once per object
                print(f"whitecap: {obj.name}: {exc}")


def add_sequence_object(context, path, kind=None):
    d, prefix, suffix, frames = find_sequence(path)
    name = (prefix.rstrip("_-. ") or "sequence")
    me = bpy.data.meshes.new(name)
    obj = bpy.data.objects.new(name, me)
    context.scene.collection.objects.link(obj)
    seq = obj.whitecap_seq
    seq.enabled, seq.directory, seq.prefix, seq.suffix = True, d, prefix, suffix
    seq.kind = kind or ("FOAM" if "diffuse" in prefix.lower() or "part" in prefix.lower() else "FLUID")
    if seq.kind == "FOAM":
        _add_points_modifier(obj)
    seq.frame_offset = context.scene.frame_start - min(frames)
    update_object(obj, context.scene.frame_current)
    return obj


def _add_points_modifier(obj):
    """Show vertex-only particle meshes as small spheres (Mesh to Points)."""
    ng = bpy.data.node_groups.new("whitecap_points", "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gi, go = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    m2p = ng.nodes.new("GeometryNodeMeshToPoints")
    m2p.inputs["Radius"].default_value = 0.004
    ng.links.new(gi.outputs[0], m2p.inputs["Mesh"])
    ng.links.new(m2p.outputs["Points"], go.inputs[0])
    obj.modifiers.new("whitecap_points", "NODES").node_group = ng


def make_material(kind):
    mat = bpy.data.materials.new(f"whitecap_{kind.lower()}")
    mat.use_nodes = True
    b = mat.node_tree.nodes.get("Principled BSDF")
    if kind == "FLUID":
        b.inputs["Transmission Weight"].default_value = 1.0
        b.inputs["IOR"].default_value = 1.33
        b.inputs["Roughness"].default_value = 0.02
        b.inputs["Base Color"].default_value = (0.8, 0.93, 1.0, 1.0)
    elif kind == "FOAM":
        b.inputs["Base Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        b.inputs["Roughness"].default_value = 0.5
    else:
        b.inputs["Base Color"].default_value = (0.8, 0.78, 0.72, 1.0)
        b.inputs["Roughness"].default_value = 0.7
    return mat


# ----------------------------------------------------------------------------- operators
class WHITECAP_OT_load(bpy.types.Operator):
    """Load a whitecap run directory or a numbered VTK/PLY/OBJ sequence"""

    bl_idname = "whitecap.load"
    bl_label = "Load sequence"
    bl_options = {"REGISTER", "UNDO"}
    filepath: StringProperty(subtype="FILE_PATH")

    def execute(self, context):
        path = bpy.path.abspath(self.filepath)
        try:
            run = path if os.path.isdir(path) else os.path.dirname(path)
            if os.path.isfile(os.path.join(run, "run.json")):
                made = []
                for sub, kind in (("mesh", "FLUID"), ("diffuse", "FOAM")):
                    d = os.path.join(run, sub)
                    files = sorted(f for f in os.listdir(d) if NUMBERED.match(f)) if os.path.isdir(d) else []
                    if files:
                        made.append(add_sequence_object(context, os.path.join(d, files[0]), kind))
                if not made:
                    raise ValueError(f"{run}: no mesh/ or diffuse/ frames; run `whitecap mesh` first")
            else:
                add_sequence_object(context, path)
        except Exception as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}


class WHITECAP_OT_material(bpy.types.Operator):
    """Give the active sequence object a material matching its type"""

    bl_idname = "whitecap.material"
    bl_label = "Apply material"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        obj = context.object
        mat = make_material(obj.whitecap_seq.kind)
        obj.data.materials.clear()
        obj.data.materials.append(mat)
        return {"FINISHED"}


class WHITECAP_PT_panel(bpy.types.Panel):
    bl_label = "whitecap sequence"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"

    def draw(self, context):
        layout = self.layout
        layout.operator("whitecap.load", icon="FILE_FOLDER")
        obj = context.object
        if obj is None or not obj.whitecap_seq.enabled:
            return
        seq = obj.whitecap_seq
        layout.label(text=f"{seq.prefix}*{seq.suffix}  (showing {seq.current})")
        layout.prop(seq, "kind")
        layout.prop(seq, "smooth")
        layout.prop(seq, "frame_offset")
        layout.prop(seq, "motion_blur")
        layout.operator("whitecap.material", icon="MATERIAL")


CLASSES = (WhitecapSequence, WHITECAP_OT_load, WHITECAP_OT_material, WHITECAP_PT_panel)


def register():
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Object.whitecap_seq = PointerProperty(type=WhitecapSequence)
    if on_frame_change not in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.append(on_frame_change)


def unregister():
    if on_frame_change in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.remove(on_frame_change)
    del bpy.types.Object.whitecap_seq
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
