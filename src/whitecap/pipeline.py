"""The Python API: one function per stage, mirroring the CLI subcommands.

This module wires stages together (the solver plus in-simulation foam, the
whole scene-to-movie run); stages themselves never import it.
"""

from __future__ import annotations

import dataclasses
import importlib
import time
from pathlib import Path
from typing import TYPE_CHECKING

from . import timing
from .config import DEFAULT_ARCH, DEFAULT_UP, Scene, load_scene, with_options
from .io.run import RunInfo

if TYPE_CHECKING:
    from .cases import ImportJob
    from .diffuse import FoamJob
    from .export import ExportJob
    from .render import RenderJob
    from .sim.driver import SimulateJob
    from .surface.driver import MeshRun
    from .view import ViewJob


def _scene(scene: Scene | str | Path) -> Scene:
    return scene if isinstance(scene, Scene) else load_scene(scene)


def default_out(scene: Scene) -> Path:
    return Path("out") / scene.name


def simulate(scene: Scene | str | Path, job: SimulateJob | None = None, out: str | Path | None = None,
             **options) -> RunInfo:
    """Simulate a scene (PBF, plus diffuse particles when ``[foam]`` is on) into ``out``
    (default ``out/<scene name>``).

    ``job`` is a :class:`whitecap.sim.driver.SimulateJob` (its fields and defaults are the
    options: frames, resume, force, arch, foam, profile, show_progress); ``options`` build one,
    or replace those fields of ``job``.
    """
    sc = _scene(scene)  # a bad scene file fails before Taichi starts
    from .sim.driver import SimulateJob, run_simulation

    job = with_options(SimulateJob, job, options)
    out = Path(out) if out is not None else default_out(sc)
    hooks = []
    if job.foam and sc.foam.enabled:
        foam_stage = importlib.import_module(".diffuse", __package__)
        hooks.append(foam_stage.simulation_hook(sc))
    timing.reset()
    info = run_simulation(sc, out, job, hooks=hooks)
    info.extra["out"] = str(out)
    if job.profile:
        print(timing.report("simulate profile"))
    return info


# ============================================================================ run: scene to movie
RUN_STAGES = ("simulate", "mesh", "render")


def _simulation_state(out: Path, frames: int) -> str:
    """'new', 'partial' or 'done' for the simulate stage of a run directory."""
    from .io.run import CHECKPOINT

    if not (out / "run.json").exists():
        return "new"
    ck = out / CHECKPOINT
    if ck.exists():
        import numpy as np

        try:
            done = int(np.load(ck)["frame"])
        except Exception:
            return "partial"
        return "done" if done >= frames else "partial"
    return "partial"


def run(
    scene: Scene | str | Path,
    out: str | Path | None = None,
    until: str = "render",
    preview: bool = False,
    arch: str = DEFAULT_ARCH,
    jobs: int | None = None,
    frames: int | None = None,
    show_progress: bool = True,
    cluster: str | None = None,
) -> dict:
    """Scene to movie: simulate (with foam), mesh, render, MP4, in one run directory.

    Resumable at every stage: rerunning continues where an interrupted run
    stopped and never redoes finished frames. ``until`` stops after a stage.
    Returns the paths of what was made (``run``, and ``movie``/``blend`` when rendered).
    ``cluster`` runs mesh and render on Dask (the simulation stays here: it is sequential in time).
    """
    from .errors import InputError
    from .progress import console

    if until not in RUN_STAGES:
        raise InputError(f"--until: expected one of {', '.join(RUN_STAGES)}, got {until!r}")
    sc = _scene(scene)
    out = Path(out) if out is not None else default_out(sc)
    nframes = sc.output.frames if frames is None else int(frames)
    stages = RUN_STAGES[: RUN_STAGES.index(until) + 1]
    result: dict = {"run": out}
    seconds: dict[str, float] = {}
    for k, stage in enumerate(stages, 1):
        console.rule(f"[bold]stage {k}/{len(stages)}: {stage}")
        t0 = time.perf_counter()
        if stage == "simulate":
            state = _simulation_state(out, nframes)
            if state != "new":  # continuing a run of another scene would mix two simulations
                from .sim.driver import refuse_changed_scene

                refuse_changed_scene(sc, out)
            if state == "done":
                console.print(f"simulate: all {nframes} frames already in {out}")
            else:
                simulate(sc, out=out, frames=nframes, resume=state == "partial", arch=arch, show_progress=show_progress)
        elif stage == "mesh":
            mesh(out, jobs=jobs, show_progress=show_progress, cluster=cluster)
        elif stage == "render":
            from .render import RenderJob

            job = RenderJob(quality="preview" if preview else "final", show_progress=show_progress, cluster=cluster)
            r = render(out, dataclasses.replace(job, jobs=jobs) if cluster and jobs else job)
            result.update(r if isinstance(r, dict) else {})
        seconds[stage] = time.perf_counter() - t0
    result["stage_seconds"] = seconds
    result["profile"] = record_stage_times(out, seconds)
    return result


