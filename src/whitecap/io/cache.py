"""A whole run as one animated scene: what the USD and Alembic writers take.

:class:`SceneCache` holds what does not change per frame (obstacle meshes and
their transforms per frame, the camera per frame, the frame rate) and a
function that loads one frame's geometry (:class:`FrameGeometry`: the fluid
surface, or the fluid particles where the run has no surface, and the
diffuse particles by type). Loading a frame is a pure function of the run's
files, so writers may treat frames independently (one layer per frame) and
skip a frame whose sources are unchanged (:attr:`SceneCache.fingerprint`).

Scene formats register in :mod:`whitecap.io.registry` with ``kind="scene"``;
:func:`whitecap.io.registry.write_scene` picks one from the extension.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .mesh import SurfaceMesh


@dataclass
class PointSet:
    """Particles of one frame: positions (n, 3), velocities (n, 3) or None [m/s],
    ids (n,) and sphere diameters ``widths`` (n,) [m]."""

    positions: np.ndarray
    velocities: np.ndarray | None
    ids: np.ndarray
    widths: np.ndarray

    def __post_init__(self) -> None:
        self.positions = np.ascontiguousarray(self.positions, np.float32).reshape(-1, 3)
        if self.velocities is not None:
            self.velocities = np.ascontiguousarray(self.velocities, np.float32).reshape(-1, 3)
        self.ids = np.ascontiguousarray(self.ids, np.int64).reshape(-1)
        self.widths = np.ascontiguousarray(self.widths, np.float32).reshape(-1)

    def __len__(self) -> int:
        return len(self.positions)


@dataclass
class FrameGeometry:
    """What changes per frame. ``mesh`` is None only in a run without surfaces;
    ``points`` maps a point-set name (:attr:`SceneCache.point_sets`) to its particles."""

    index: int
    mesh: SurfaceMesh | None
    points: dict[str, PointSet]


@dataclass
class CacheObstacle:
    """An obstacle's render mesh in its own coordinates, its rest ``placement`` (4×4, column
    vectors) and, for a moving body, its pose per frame index: (position [m], unit
    quaternion w x y z), as ``run.json`` records it. World = T(position)·R(quaternion)·placement
    (:func:`whitecap.geometry.obstacle_matrix`); ``poses`` is empty when it never moves."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[float, float, float]
    placement: np.ndarray
    poses: dict[int, tuple[list[float], list[float]]]


@dataclass
class CacheCamera:
    """A pinhole camera: its 4×4 world matrix (column vectors; it looks along its −z with
    +y up, as Blender and USD cameras do) per frame index, or one under key None when it
    never moves. ``lens`` is the focal length and ``sensor`` the film width across the
    wider image side [mm]; ``aspect`` = width / height; ``clip`` near and far [m];
    ``fstop`` and ``focus`` (distance to the plane in focus per frame [m]) for depth of
    field, or None."""

    matrices: dict[int | None, np.ndarray]
    lens: float
    sensor: float
    aspect: float
    clip: tuple[float, float]
    fstop: float | None = None
    focus: dict[int | None, float] | None = None


@dataclass
class SceneCache:
    """A run ready to write: frames (index, time [s]) in order, at ``frame_rate`` frames per second."""

    frame_rate: float
    frames: list[tuple[int, float]]
    has_mesh: bool  # the fluid is a surface mesh (else the fluid particles are a point set)
    point_sets: tuple[str, ...]  # names of the point sets every frame has, in order
    load: Callable[[int], FrameGeometry]  # frame index -> its geometry (pure)
    fingerprint: Callable[[int], str]  # frame index -> identity of its sources (same = same geometry)
    obstacles: list[CacheObstacle] = field(default_factory=list)
    camera: CacheCamera | None = None
    radii: dict[str, tuple[float, float]] = field(default_factory=dict)  # point set -> sphere radius [min, max] [m]
    notes: list[str] = field(default_factory=list)  # what the export left out, said to the user

    @property
    def first(self) -> int:
        return self.frames[0][0]

    @property
    def last(self) -> int:
        return self.frames[-1][0]
