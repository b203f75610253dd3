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

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from . import alembic, usd  # noqa: F401  (register the scene formats; pxr and bpy load only when used)

SERIES_TARGETS = ("vtk", "ply")  # ParaView series: vtk (.vtp + .pvd), ply (PLY + .series)
SCENE_TARGETS = ("usd", "abc")  # one animated scene: a USD stage, an Alembic archive
TARGETS = SERIES_TARGETS + SCENE_TARGETS


@dataclass(frozen=True)
class ExportJob:
    """What one ``export`` does: the options of ``whitecap export`` and of
    :func:`whitecap.pipeline.export`, with their defaults, defined here once (the CLI and the
    pipeline build one; :func:`export`, :func:`.series.export_run` and :func:`.scene.export_scene`
    take it).

    ``to`` is the target (one of :data:`TARGETS`); ``split_types`` also writes the diffuse spray,
    foam and bubbles as separate series (a scene always splits them); ``jobs`` frames of a series
    are written in parallel, or on Dask with ``cluster`` (an address, or local, slurm, pbs); a
    scene is written by one process (``jobs`` is checked all the same).
    """

    to: str = "vtk"
    split_types: bool = False
    show_progress: bool = True
    jobs: int = 1
    cluster: str | None = None


def export(run: str | Path, job: ExportJob, out: str | Path | None = None) -> dict[str, Path | str]:
    """Export ``run`` as ``job`` says: ParaView series (:func:`.series.export_run`) or one scene
    (:func:`.scene.export_scene`). Returns {series or target: path} (see those)."""
    from ..errors import InputError

    if job.to in SCENE_TARGETS:
        from .scene import export_scene

        return export_scene(run, job, out)
    if job.to not in TARGETS:
        raise InputError(f"export: unknown target '{job.to}' (choose from {', '.join(TARGETS)})")
    from .series import export_run

    return dict(export_run(run, job, out))
