"""The Python API: one function per stage, mirroring the CLI subcommands.

This module wires stages together (the solver plus in-simulation foam, the
whole scene-to-movie run); stages themselves never import it.
"""

from __future__ import annotations

from pathlib import Path

from . import timing
from .config import Scene, load_scene
from .io.run import RunInfo


def _scene(scene: Scene | str | Path) -> Scene:
    return scene if isinstance(scene, Scene) else load_scene(scene)


def default_out(scene: Scene) -> Path:
    return Path("out") / scene.name


def simulate(
    scene: Scene | str | Path,
    out: str | Path | None = None,
    frames: int | None = None,
    resume: bool = False,
    force: bool = False,
    arch: str = "cpu",
    foam: bool = True,
    profile: bool = False,
    show_progress: bool = True,
) -> RunInfo:
    """Simulate a scene (PBF, plus diffuse particles when ``[foam]`` is on) into ``out``."""
    from .sim.driver import run_simulation

    sc = _scene(scene)
    out = Path(out) if out is not None else default_out(sc)
    hooks = []
    if foam and sc.foam.enabled:
        from . import foam as foam_stage

        if hasattr(foam_stage, "simulation_hook"):
            hooks.append(foam_stage.simulation_hook(sc))
    timing.reset()
    info = run_simulation(sc, out, frames=frames, resume=resume, force=force, arch=arch, hooks=hooks,
                          show_progress=show_progress)
    info.extra["out"] = str(out)
    if profile:
        print(timing.report("simulate profile"))
    return info


def mesh(
    run: str | Path,
    out: str | Path | None = None,
    radius: float | None = None,
    jobs: int | None = None,
    force: bool = False,
    config: str | Path | None = None,
    up: str = "z",
    show_progress: bool = True,
    **overrides,
) -> list[dict]:
    """Reconstruct a surface per frame of a run (or a particle sequence) with splashsurf.

    ``overrides`` are ``[mesh]`` fields (``cube_size=0.6``, ``format="obj"``...);
    ``config`` is a scene TOML whose ``[mesh]`` replaces the run's. Returns
    per-frame stats; meshes of a run are recorded in its run.json.
    """
    import os

    from .surface.driver import plan, run_mesh

    jobs = max(1, jobs or len(os.sched_getaffinity(0)))
    cfg = load_scene(config).mesh if config is not None else None
    job = plan(run, out=out, radius=radius, config=cfg, jobs=jobs, up=up, **overrides)
    return run_mesh(job, jobs=jobs, force=force, show_progress=show_progress)


def export(
    run: str | Path,
    to: str = "vtk",
    out: str | Path | None = None,
    split_types: bool = False,
    show_progress: bool = True,
) -> dict[str, Path]:
    """ParaView series (.pvd + .vtp, or PLY + .series) of a run's particles and meshes."""
    from .surface.export import export_run

    return export_run(run, to=to, out=out, split_types=split_types, show_progress=show_progress)
