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
from typing import TYPE_CHECKING

import numpy as np

from ..config import DEFAULT_UP, with_options

if TYPE_CHECKING:
    from ..io.record import Pose
    from ..io.run import RunInfo

#: roles a shape can have in a case
ROLES = ("container", "obstacle", "body")


@dataclass
class CaseShape:
    """One rigid shape of a case, z up, SI units.

    ``vertices``/``faces`` are the shape's mesh in its rest placement (world
    coordinates at the first frame). ``poses`` is None for a fixed shape;
    otherwise one pose per fluid frame, in frame order, each the rigid motion
    from the rest placement as ``run.json`` records it (:class:`whitecap.io.record.Pose`:
    position [x, y, z], quaternion [w, x, y, z]; world = T(position)·R(quaternion)·rest,
    see ``geometry.obstacle_matrix``).
    """

    name: str
    vertices: np.ndarray  # (V, 3) float64 [m]
    faces: np.ndarray  # (F, 3) int
    role: str = "obstacle"  # one of ROLES; "container" holds the fluid (a tank)
    poses: list[Pose] | None = None
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


@dataclass(frozen=True)
class ImportJob:
    """What one ``import`` does: the options of ``whitecap import`` and of
    :func:`whitecap.pipeline.import_case`, with their defaults, defined here once (the CLI and the
    pipeline build one; :func:`import_case` and :func:`read_case` take it).

    ``up`` is the case's up axis (None: z for DualSPHysics and bare sequences, y for
    SPlisHSPlasH); ``xml``/``floating_csv`` are DualSPHysics inputs, ``scene_json``/``fluid_model``
    SPlisHSPlasH ones, ``dt`` [s]/``radius`` [m] a bare sequence's; ``force`` replaces a run of
    another simulation at the output, whole.
    """

    up: str | None = None
    xml: str | Path | None = None
    floating_csv: str | Path | None = None
    scene_json: str | Path | None = None
    fluid_model: str | None = None
    dt: float | None = None
    radius: float | None = None
    force: bool = False
    show_progress: bool = True


def import_case(src: str | Path, out: str | Path, job: ImportJob | None = None, **options) -> RunInfo:
    """A whole case (or a bare sequence) at ``src`` -> the run directory ``out``, as ``job`` says
    (``options``, its field names, build one or replace its fields). The case is read and checked
    in full (:func:`read_case`) before anything is written (:func:`.run_dir.write_case`)."""
    from .run_dir import write_case

    job = with_options(ImportJob, job, options)
    return write_case(read_case(src, job), out, show_progress=job.show_progress, force=job.force)


def read_case(src: str | Path, job: ImportJob | None = None, **options) -> Case:
    """A DualSPHysics or SPlisHSPlasH output folder, else a bare sequence of frames, as a :class:`Case`,
    read as ``job`` says (``options``, its field names, build one or replace its fields): its
    ``xml``/``floating_csv`` are DualSPHysics inputs, ``scene_json``/``fluid_model`` SPlisHSPlasH
    ones, ``dt``/``radius`` a bare sequence's (:func:`whitecap.cases.sequence.read_sequence`, which
    reads a DualSPHysics case XML too)."""
    from ..errors import InputError
    from ..io.sequence import particle_files
    from . import dualsphysics, sequence, splishsplash

    job = with_options(ImportJob, job, options)
    up, xml = job.up, job.xml
    src = Path(src)
    pattern = any(c in str(src) for c in "*?[") and not src.exists()
    if not src.exists() and not pattern:
        raise InputError(f"{src}: no such file or directory")
    kind = ("dualsphysics" if dualsphysics.is_case(src) else "splishsplash" if splishsplash.is_case(src)
            else "sequence")
    if kind == "sequence" and src.is_dir() and not particle_files(src):
        raise InputError(f"{src}: neither a DualSPHysics output folder (PartFluid_*.vtk / PartAll_*.vtk), "
                         "SPlisHSPlasH output nor a sequence of particle frames")
    for opt, val in (("--xml", xml), ("--floating-csv", job.floating_csv), ("--scene", job.scene_json),
                     ("--fluid-model", job.fluid_model), ("--dt", job.dt), ("--radius", job.radius)):
        if val is not None and kind not in OPTION_KINDS[opt]:
            raise InputError(f"{src}: {opt} is for {KIND_NAMES[OPTION_KINDS[opt][0]][0]}; "
                             f"this is {KIND_NAMES[kind][1]}")
    if kind == "dualsphysics":
        return dualsphysics.read_output(src, xml=xml, up=up or "z", floating_csv=job.floating_csv)
    if kind == "splishsplash":
        return splishsplash.read_output(src, up=up or "y", scene_json=job.scene_json, model=job.fluid_model)
    return sequence.read_sequence(src, xml=xml, up=up or "z", dt=job.dt, radius=job.radius, option="--xml")


#: how each kind of input is named in messages: (the cases an option is for, what an input is)
KIND_NAMES = {"dualsphysics": ("DualSPHysics cases", "DualSPHysics output"),
              "splishsplash": ("SPlisHSPlasH cases", "SPlisHSPlasH output"),
              "sequence": ("bare sequences", "a bare sequence of frames")}
#: the kinds of input each option of `import` applies to
OPTION_KINDS = {"--xml": ("dualsphysics", "sequence"), "--floating-csv": ("dualsphysics",),
                "--scene": ("splishsplash",), "--fluid-model": ("splishsplash",), "--dt": ("sequence",),
                "--radius": ("sequence",)}
