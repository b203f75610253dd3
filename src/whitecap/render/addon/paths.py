"""Stored folders: ``//x`` relative to the .blend, plain relative ones to the scene's root folder."""

import os

import bpy


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
