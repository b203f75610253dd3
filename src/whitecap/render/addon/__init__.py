"""whitecap sequences: a Blender add-on that plays back simulation frame sequences.

*Load* takes a whitecap run directory (the fluid surface, one object per diffuse type,
the obstacles, the run's frame range and rate, and the stage that F12 needs), a folder
(each numbered sequence in it, or in its subfolders, that passes a filter), one numbered
file (DualSPHysics ``PartFluid_0000.vtk``, splashsurf meshes, SPlisHSPlasH ``.bgeo``,
any format meshio reads...) or a pattern (``PartFluid_@.vtk``). Each sequence is an object
whose mesh is refilled in place when the frame changes, with every point array of the
file as a mesh attribute. A run looks as ``whitecap render`` draws it: both build it with
whitecap's bpy layer (whitecap/blender), which the extension carries in its ``whitecap``
folder with the modules it needs.

Modules, by Blender concept: properties (the per-object settings), handlers (frame
change, save, render), operators, panels, readers (files), sequences (numbered files),
load (runs, folders, files), paths (stored folders).
"""

from . import handlers, operators, panels, properties

MODULES = (properties, operators, panels)


def register():
    import bpy

    properties.register()
    for c in operators.CLASSES + panels.CLASSES:
        bpy.utils.register_class(c)
    handlers.register()


def unregister():
    import bpy

    handlers.unregister()
    for c in reversed(operators.CLASSES + panels.CLASSES):
        bpy.utils.unregister_class(c)
    properties.unregister()
