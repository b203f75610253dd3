"""File I/O: particle frames, run directories, atomic writes.

Formats register themselves on import (one module per format). Importing
``whitecap.io`` loads all built-in formats.
"""

from . import bgeo, npz, ply, vtk_legacy, vtu  # noqa: F401  (registers the formats)
from . import mesh_ply  # noqa: F401  (registers the PLY surface-mesh format)
from . import mesh_obj  # noqa: F401  (registers the OBJ surface-mesh format)
from .atomic import atomic_path, write_bytes, write_text
from .frame import ParticleFrame
from .registry import FORMATS, read, register, write

__all__ = ["ParticleFrame", "read", "write", "register", "FORMATS", "atomic_path", "write_bytes", "write_text"]
