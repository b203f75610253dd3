"""File I/O: particle frames, run directories, atomic writes.

Formats register themselves on import (one module per format) in the one
registry, :mod:`whitecap.io.registry`, as particle, mesh or scene formats. Importing
``whitecap.io`` loads the built-in particle and mesh formats; the scene formats (USD,
Alembic) register from :mod:`whitecap.export`, their one user.
"""

from . import bgeo, mesh_obj, mesh_ply, npz, ply, vtk_legacy, vtu  # noqa: F401  (registers the formats)
from .atomic import atomic_path, write_bytes, write_text
from .frame import ParticleFrame
from .registry import FORMATS, find_array, read, read_mesh, register, write, write_copy, write_mesh, write_scene

__all__ = [
    "ParticleFrame", "read", "write", "write_copy", "read_mesh", "write_mesh", "write_scene", "register", "FORMATS",
    "find_array", "atomic_path", "write_bytes", "write_text",
]
