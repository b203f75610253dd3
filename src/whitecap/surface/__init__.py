"""Surfaces: splashsurf meshes per frame (exports are :mod:`whitecap.export`).

- :mod:`.reconstruct`: ``mesh_frame(in_path, out_path, params) -> stats``, the pure per-frame function
- :mod:`.driver`: plans a run or sequence and maps ``mesh_frame`` over a process pool
"""

from .reconstruct import MeshParams, mesh_frame, params_from_config, reconstruct

__all__ = ["MeshParams", "mesh_frame", "params_from_config", "reconstruct"]
