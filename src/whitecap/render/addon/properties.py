"""The per-object sequence settings (``Object.whitecap_seq``) and what each change does at once."""

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from . import handlers
from .shared import looks

KINDS = [("FLUID", "Fluid", "a surface mesh (water material)"), ("PARTICLES", "Particles", "points shown as spheres"),
         ("FOAM", "Foam", "diffuse foam"), ("SPRAY", "Spray", "diffuse spray"),
         ("BUBBLES", "Bubbles", "diffuse air bubbles"), ("OTHER", "Other", "")]
POINT_KINDS = ("PARTICLES", "FOAM", "SPRAY", "BUBBLES")
TEMPLATE = "whitecap_nodes"  # the Geometry Nodes template modifier's name (spheres or mesh)


def _reload(seq, context):
    handlers.reload(seq.id_data, context.scene)


def _on_path(seq, context):
    handlers.forget_tables()
    _reload(seq, context)


def _on_root(scene, context):
    handlers.forget_tables()
    handlers.update_all(scene, force=True)


def _on_smooth(seq, context):
    me = seq.id_data.data
    if me is not None and len(me.polygons):
        me.shade_smooth() if seq.smooth else me.shade_flat()


def _on_motion_blur(seq, context):
    seq.id_data.cycles.use_motion_blur = seq.motion_blur
    if seq.motion_blur:  # the per-object flag does nothing while the scene's is off
        context.scene.render.use_motion_blur = True


def template_group(obj):
    mod = obj.modifiers.get(TEMPLATE)
    return mod.node_group if mod is not None else None


def remove_template(obj):
    """Remove the template modifier and its node group when nothing else uses it (no leak)."""
    mod = obj.modifiers.get(TEMPLATE)
    if mod is None:
        return
    ng = mod.node_group
    obj.modifiers.remove(mod)
    if ng is not None and ng.users == 0:
        bpy.data.node_groups.remove(ng)


def add_template(obj, seq):
    """The Geometry Nodes template of a point kind, each with the picked material (else the
    kind's): the shared spheres (blender/looks.sphere_nodes) at the object's radius range, the
    file's radius where asked, as a point cloud or as instances (EEVEE), or the mesh template
    (blender/looks.mesh_nodes: the surface around the points, at the largest radius)."""
    remove_template(obj)
    mat = seq.material or looks.material(seq.kind)
    if seq.display == "MESH":
        ng = looks.mesh_nodes(f"{obj.name}_mesh", seq.radius_max, mat)
    else:
        ng = looks.sphere_nodes(f"{obj.name}_spheres", seq.radius_min, seq.radius_max, mat, seq.seed,
                                file_radius=seq.file_radius, instances=seq.display == "INSTANCES")
    obj.modifiers.new(TEMPLATE, "NODES").node_group = ng
    return ng


def _on_kind(seq, context):
    obj = seq.id_data
    if seq.kind in POINT_KINDS:
        add_template(obj, seq)
    else:
        remove_template(obj)


def _on_radius(seq, context):
    mod = seq.id_data.modifiers.get(TEMPLATE)
    if mod is None or mod.node_group is None:
        return
    items = mod.node_group.interface.items_tree
    for name, value in (("Radius min", seq.radius_min), ("Radius max", seq.radius_max),
                        ("File radius", seq.file_radius), ("Radius", seq.radius_max),
                        ("Voxel size", looks.MESH_VOXEL * seq.radius_max)):
        if name in items:
            mod[items[name].identifier] = value
    seq.id_data.update_tag()


def _on_material(seq, context):
    if seq.material is not None:
        apply_material(seq.id_data, seq.material)


