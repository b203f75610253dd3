"""A bare sequence of particle frames as a :class:`~whitecap.cases.Case` with no shapes.

A bare sequence is a folder of numbered frames or a glob (``frames/*.vtk``) in any format the io
registry reads (PLY, VTU, NPZ, legacy VTK such as DualSPHysics' PartFluid files, partio BGEO):
only fluid, no tank or bodies. ``whitecap foam FOREIGN --out RUN`` imports it this way
(:func:`whitecap.cases.run_dir.write_case`) and makes foam over RUN as over any run, each frame
read once, from FOREIGN, and written into RUN by the foam pass.

Its constants come from the arguments, else from a DualSPHysics case XML beside the files
(:mod:`whitecap.cases.dualsphysics_xml`: spacing, mass, output interval, rest density,
gravity, domain). Without a domain (given or the case's) the run's domain is the flow's over
all frames (:func:`whitecap.io.run.flow_domain`), as for every other import.
"""

from __future__ import annotations

import math
from pathlib import Path

from ..config import DEFAULT_UP
from ..errors import InputError
from ..io.sequence import find_sequence
from . import Case
from .dualsphysics_xml import find_case_xml, read_xml

SOLVER = "sequence"


def read_sequence(src: str | Path, frames: list[tuple[int, Path]] | None = None, xml: str | Path | None = None,
                  up: str = DEFAULT_UP, dt: float | None = None, radius: float | None = None,
                  domain: tuple | None = None, option: str = "--case") -> Case:
    """The frames at ``src`` (``frames``, (index, path) pairs, when given) as a :class:`Case`.

    ``xml``: the DualSPHysics case XML (default: the only one beside the files; several are
    refused, asking for ``option``). ``dt`` [s] and ``radius`` [m] replace the XML's;
    ``domain`` ((lower, upper) [m]) replaces the XML's box."""
    src = Path(src)
    if frames is None:
        if not src.exists() and not any(c in str(src) for c in "*?["):
            raise InputError(f"{src}: no such file or directory")
        files = find_sequence(src)
    else:
        files = list(frames)
    xml_path = find_case_xml(src if src.is_dir() else src.parent, xml, option=option)
    c = read_xml(xml_path) if xml_path is not None else None
    for opt, v in (("--dt", dt), ("--radius", radius)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise InputError(f"{opt}: must be a positive number of {'seconds' if opt == '--dt' else 'metres'} "
                             f"(got {v:g})")
    frame_dt = dt or (c.time_out if c is not None else None)
    if not frame_dt or frame_dt <= 0:
        raise InputError(f"{src}: the time between frames is unknown; pass --dt SECONDS")
    r = radius or (c.particle_radius if c is not None else None)
    if not r or r <= 0:
        raise InputError(f"{src}: the particle radius is unknown; pass --radius METRES (half the spacing)")
    box, rule = None, "the case's"
    if domain is not None:
        box, rule = (list(map(float, domain[0])), list(map(float, domain[1]))), "given"
    elif c is not None and c.lower is not None and c.upper is not None:
        box, rule = (list(map(float, c.lower)), list(map(float, c.upper))), f"the case's ({xml_path})"
    return Case(
        source=src, solver=SOLVER, fluid=files, frame_dt=frame_dt, particle_radius=r,
        rest_density=c.rho0 if c is not None else 1000.0, particle_mass=c.mass if c is not None else None,
        gravity=list(c.gravity) if c is not None else [0.0, 0.0, -9.81], up=up, domain=box, domain_rule=rule,
        notes={"case": str(xml_path)} if xml_path is not None else {},
    )