STAGE_PROFILE = "profile.json"  # wall time per stage of the last `whitecap run` in this directory


def record_stage_times(out: Path, seconds: dict[str, float]) -> Path:
    """Write the wall time per stage to ``out/profile.json`` (atomically); the CLI prints it.

    A stage that found its frames already made counts only the time it took to
    see so; the file is rewritten by every run, so it holds the last one."""
    import json

    from .io.atomic import write_text

    total = sum(seconds.values())
    path = out / STAGE_PROFILE
    write_text(path, json.dumps({"stage_seconds": {k: round(v, 3) for k, v in seconds.items()},
                                 "total_seconds": round(total, 3)}, indent=2) + "\n")
    return path


# ============================================================================ mesh, export
def mesh(
    run: str | Path,
    options: MeshRun | None = None,
    out: str | Path | None = None,
    radius: float | None = None,
    config: str | Path | None = None,
    up: str = DEFAULT_UP,
    profile: bool = False,
    **settings,
) -> list[dict]:
    """Reconstruct a surface per frame of a run (or a particle sequence) with splashsurf.

    ``options`` is a :class:`whitecap.surface.driver.MeshRun` (how the stage runs: jobs, force,
    show_progress, cluster; their defaults are its fields); ``settings`` named like its fields
    build one or replace them, the others are ``[mesh]`` fields (``cube_size=0.6``,
    ``format="obj"``...). ``config`` is a scene TOML whose ``[mesh]`` replaces the run's, and
    whose ``[cluster]`` (else the run's scene's) configures a ``cluster``. Returns per-frame
    stats; meshes of a run are recorded in its run.json. ``profile`` prints the time per phase.
    """
    from .surface.driver import MeshRun, plan, run_mesh

    names = {f.name for f in dataclasses.fields(MeshRun)}
    given = {k: settings.pop(k) for k in names & settings.keys()}
    options = MeshRun(**given) if options is None else dataclasses.replace(options, **given)
    if options.cluster and options.cluster_config is None:
        from .executor import cluster_settings

        options = dataclasses.replace(options, cluster_config=cluster_settings(run, config))
    cfg = load_scene(config).mesh if config is not None else None
    timing.reset()
    job = plan(run, out=out, radius=radius, config=cfg, up=up, **settings)
    stats = run_mesh(job, options)
    if profile:
        print(timing.report("mesh profile"))
    return stats


def export(run: str | Path, job: ExportJob | None = None, out: str | Path | None = None,
           **options) -> dict[str, Path | str]:
    """Export a run: ParaView series (``vtk``: .pvd + .vtp, ``ply``: PLY + .series) of its
    particles and meshes, or the whole run as one animated scene (``usd``: a USD stage,
    ``abc``: an Alembic archive) with the fluid, diffuse particles, obstacles and camera.

    ``job`` is a :class:`whitecap.export.ExportJob` (its fields and defaults are the options:
    to, split_types, show_progress, jobs, cluster); ``options`` build one, or replace those
    fields of ``job``. Returns {series or target: path}; a scene export adds {"note": ...} when
    it left something out (a run without surfaces exports points only). For ``vtk`` and
    ``ply``, ``jobs`` frames are written in parallel, or on Dask with ``cluster`` (an address,
    or local, slurm, pbs)."""
    from .export import ExportJob, export as export_run

    return export_run(run, with_options(ExportJob, job, options), out)


