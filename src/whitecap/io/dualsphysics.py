"""DualSPHysics case XML: the spacing, mass, output time step and domain of a run."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError


@dataclass
class CaseInfo:
    dp: float  # particle spacing [m]
    rho0: float  # reference density [kg/m³]
    time_out: float | None  # time between output frames [s]
    gravity: list[float]
    lower: list[float] | None
    upper: list[float] | None

    @property
    def particle_radius(self) -> float:
        return self.dp / 2.0

    @property
    def mass(self) -> float:
        return self.rho0 * self.dp**3


def read_case(path: str | Path) -> CaseInfo:
    p = Path(path)
    try:
        root = ET.parse(p).getroot()
    except (OSError, ET.ParseError) as exc:
        raise InputError(f"{p}: not a readable DualSPHysics case XML ({exc})") from None
    d = root.find(".//definition")
    if d is None or "dp" not in d.attrib:
        raise InputError(f"{p}: missing <definition dp=...> (particle spacing)")

    def vec(e, default=None):
        return [float(e.get(k)) for k in "xyz"] if e is not None else default

    rho = root.find(".//constantsdef/rhop0")
    rho = rho if rho is not None else root.find(".//rhop0")
    dt = None
    for par in root.iter("parameter"):
        if par.get("key", "").lower() == "timeout":
            dt = float(par.get("value"))
    return CaseInfo(
        dp=float(d.get("dp")),
        rho0=float(rho.get("value")) if rho is not None else 1000.0,
        time_out=dt,
        gravity=vec(root.find(".//gravity"), [0.0, 0.0, -9.81]),
        lower=vec(d.find("pointmin")),
        upper=vec(d.find("pointmax")),
    )
