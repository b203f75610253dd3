"""Whole cases from other solvers (DualSPHysics, SPlisHSPlasH) -> a whitecap run directory.

A reader turns a solver's output folder into a :class:`Case`: the fluid frames,
the case's constants, and its rigid shapes (tank, obstacles, moving and floating
bodies) as meshes with, for moving ones, a pose per frame. One writer
(:func:`write_case`) turns any :class:`Case` into a run directory whose
``run.json`` lists the shapes as obstacles of the same contract as whitecap's own
(``io/run.py``), so that foam, mesh, view, render, export and the Blender add-on
show them with no extra step.

Layering: this package sits with the stages; it imports ``config``/``io`` (and
``sim`` for nothing). ``pipeline.import_case`` is its entry point.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: roles a shape can have in a case
ROLES = ("container", "obstacle", "body")


@dataclass
class CaseShape:
    """One rigid shape of a case, z up, SI units.

    ``vertices``/``faces`` are the shape's mesh in its rest placement (world
    coordinates at the first frame). ``poses`` is None for a fixed shape;
    otherwise one pose per fluid frame, in frame order, each the rigid motion
    from the rest placement as ``run.json`` records it:
    ``{"position": [x, y, z], "quaternion": [w, x, y, z]}``
    (world = T(position)·R(quaternion)·rest, see ``geometry.obstacle_matrix``).
    """

    name: str
    vertices: np.ndarray  # (V, 3) float64 [m]
    faces: np.ndarray  # (F, 3) int
    role: str = "obstacle"  # one of ROLES; "container" holds the fluid (a tank)
    poses: list[dict] | None = None
    source: str = ""  # where it came from, for messages and run.json (e.g. "mk 10", "rigid body 1")
    look: dict | None = None  # render look ({"material": ..., "color": [r, g, b]}); None: the role's default


@dataclass
class Case:
    """A foreign solver's case, ready to be written as a run directory."""

    source: Path  # the output folder it was read from
    solver: str  # "dualsphysics" | "splishsplash"
    fluid: list[tuple[int, Path]]  # (frame index, file) of each fluid frame, in order
    frame_dt: float  # time between frames [s]
    particle_radius: float  # half the particle spacing [m]
    rest_density: float = 1000.0  # [kg/m³]
    particle_mass: float | None = None  # [kg]; None: rest_density·(2r)³
    gravity: list[float] = field(default_factory=lambda: [0.0, 0.0, -9.81])
    up: str = "z"  # axis that is up in the fluid files ("y": converted to z up on reading)
    domain: tuple[list[float], list[float]] | None = None  # (lower, upper) [m], z up; None: from the data
    shapes: list[CaseShape] = field(default_factory=list)
    times: list[float] | None = None  # simulated time of each fluid frame [s]; None: index·frame_dt
    fluid_reader_options: dict = field(default_factory=dict)  # extra options for reading the fluid files
