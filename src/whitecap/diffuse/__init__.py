"""Diffuse particles (spray, foam, air bubbles) after Ihmsen et al. 2012.

- :mod:`.kernels`: the Taichi kernels (potentials, generation, advection);
- :mod:`.generator`: :class:`FoamGenerator`, the per-frame state machine;
- :mod:`.params`: thresholds, presets and parameter files;
- :mod:`.splishsplash`: SPlisHSPlasH FoamGenerator's automatic mode (the ``splishsplash`` preset);
- :mod:`.driver`: the simulation frame hook and post-processing of any sequence.
"""

from .driver import FoamJob, FoamStage, postprocess, postprocess_params_file, simulation_hook
from .generator import DiffuseState, FoamGenerator
from .params import FoamParams, resolve

__all__ = [
    "FoamJob", "simulation_hook", "postprocess", "postprocess_params_file", "FoamStage", "FoamGenerator",
    "DiffuseState", "FoamParams", "resolve",
]
