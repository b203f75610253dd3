"""Operators: load, apply material (to the selected row of the sequence list), refresh."""

import bpy
from bpy.props import BoolProperty, FloatProperty, StringProperty

from . import handlers, load
from .properties import apply_material
from .shared import looks


class WHITECAP_OT_load(bpy.types.Operator):
    """Load a whitecap run directory, a folder of numbered files, one numbered file or a pattern (name_@.vtk)"""

    bl_idname = "whitecap.load"
    bl_label = "Load sequence"
    bl_options = {"REGISTER", "UNDO"}
    filepath: StringProperty(subtype="FILE_PATH")
    directory: StringProperty(subtype="DIR_PATH")
    filter_text: StringProperty(name="Filter", description="only files whose name holds this (or matches it: * ?)")
    recursive: BoolProperty(name="Subfolders", default=False, description="also load the sequences of subfolders")
    fps: FloatProperty(name="Frame rate", default=load.DEFAULT_FPS, min=0.001,
                       description="frames per second of a plain folder (a run sets its own)")

    def execute(self, context):
        path = self.filepath or self.directory  # the file browser gives a folder as directory
        try:
            load.load_path(context, path, self.filter_text, self.recursive, self.fps)
        except Exception as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}


def selected_sequence(context):
    """The object of the selected row in the panel's list, else the context object."""
    objs, k = bpy.data.objects, context.scene.whitecap_active
    if 0 <= k < len(objs) and objs[k].type == "MESH" and objs[k].whitecap_seq.directory:
        return objs[k]
    obj = context.object
    return obj if obj is not None and obj.type == "MESH" else None


class WHITECAP_OT_material(bpy.types.Operator):
    """Give the selected sequence its material: the picked one, else its type's (made once, then reused)"""

    bl_idname = "whitecap.material"
    bl_label = "Apply material"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if selected_sequence(context) is None:
            cls.poll_message_set("select a sequence object first")
            return False
        return True

    def execute(self, context):
        obj = selected_sequence(context)
        seq = obj.whitecap_seq
        apply_material(obj, seq.material or looks.material(seq.kind))
        return {"FINISHED"}


class WHITECAP_OT_refresh(bpy.types.Operator):
    """Look for new or removed files of every sequence and reload the current frame"""

    bl_idname = "whitecap.refresh"
    bl_label = "Refresh"
    bl_options = {"REGISTER"}

    def execute(self, context):
        handlers.forget_tables()
        handlers.update_all(context.scene, force=True)
        return {"FINISHED"}


CLASSES = (WHITECAP_OT_load, WHITECAP_OT_material, WHITECAP_OT_refresh)
