"""Offline rendering of a run in Blender (the ``bpy`` module), plus the Blender add-on.

- :mod:`.driver`: frames over worker processes, the movie, the add-on zip;
- :mod:`.scene`: the Blender scene (runs inside a worker, imports ``bpy``);
- :mod:`.worker`: the worker process entry point.
"""

from .driver import RenderJob, build_addon, encode_movie, render_run, render_worker, require_bpy

__all__ = ["RenderJob", "render_run", "render_worker", "build_addon", "encode_movie", "require_bpy"]
