"""A DualSPHysics output folder as a :class:`~whitecap.cases.Case`: fluid, tank, obstacles, moving bodies.

Files read (PartVTK legacy VTK, z up):

- the fluid: ``PartFluid_NNNN.vtk`` (else the fluid particles, ``Type`` 3, of ``PartAll_NNNN.vtk``);
- the boundaries: ``PartAll_NNNN.vtk`` (else ``PartBound_NNNN.vtk``), with the
  point arrays ``Type`` and ``Mk`` (and ``Idp`` for moving bodies);
- the case XML beside them (the only ``*.xml`` there; with several, ``xml=`` must
  choose, :func:`whitecap.cases.dualsphysics_xml.find_case_xml`): the spacing dp, output interval,
  constants, which Mks are one shape, and which are fixed, moving or floating
  (:mod:`whitecap.cases.dualsphysics_xml`).

PartVTK's ``Type``: 0 fixed, 1 moving, 2 floating, 3 fluid
(:data:`TYPE_NAMES`; 0 and 3 as in the shared dam-break output). An Mk is
moving when the XML says so (``<moving>``/``<floating>``) or its particles'
Type is 1 or 2.

Shapes: one per shape the XML names (else one per Mk), meshed from the
particles of the first boundary file as the union of their dp cells
(:mod:`whitecap.cases.particle_surface`); fixed shapes once. The shape that
holds the fluid (whose box holds most of the first frame's fluid) is the
``container``. A moving shape's pose at every fluid frame is the least-squares
rigid motion (:mod:`whitecap.cases.rigid_fit`) of its particles, matched by
``Idp``, from the first boundary file to that frame's; or, with
``floating_csv``, the motion DualSPHysics' FloatingInfo tool wrote
(:func:`read_floating_csv`).

Every fluid and boundary file is checked for truncation (:func:`whitecap.io.registry.check`,
headers and sizes only) before the case is returned, so a file cut short stops the import
before anything is written.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..config import DEFAULT_UP
from ..errors import InputError
from ..io.record import Pose
from ..io.registry import check, find_array
from ..io.sequence import frame_number
from ..io.vtk_legacy import DUALSPHYSICS_FLUID_TYPE as FLUID_TYPE
from . import Case, CaseShape
from .dualsphysics_xml import CaseInfo, find_case_xml, read_xml
from .particle_surface import cell_surface
from .rigid_fit import fit_pose, pose

#: PartVTK's particle Type codes
TYPE_NAMES = {0: "fixed", 1: "moving", 2: "floating", 3: "fluid"}
MOVING_TYPES = (1, 2)
#: a rigid fit needs this many particles (3 non-collinear fix a rotation; one more to be over-determined)
MIN_SHAPE_PARTICLES = 4
#: the container is the shape whose box holds at least this fraction of the first frame's fluid
CONTAINER_FLUID_FRACTION = 0.9
FLUID_PREFIX, ALL_PREFIX, BOUND_PREFIX = "PartFluid_", "PartAll_", "PartBound_"


def _named(folder: Path, prefix: str) -> list[Path]:
    """The ``PREFIX*.vtk`` files of a folder, listed (not globbed: the folder's name may hold ``[``)."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.name.startswith(prefix) and p.name.lower().endswith(".vtk"))


def _files(folder: Path, prefix: str) -> list[tuple[int, Path]]:
    files = _named(folder, prefix)
    if not files:
        return []
    frames: dict[int, Path] = {}
    for p in files:
        n = frame_number(p)
        if n is None:
            raise InputError(f"{p}: no frame number in the file name")
        if n in frames:
            raise InputError(f"{p}: frame {n} also given by {frames[n].name}")
        frames[n] = p
    return sorted(frames.items())


def is_case(folder: str | Path) -> bool:
    """Whether ``folder`` holds DualSPHysics PartVTK output (PartFluid_/PartAll_/PartBound_ files)."""
    f = Path(folder)
    return any(_named(f, p) for p in (FLUID_PREFIX, ALL_PREFIX, BOUND_PREFIX))


def _boundary_particles(path: Path) -> dict[str, np.ndarray]:
    """Positions, Type, Mk and Idp of the boundary (non-fluid) particles of one file."""
    from ..io.vtk_legacy import read_points

    pos, arrays = read_points(path)
    pos = pos.astype(np.float64)
    out = {"pos": pos}
    for name in ("Type", "Mk"):
        k = find_array(arrays, (name.lower(),))
        if k is None:
            raise InputError(f"{path}: missing array '{name}' (DualSPHysics boundary particles need Type and Mk); "
                             f"found {sorted(arrays) or 'no arrays'}")
        out[name] = np.asarray(arrays[k]).astype(np.int64).reshape(-1)
    ik = find_array(arrays, ("idp", "id"))
    out["Idp"] = np.asarray(arrays[ik]).astype(np.int64).reshape(-1) if ik else np.arange(len(pos))
    keep = out["Type"] != FLUID_TYPE
    return {k: v[keep] for k, v in out.items()}


def _xml(folder: Path, xml: str | Path | None) -> tuple[CaseInfo | None, Path | None]:
    p = find_case_xml(folder, xml, option="--xml")
    return (read_xml(p), p) if p is not None else (None, None)


def _groups(info: CaseInfo | None, mks: list[int]) -> list[tuple[str, list[int]]]:
    """Shapes as (name, Mks): the XML's shapes (Mks present in the data), then every other Mk alone."""
    groups, seen = [], set()
    for name, members in (info.shapes if info is not None else []):
        members = [m for m in members if m in mks and m not in seen]
        if members:
            groups.append((name, members))
            seen.update(members)
    groups += [(f"mk{m}", [m]) for m in mks if m not in seen]
    return groups


def read_output(folder: str | Path, xml: str | Path | None = None, up: str = DEFAULT_UP,
              floating_csv: str | Path | None = None) -> Case:
    """Read a DualSPHysics output folder (see the module docstring). Every check is made
    here, before anything is written: a bad input leaves the output untouched."""
    folder = Path(folder)
    if not is_case(folder):
        raise InputError(f"{folder}: no DualSPHysics PartVTK files (PartFluid_*.vtk, PartAll_*.vtk) found")
    if up != "z":
        raise InputError(f"{folder}: DualSPHysics output is z up; --up {up} does not apply")
    info, xml_path = _xml(folder, xml)
    fluid = _files(folder, FLUID_PREFIX) or _files(folder, ALL_PREFIX)
    if not fluid:
        raise InputError(f"{folder}: no fluid frames (PartFluid_*.vtk or PartAll_*.vtk)")
    bound = dict(_files(folder, ALL_PREFIX) or _files(folder, BOUND_PREFIX))
    for _, path in fluid + sorted(bound.items()):
        check(path)  # a file cut short is refused now, before anything is written (headers and sizes only)
    if info is None or not info.time_out:
        raise InputError(f"{folder}: the time between frames is unknown: no case XML with a TimeOut parameter "
                         "beside the files (pass --xml CASE.xml)")
    frame_dt = info.time_out
    times = [i * frame_dt for i, _ in fluid]
    case = Case(source=folder, solver="dualsphysics", fluid=fluid, frame_dt=frame_dt,
                particle_radius=info.particle_radius, rest_density=info.rho0, particle_mass=info.mass,
                gravity=list(info.gravity), times=times)
    if not bound:
        if floating_csv is not None:
            raise InputError(f"{floating_csv}: no boundary files (PartAll_*.vtk) in {folder} to place a body from")
        return case
    first_index = min(bound)
    b0 = _boundary_particles(bound[first_index])
    dp = info.dp
    mks = sorted(int(m) for m in np.unique(b0["Mk"]))
    for m in mks:
        n = int((b0["Mk"] == m).sum())
        if n < MIN_SHAPE_PARTICLES:
            raise InputError(f"{bound[first_index]}: mk {m} has {n} particle(s); a boundary shape needs at least "
                             f"{MIN_SHAPE_PARTICLES}")
    groups = _groups(info, mks)
    kinds = info.mk_kinds if info is not None else {}
    moving = []
    for name, members in groups:
        sel = np.isin(b0["Mk"], members)
        types = set(np.unique(b0["Type"][sel]).tolist())
        is_moving = bool(types & set(MOVING_TYPES)) or any(kinds.get(m) in ("moving", "floating") for m in members)
        v, f = cell_surface(b0["pos"][sel], dp)
        shape = CaseShape(name=name, vertices=v, faces=f, role="body" if is_moving else "obstacle",
                          source="mk " + ",".join(map(str, members)))
        case.shapes.append(shape)
        if is_moving:
            moving.append((shape, members, sel))
    _pick_container(case, [s for s in case.shapes if s.role == "obstacle"])
    if floating_csv is not None:
        _poses_from_csv(case, moving, Path(floating_csv), first_index * frame_dt)
    for shape, members, sel in moving:
        if shape.poses is None:
            shape.poses = _fitted_poses(case, bound, first_index, b0, members, sel, shape)
    return case


def _pick_container(case: Case, fixed: list[CaseShape]) -> None:
    """The fixed shape whose box holds most of the first frame's fluid becomes the container."""
    if not fixed:
        return
    from ..io import read

    fr = read(case.fluid[0][1])
    if not len(fr):
        return
    p = fr.positions.astype(np.float64)
    best, best_vol = None, -1.0
    for s in fixed:
        lo, hi = s.vertices.min(0), s.vertices.max(0)
        inside = np.all((p[:, :2] >= lo[:2]) & (p[:, :2] <= hi[:2]), axis=1) & (p[:, 2] >= lo[2])
        vol = float(np.prod(hi - lo))
        if inside.mean() >= CONTAINER_FLUID_FRACTION and vol > best_vol:
            best, best_vol = s, vol
    if best is not None:
        best.role = "container"


def _fitted_poses(case: Case, bound: dict[int, Path], first_index: int, b0: dict, members: list[int],
                  sel: np.ndarray, shape: CaseShape) -> list[Pose]:
    """Per fluid frame, the Kabsch fit of the body's particles (matched by Idp) from the first boundary file."""
    rest_ids = b0["Idp"][sel]
    order = np.argsort(rest_ids)
    rest_ids, rest = rest_ids[order], b0["pos"][sel][order]
    poses: list[Pose] = []
    for index, _ in case.fluid:
        path = bound.get(index)
        if path is None:
            raise InputError(f"{case.source}: {shape.name} ({shape.source}) moves, but frame {index} has no "
                             f"{ALL_PREFIX}{index:04d}.vtk to place it from (write PartAll files for every frame, "
                             "or pass --floating-csv)")
        b = b0 if index == first_index else _boundary_particles(path)
        mine = np.isin(b["Mk"], members)
        ids, pos = b["Idp"][mine], b["pos"][mine]
        common, ia, ib = np.intersect1d(rest_ids, ids, return_indices=True)
        if len(common) < MIN_SHAPE_PARTICLES:
            raise InputError(f"{path}: {shape.source} has {len(common)} of its particles; a rigid fit needs at "
                             f"least {MIN_SHAPE_PARTICLES}")
        poses.append(fit_pose(rest[ia], pos[ib], poses[-1] if poses else None))
    return poses


# ----------------------------------------------------------------------------- FloatingInfo CSV
def _rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw)·Ry(pitch)·Rx(roll), angles in degrees (roll about x, pitch about y, yaw about z)."""
    import trimesh.transformations as T

    M = T.concatenate_matrices(T.rotation_matrix(math.radians(yaw), [0, 0, 1]),
                               T.rotation_matrix(math.radians(pitch), [0, 1, 0]),
                               T.rotation_matrix(math.radians(roll), [1, 0, 0]))
    return M[:3, :3]


def _omega_step(omega: np.ndarray, dt: float) -> np.ndarray:
    """The rotation by angular velocity ``omega`` [rad/s] over ``dt`` (Rodrigues)."""
    import trimesh.transformations as T

    w = float(np.linalg.norm(omega))
    if w * dt == 0:
        return np.eye(3)
    return T.rotation_matrix(w * dt, omega / w)[:3, :3]


def read_floating_csv(path: str | Path) -> dict[str, np.ndarray]:
    """The columns of a FloatingInfo CSV (``FloatingMotion_mkNN.csv`` with ``-savemotion``, or
    ``FloatingInfo_mkNN.csv``), ``;`` or ``,`` separated, by lower-case name without units:
    ``time``, ``center.x``..., ``roll``/``pitch``/``yaw`` [deg] when present, ``fomega.x``... [rad/s]."""
    p = Path(path)
    try:
        lines = [ln.strip() for ln in p.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror})") from None
    if len(lines) < 2:
        raise InputError(f"{p}: not a FloatingInfo CSV (no header and rows)")
    sep = ";" if lines[0].count(";") >= lines[0].count(",") else ","
    names = [re.sub(r"\s*\[.*?\]\s*", "", h).strip().lower() for h in lines[0].split(sep)]
    names = [n.replace("fcenter", "center") for n in names]
    for need in ("time", "center.x", "center.y", "center.z"):
        if need not in names:
            raise InputError(f"{p}: missing column '{need}' (a DualSPHysics FloatingInfo CSV has time [s] and "
                             f"center.x/y/z [m]); found {', '.join(names)}")
    rows = []
    for n, ln in enumerate(lines[1:], 2):
        cells = [c.strip() for c in ln.rstrip(sep).split(sep)]
        try:
            rows.append([float(c) if c else math.nan for c in cells[:len(names)]])
        except ValueError:
            raise InputError(f"{p}: line {n}: not a row of numbers: {ln[:60]!r}") from None
        if len(rows[-1]) < len(names):
            raise InputError(f"{p}: line {n}: {len(rows[-1])} values for {len(names)} columns")
    data = np.array(rows, np.float64)
    return {name: data[:, k] for k, name in enumerate(names)}


def _poses_from_csv(case: Case, moving: list, path: Path, rest_time: float) -> None:
    """Poses of the floating body the CSV describes, at every fluid frame's time."""
    cols = read_floating_csv(path)
    m = re.search(r"mk(\d+)", path.name, re.IGNORECASE)
    if m is not None:
        pick = [x for x in moving if int(m.group(1)) in x[1]]
        if not pick:
            raise InputError(f"{path}: mk {m.group(1)} (from the file name) is not a moving or floating shape of "
                             f"{case.source}")
    elif len(moving) == 1:
        pick = moving
    else:
        raise InputError(f"{path}: {'no' if not moving else 'more than one'} floating body in {case.source}; "
                         "name the body in the file name (FloatingMotion_mkNN.csv)")
    shape = pick[0][0]
    t = cols["time"]
    tol = 1e-6 + 1e-3 * case.frame_dt

    def row_at(time: float, what: str) -> int:
        k = int(np.argmin(np.abs(t - time)))
        if abs(t[k] - time) > tol:
            raise InputError(f"{path}: no row at time {time:.6g} s ({what}); the CSV's times "
                             f"({t.min():.6g}..{t.max():.6g} s) must match the fluid frames")
        return k

    assert case.times is not None  # read_output gives every frame's time
    rows = [row_at(tm, f"frame {i}") for tm, (i, _) in zip(case.times, case.fluid)]
    k0 = row_at(rest_time, "the first boundary file")
    centre = np.stack([cols["center.x"], cols["center.y"], cols["center.z"]], 1)
    if all(a in cols for a in ("roll", "pitch", "yaw")):
        rot = [_rotation_rpy(cols["roll"][k], cols["pitch"][k], cols["yaw"][k]) for k in range(len(t))]
    elif all(f"fomega.{a}" in cols for a in "xyz"):
        # No angles (FloatingInfo without -savemotion): integrate the angular velocity, midpoint rule.
        om = np.stack([cols[f"fomega.{a}"] for a in "xyz"], 1)
        rot = [np.eye(3)]
        for k in range(1, len(t)):
            rot.append(_omega_step(0.5 * (om[k] + om[k - 1]), t[k] - t[k - 1]) @ rot[-1])
    else:
        raise InputError(f"{path}: no orientation: expected roll/pitch/yaw [deg] (FloatingInfo -savemotion) "
                         "or fomega.x/y/z [rad/s] columns")
    if not np.all(np.isfinite(centre[rows + [k0]])):
        raise InputError(f"{path}: a centre value at a frame's time is not a number")
    R0, c0 = rot[k0], centre[k0]
    poses: list[Pose] = []
    for k in rows:
        R = rot[k] @ R0.T
        poses.append(pose(R, centre[k] - R @ c0, poses[-1] if poses else None))
    shape.poses = poses