# ============================================================================ render
def render(run: str | Path, job: RenderJob | None = None, **options) -> dict:
    """Render a run in Blender: PNG frames, movie.mp4 and scene.blend under RUN/render.

    ``job`` is a :class:`whitecap.render.RenderJob` (its fields and defaults are the
    options: quality, frames, jobs, force, movie, show_progress, device, cluster);
    ``options`` build one, or replace those fields of ``job``.
    """
    from .render import RenderJob, render_run

    return render_run(run, with_options(RenderJob, job, options))


def blender_addon(out: str | Path | None = None) -> Path:
    """Build the Blender add-on zip."""
    from .render import build_addon

    return build_addon(out)


# ============================================================================ foam (post-processing)
def foam(
    input: str | Path | None = None,
    job: FoamJob | None = None,
    out: str | Path | None = None,
    ini: str | Path | None = None,
    case: str | Path | None = None,
    **options,
) -> RunInfo:
    """Diffuse particles over any particle sequence (see :func:`whitecap.diffuse.postprocess`).

    ``job`` is a :class:`whitecap.diffuse.FoamJob` (its fields and defaults are the options:
    preset, up, dt, radius, seed, show_progress, force, arch, profile); ``options`` build one, or replace
    those fields of ``job``. With ``ini`` (a parameter file), ``input`` may be left out when the
    file names the job (a VisualSPHysics foam .ini: [PATHS], [TIMESTEPS], [DOMAIN]); see
    :func:`whitecap.diffuse.postprocess_params_file`.
    """
    from .diffuse.driver import FoamJob
    from .errors import InputError

    job = with_options(FoamJob, job, options)
    if ini is None and input is None:
        raise InputError("foam: give the INPUT sequence, or --params FILE naming it ([PATHS] InputDataPath)")
    from .diffuse import postprocess, postprocess_params_file

    timing.reset()
    if ini is not None:
        info = postprocess_params_file(ini, src=input, out=out, case=case, job=job)
    else:
        assert input is not None  # (refused above)
        info = postprocess(input, out=out, case=case, job=job)
    if job.profile:
        print(timing.report("foam profile"))
    return info


# ============================================================================ import a foreign case
def import_case(case_output: str | Path, out: str | Path, job: ImportJob | None = None, **options) -> RunInfo:
    """A whole case from another solver (fluid, tank, obstacles, moving bodies), or a bare sequence of
    frames, -> a run directory that ``foam``, ``mesh``, ``view`` and ``render`` continue from
    (:func:`whitecap.cases.read_case`). Resumable. The case is read and checked in full before
    anything is written.

    ``job`` is a :class:`whitecap.cases.ImportJob` (its fields and defaults are the options: up,
    xml, floating_csv, scene_json, fluid_model, dt, radius, force, show_progress); ``options``
    build one, or replace those fields of ``job``."""
    from .cases import ImportJob, import_case as import_into

    return import_into(case_output, out, with_options(ImportJob, job, options))


# ============================================================================ view
def view(target: Scene | str | Path, job: ViewJob | None = None, out: str | Path | None = None, **options):
    """Real-time viewer: a scene TOML simulates live, a run directory or sequence plays back.

    ``job`` is a :class:`whitecap.view.ViewJob` (its fields and defaults are the options:
    headless, frames, mp4, arch, web, size, color_mode, up, panel, legend, show_progress, host,
    port, max_points, points); ``options`` build one, or replace those fields of ``job``.
    ``headless`` renders OUT/view_NNNNN.png offscreen (and view.mp4 with ``mp4``) and returns
    the PNG paths. ``web`` serves the viewer to a browser until interrupted, after printing its
    URL. See :mod:`whitecap.view`.
    """
    from .view import ViewJob, view as _view

    return _view(target, with_options(ViewJob, job, options), out=out)