def apply_material(obj, mat):
    """``mat`` on the object's mesh and in its sphere group."""
    ng = template_group(obj)
    if ng is not None:
        for node in ng.nodes:
            if node.bl_idname == "GeometryNodeSetMaterial":
                node.inputs["Material"].default_value = mat
    obj.data.materials.clear()
    obj.data.materials.append(mat)


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
    display: EnumProperty(name="Draw as", items=[
        ("POINTS", "Point cloud", "spheres as a point cloud (Cycles)"),
        ("INSTANCES", "Instances", "an ico sphere instanced on each point (renders in EEVEE too)"),
        ("MESH", "Mesh", "the surface around the points (Points to Volume, Volume to Mesh at half the largest "
                         "radius); a file's faces as they are")], default="POINTS", update=_on_kind)
    material: PointerProperty(name="Material", type=bpy.types.Material, update=_on_material,
                              description="the material of the mesh or spheres (empty: the type's own)")
    frame_offset: IntProperty(name="Frame offset", default=0, update=_reload,
                              description="scene frame at which file 0 shows")
    use_frame: BoolProperty(name="Own frame", default=False, update=_reload,
                            description="show the file of the Frame property (keyframe or drive it for slow "
                                        "motion and freeze frames) instead of the scene frame")
    frame: FloatProperty(name="Frame", default=0.0, update=_reload, options={"ANIMATABLE"},
                         description="the sequence frame shown while Own frame is on")
    out_of_range: EnumProperty(name="Outside the files", items=[
        ("HOLD", "Hold", "the first or last file"), ("LOOP", "Loop", "start again from the first file"),
        ("BLANK", "Nothing", "an empty mesh")], default="HOLD", update=_reload)
    smooth: BoolProperty(name="Smooth shading", default=True, update=_on_smooth)
    motion_blur: BoolProperty(name="Motion blur", default=False, update=_on_motion_blur,
                              description="blur by the velocity attribute (turns on the scene's motion blur)")
    up: EnumProperty(name="Up axis", items=[("Z", "Z up", "z up, as whitecap and DualSPHysics"),
                                            ("Y", "Y up", "y up, as SPlisHSPlasH: rotated to z up")],
                     default="Z", update=_reload)
    radius_min: FloatProperty(name="Radius min", default=0.01, min=0.0, precision=5, subtype="DISTANCE",
                              update=_on_radius, description="smallest sphere radius (drawn per point by its id)")
    radius_max: FloatProperty(name="Radius max", default=0.01, min=0.0, precision=5, subtype="DISTANCE",
                              update=_on_radius, description="largest sphere radius (drawn per point by its id)")
    file_radius: BoolProperty(name="File radius", default=False, update=_on_radius,
                              description="use the points' radius attribute where the file has one")
    seed: IntProperty(default=1, description="seed of the per-id radius draw (the renderer's per diffuse type)")
    normals: BoolProperty(name="File normals", default=True, update=_reload,
                          description="the file's point normals as custom split normals")
    current: IntProperty(default=-1)
    error: StringProperty(description="why the current frame could not be shown (empty: shown)")
    shown_file: StringProperty(description="the file shown now")
    load_ms: FloatProperty(name="Load time", default=0.0, description="time the last file took to read and fill [ms]")


CLASSES = (WhitecapSequence,)


def register():
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Object.whitecap_seq = PointerProperty(type=WhitecapSequence)
    bpy.types.Scene.whitecap_root = StringProperty(
        name="Root folder", subtype="DIR_PATH", update=_on_root,
        description="relative sequence folders are taken from here (empty: from the .blend's folder)")
    bpy.types.Scene.whitecap_active = IntProperty(default=0)
    bpy.types.Scene.whitecap_fail_render = BoolProperty(
        name="Fail renders on a bad frame", default=False,
        description="a render stops with an error when a sequence cannot show its frame")
    bpy.types.Scene.whitecap_log = StringProperty(
        name="Render log", subtype="FILE_PATH", default="",
        description="while rendering, append the file each sequence showed at each frame to this text file")


def unregister():
    del bpy.types.Object.whitecap_seq
    for name in ("whitecap_root", "whitecap_active", "whitecap_fail_render", "whitecap_log"):
        delattr(bpy.types.Scene, name)
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
