"""The in-memory surface mesh and its per-format readers/writers.

Meshes are not particle frames, so they have their own small registry,
mirroring :mod:`whitecap.io.registry`: a format module calls
:func:`register_mesh` at import time; :func:`read_mesh` and
:func:`write_mesh` pick the format from the file extension.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

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


MeshReader = Callable[[Path], SurfaceMesh]
MeshWriter = Callable[[Path, SurfaceMesh], None]
MESH_FORMATS: dict[str, tuple[tuple[str, ...], MeshReader | None, MeshWriter | None]] = {}


def register_mesh(name: str, extensions: tuple[str, ...], reader: MeshReader | None, writer: MeshWriter | None) -> None:
    MESH_FORMATS[name] = (extensions, reader, writer)


def _format(path: Path):
    name = path.name.lower()
    for fmt, (exts, reader, writer) in MESH_FORMATS.items():
        if any(name.endswith(e) for e in exts):
            return fmt, reader, writer
    raise InputError(f"{path}: no mesh format for this file type (known: {', '.join(sorted(MESH_FORMATS))})")


def read_mesh(path: str | Path) -> SurfaceMesh:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found")
    fmt, reader, _ = _format(p)
    if reader is None:
        raise InputError(f"{p}: mesh format '{fmt}' cannot be read")
    return reader(p)


def write_mesh(path: str | Path, mesh: SurfaceMesh) -> None:
    """Write a mesh atomically; the format comes from the extension."""
    p = Path(path)
    fmt, _, writer = _format(p)
    if writer is None:
        raise InputError(f"{p}: mesh format '{fmt}' cannot be written")
    writer(p, mesh)
