"""``whitecap export``: a run's frames for other tools, one package.

- :mod:`.series`: ParaView series (``--to vtk``: ``.vtp`` + ``.pvd``; ``--to ply``: PLY + ``.series``)
  of the fluid and diffuse particles and the surface meshes;
- :mod:`.scene`: the whole run as one animated scene (``--to usd|abc``), the one the renderer builds;
- :mod:`.usd`, :mod:`.alembic`: the scene formats' writers, which register in the io registry
  (:func:`whitecap.io.registry.write_scene`) when this package is imported.

Both kinds list their files in ``export.json`` in the output folder (:func:`.series.record_planned`,
:func:`.series.replace_previous`); frames are written with the stage skeleton of
:mod:`whitecap.stage_frames`. Floor: after render (the scene's camera and looks are the renderer's).
"""

from . import alembic, usd  # noqa: F401  (register the scene formats; pxr and bpy load only when used)
