"""The sidebar panel (the scene's sequences as a list) and the object panel."""

import bpy

from .properties import POINT_KINDS


class WHITECAP_UL_sequences(bpy.types.UIList):
    """The scene's sequence objects, each with its enable switch and a warning when its frame failed."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        seq = item.whitecap_seq
        row = layout.row(align=True)
        row.prop(seq, "enabled", text="")
        row.label(text=item.name, icon="ERROR" if seq.error else "MESH_DATA")
        row.label(text=f"{seq.prefix}@{seq.suffix}" if not seq.run_kind else seq.run_kind)
        row.label(text=f"{seq.load_ms:.0f} ms")

    def filter_items(self, context, data, propname):
        objs = getattr(data, propname)
        flags = [self.bitflag_filter_item if getattr(o, "whitecap_seq", None) is not None and o.whitecap_seq.directory
                 else 0 for o in objs]
        return flags, []


def sequence_panel(layout, obj):
    seq = obj.whitecap_seq
    if seq.error:
        box = layout.box()
        box.alert = True
        box.label(text=seq.error, icon="ERROR")
    layout.prop(seq, "directory")
    if not seq.run_kind:
        row = layout.row(align=True)
        row.prop(seq, "prefix")
        row.prop(seq, "suffix")
    layout.label(text=f"file {seq.current}: {seq.load_ms:.1f} ms to load")
    layout.prop(seq, "kind")
    if seq.kind in POINT_KINDS:
        layout.prop(seq, "display")
        row = layout.row(align=True)
        row.prop(seq, "radius_min")
        row.prop(seq, "radius_max")
        layout.prop(seq, "file_radius")
    layout.prop(seq, "material")
    layout.prop(seq, "smooth")
    layout.prop(seq, "normals")
    layout.prop(seq, "use_frame")
    if seq.use_frame:
        layout.prop(seq, "frame")
    else:
        layout.prop(seq, "frame_offset")
    layout.prop(seq, "out_of_range")
    layout.prop(seq, "up")
    layout.prop(seq, "motion_blur")
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
        layout.prop(context.scene, "whitecap_fail_render")
        layout.prop(context.scene, "whitecap_log")
        layout.template_list("WHITECAP_UL_sequences", "", bpy.data, "objects", context.scene, "whitecap_active")
        objs = bpy.data.objects
        k = context.scene.whitecap_active
        if 0 <= k < len(objs) and objs[k].whitecap_seq.directory:
            sequence_panel(layout, objs[k])


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
            sequence_panel(layout, obj)


CLASSES = (WHITECAP_UL_sequences, WHITECAP_PT_sequences, WHITECAP_PT_object)
