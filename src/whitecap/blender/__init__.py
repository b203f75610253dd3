"""The bpy layer shared by ``whitecap render`` and the Blender add-on.

One definition of how a whitecap run becomes Blender data: mesh fill
(:mod:`.mesh`), materials and the diffuse spheres (:mod:`.looks`), obstacle and
body placement (:mod:`.place`) and the parts of loading a run that both make
(:mod:`.run`: the diffuse objects, a frame's diffuse points, the stage an
add-on scene needs to render). ``whitecap render`` adds only what is specific to
batch rendering (render/: Cycles, output, compositing, the worker); the add-on
adds its sequence objects, panels and handlers (render/addon/).

Layering: a stage-level package. It imports bpy (inside functions, so its
constants load without Blender), numpy and whitecap's pure modules
(:mod:`whitecap.errors`, :mod:`whitecap.io.diffuse_types`, :mod:`whitecap.io.run`
and what they import), never config, pipeline or cli: ``whitecap blender-addon``
copies it with those modules into the extension, where whitecap is not installed.
"""
