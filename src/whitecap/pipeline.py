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
