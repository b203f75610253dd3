"""The DualSPHysics case XML: the spacing, mass, output time step and domain of a run, and its
boundary shapes (read by ``import`` and by ``foam`` over PartVTK frames).

GenCase writes, besides the drawing commands, what it made of them:

- ``<execution><particles>``: one ``<fixed>``, ``<moving>`` or ``<floating>``
  element per boundary Mk (``mk`` = ``mkbound`` + ``mkboundfirst``), which says
  how that Mk's particles move;
- ``<execution><vtkout><vtkfile name="CASE_NAME_Dp.vtk" mk="11,20">``: the
  Mks drawn as one shape (between two ``<shapeout file="NAME"/>`` commands in
  ``<mainlist>``). When ``vtkout`` is missing the ``shapeout`` commands of the
  main list are followed instead.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
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
    #: boundary Mk -> "fixed", "moving" or "floating" (from <execution><particles>)
    mk_kinds: dict[int, str] = field(default_factory=dict)
    #: shapes as GenCase drew them: (name, [Mk...]) in drawing order
    shapes: list[tuple[str, list[int]]] = field(default_factory=list)

    @property
    def particle_radius(self) -> float:
        return self.dp / 2.0

    @property
    def mass(self) -> float:
        return self.rho0 * self.dp**3


def find_case_xml(folder: str | Path, xml: str | Path | None = None, option: str = "--xml") -> Path | None:
    """The case XML of a DualSPHysics output ``folder``: ``xml`` when given (it must be a file),
    else the only ``*.xml`` file in the folder; None when there is none. Several XML files are
    refused (InputError, one line naming the folder and the candidates and asking for
    ``option``: ``--xml`` for ``import``, ``--case`` for ``foam``): their output intervals and
    spacings may differ, and picking one by name would be a guess."""
    if xml is not None:
        p = Path(xml)
        if not p.is_file():
            raise InputError(f"{p}: case XML not found")
        return p
    d = Path(folder)
    if not d.is_dir():
        return None
    found = sorted(q for q in d.iterdir() if q.suffix.lower() == ".xml" and q.is_file() and not q.name.startswith("."))
    if len(found) > 1:
        raise InputError(f"{d}: {len(found)} case XML files ({', '.join(q.name for q in found)}); "
                         f"choose the one that was run with {option} FILE")
    return found[0] if found else None


def read_xml(path: str | Path) -> CaseInfo:
    """The case XML at ``path``: spacing, constants, output interval, domain and boundary shapes."""
    p = Path(path)
    try:
        root = ET.parse(p).getroot()
    except (OSError, ET.ParseError) as exc:
        raise InputError(f"{p}: not a readable DualSPHysics case XML ({exc})") from None
    d = root.find(".//definition")
    if d is None or "dp" not in d.attrib:
        raise InputError(f"{p}: missing <definition dp=...> (particle spacing)")

    def vec(e: ET.Element | None) -> list[float] | None:
        return [_number(p, e, k) for k in "xyz"] if e is not None else None

    rho = root.find(".//constantsdef/rhop0")
    rho = rho if rho is not None else root.find(".//rhop0")
    dt = None
    for par in root.iter("parameter"):
        if par.get("key", "").lower() == "timeout":
            dt = _number(p, par, "value")
    try:
        kinds, shapes = _boundary_shapes(root, p.stem)
    except ValueError as exc:
        raise InputError(f"{p}: {exc}") from None
    return CaseInfo(
        mk_kinds=kinds,
        shapes=shapes,
        dp=_number(p, d, "dp"),
        rho0=_number(p, rho, "value") if rho is not None else 1000.0,
        time_out=dt,
        gravity=vec(root.find(".//gravity")) or [0.0, 0.0, -9.81],
        lower=vec(d.find("pointmin")),
        upper=vec(d.find("pointmax")),
    )


BOUNDARY_KINDS = ("fixed", "moving", "floating")


def _number(p: Path, e: ET.Element, key: str) -> float:
    """Attribute ``key`` of element ``e`` as a number; InputError naming the file, element and
    attribute when it is missing or not a number."""
    text = e.get(key)
    if text is not None:
        try:
            return float(text)
        except ValueError:
            pass
    raise InputError(f"{p}: <{e.tag} {key}=...>: expected a number, got {text!r}")


def _mk_list(text: str) -> list[int]:
    """'11,20' or '10-12,20' -> [11, 20] / [10, 11, 12, 20]."""
    out: list[int] = []
    for part in (text or "").replace(" ", "").split(","):
        if not part:
            continue
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


def _boundary_shapes(root, case_stem: str) -> tuple[dict[int, str], list[tuple[str, list[int]]]]:
    """(Mk -> kind, [(shape name, [Mk...])]) from the XML GenCase wrote (see the module docstring)."""
    kinds: dict[int, str] = {}
    parts = root.find(".//execution/particles")
    first = None
    if parts is not None:
        for e in parts:
            if e.tag in BOUNDARY_KINDS and e.get("mk") is not None:
                kinds[int(e.get("mk"))] = e.tag
        if parts.get("mkboundfirst") is not None:
            first = int(parts.get("mkboundfirst"))
    shapes: list[tuple[str, list[int]]] = []
    vtkout = root.find(".//execution/vtkout")
    if vtkout is not None:
        first = int(vtkout.get("mkboundfirst", first if first is not None else 0))
        for f in vtkout.findall("vtkfile"):
            name = f.get("name", "").removeprefix(case_stem + "_").removesuffix(".vtk").removesuffix("_Dp")
            name = name or f"mk{f.get('mk')}"
            shapes.append((name, _mk_list(f.get("mk", ""))))
    if not shapes:  # follow the drawing commands: the bound Mks set between two shapeouts are one shape
        first = first if first is not None else 0
        current, group = None, []
        ml = root.find(".//geometry/commands/mainlist")
        for e in ml if ml is not None else []:
            if e.tag == "setmkbound":
                current = int(e.get("mk")) + first
            elif e.tag in ("setmkfluid", "setmkvoid"):
                current = None
            elif e.tag.startswith("draw") and current is not None and current not in group:
                group.append(current)
            elif e.tag == "shapeout" and group:
                shapes.append((e.get("file") or f"mk{group[0]}", group))
                group = []
        if group:
            shapes.append((f"mk{group[0]}", group))
    return kinds, shapes
