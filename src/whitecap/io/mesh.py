"""The in-memory surface mesh every mesh reader returns and every mesh writer takes.

Mesh formats register in :mod:`whitecap.io.registry` with ``kind="mesh"``;
:func:`read_mesh` and :func:`write_mesh` (from there) pick the format from
the file extension.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError


@dataclass
class SurfaceMesh:
    """A triangle mesh, SI units, z up.

    ``vertices`` (V, 3) float32, ``faces`` (F, 3) int32 (counter-clockwise
    seen from outside), ``normals`` (V, 3) float32 or None, ``arrays`` holds
    per-vertex arrays by name (``velocity`` (V, 3) float32).
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = "<memory>"

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32).reshape(-1, 3)
        if self.normals is not None:
            self.normals = np.ascontiguousarray(self.normals, dtype=np.float32).reshape(-1, 3)
        for k, a in list(self.arrays.items()):
            a = np.ascontiguousarray(a, dtype=np.float32)
            if len(a) != len(self.vertices):
                raise InputError(f"{self.source}: array '{k}' has {len(a)} entries for {len(self.vertices)} vertices")
            self.arrays[k] = a
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise InputError(f"{self.source}: face indices outside 0..{len(self.vertices) - 1}")

    @classmethod
    def empty(cls) -> "SurfaceMesh":
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), {"velocity": np.zeros((0, 3))})

    def __len__(self) -> int:
        return len(self.vertices)

    def check_finite(self) -> None:
        """Raise InputError naming the file if any vertex is NaN/inf."""
        bad = int((~np.isfinite(self.vertices).all(axis=1)).sum())
        if bad:
            raise InputError(f"{self.source}: vertices: {bad} are NaN or infinite")


# Meshes are read and written through the one format registry (kind "mesh").
from .registry import read_mesh, write_mesh  # noqa: E402,F401
