"""Whole cases from other solvers (DualSPHysics, SPlisHSPlasH) and bare particle sequences ->
a whitecap run directory.

A reader turns a solver's output folder (or a bare sequence of frames,
:mod:`whitecap.cases.sequence`) into a :class:`Case`: the fluid frames,
the case's constants, and its rigid shapes (tank, obstacles, moving and floating
bodies) as meshes with, for moving ones, a pose per frame. One writer
(:func:`write_case`) turns any :class:`Case` into a run directory whose
``run.json`` lists the shapes as obstacles of the same contract as whitecap's own
(``io/run.py``), so that foam, mesh, view, render, export and the Blender add-on
show them with no extra step.

Layering: this package sits with the stages; it imports ``config``/``io`` (and
``sim`` for nothing). :func:`read_case` and :func:`whitecap.cases.run_dir.write_case` are
its entry points (``pipeline.import_case``, and ``foam`` over a foreign sequence).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import DEFAULT_UP

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
    up: str = DEFAULT_UP  # axis that is up in the fluid files ("y": converted to z up on reading)
    domain: tuple[list[float], list[float]] | None = None  # (lower, upper) [m], z up; None: from the data
    domain_rule: str = "the case's"  # where ``domain`` came from, for run.json and the message
    shapes: list[CaseShape] = field(default_factory=list)
    times: list[float] | None = None  # simulated time of each fluid frame [s]; None: index·frame_dt
    fluid_reader_options: dict = field(default_factory=dict)  # extra options for reading the fluid files
    notes: dict = field(default_factory=dict)  # more for run.json's ``extra`` (e.g. {"case": the case XML})


def read_case(src: str | Path, up: str | None = None, xml: str | Path | None = None,
              floating_csv: str | Path | None = None, scene_json: str | Path | None = None,
              fluid_model: str | None = None, dt: float | None = None, radius: float | None = None) -> Case:
    """A DualSPHysics or SPlisHSPlasH output folder, else a bare sequence of frames, as a :class:`Case`.
    ``xml``/``floating_csv`` are DualSPHysics inputs, ``scene_json``/``fluid_model`` SPlisHSPlasH
    ones, ``dt``/``radius`` a bare sequence's (:func:`whitecap.cases.sequence.read_sequence`, which
    reads a DualSPHysics case XML too)."""
    from ..errors import InputError
    from ..io.sequence import particle_files
    from . import dualsphysics, sequence, splishsplash

    src = Path(src)
    pattern = any(c in str(src) for c in "*?[") and not src.exists()
    if not src.exists() and not pattern:
        raise InputError(f"{src}: no such file or directory")
    kind = ("dualsphysics" if dualsphysics.is_case(src) else "splishsplash" if splishsplash.is_case(src)
            else "sequence")
    if kind == "sequence" and src.is_dir() and not particle_files(src):
        raise InputError(f"{src}: neither a DualSPHysics output folder (PartFluid_*.vtk / PartAll_*.vtk), "
                         "SPlisHSPlasH output nor a sequence of particle frames")
    for opt, val in (("--xml", xml), ("--floating-csv", floating_csv), ("--scene", scene_json),
                     ("--fluid-model", fluid_model), ("--dt", dt), ("--radius", radius)):
        if val is not None and kind not in OPTION_KINDS[opt]:
            raise InputError(f"{src}: {opt} is for {KIND_NAMES[OPTION_KINDS[opt][0]][0]}; "
                             f"this is {KIND_NAMES[kind][1]}")
    if kind == "dualsphysics":
        return dualsphysics.read_output(src, xml=xml, up=up or "z", floating_csv=floating_csv)
    if kind == "splishsplash":
        return splishsplash.read_output(src, up=up or "y", scene_json=scene_json, model=fluid_model)
    return sequence.read_sequence(src, xml=xml, up=up or "z", dt=dt, radius=radius, option="--xml")


#: how each kind of input is named in messages: (the cases an option is for, what an input is)
KIND_NAMES = {"dualsphysics": ("DualSPHysics cases", "DualSPHysics output"),
              "splishsplash": ("SPlisHSPlasH cases", "SPlisHSPlasH output"),
              "sequence": ("bare sequences", "a bare sequence of frames")}
#: the kinds of input each option of `import` applies to
OPTION_KINDS = {"--xml": ("dualsphysics", "sequence"), "--floating-csv": ("dualsphysics",),
                "--scene": ("splishsplash",), "--fluid-model": ("splishsplash",), "--dt": ("sequence",),
                "--radius": ("sequence",)}
