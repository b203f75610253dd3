"""SPlisHSPlasH output folders -> :class:`~whitecap.cases.Case`.

A SPlisHSPlasH run (``SPHSimulator --output-dir OUT scene.json``) leaves, in OUT:

- ``vtk/ParticleData_<model>_<k>.vtk``: the fluid of one fluid model per
  frame k = 1, 2, ... (legacy binary VTK, read by ``io/vtk_legacy.py``), or,
  when there is no VTK export, ``partio/ParticleData_<model>_<k>.bgeo``
  (``io/bgeo.py``). The solver z-sorts its particles, so the row order differs
  from frame to frame; the rows are put in ``id`` order on reading
  (``by_id``), which needs ``id`` in the scene's ``particleAttributes``.
- the rigid bodies (boundaries, walls, floating bodies) in up to four forms,
  read in this order of preference, the first one present winning:

  1. ``rigid_bodies/rb_data_<k>.bin`` (``enableRigidBodyExport``): per frame a
     pose (t, R) per body; the first file also holds the body list (mesh file
     name, scale, isWall). Exact: the mesh as modelled, posed by float32 poses.
  2. ``vtk/rb_data_<i>_<k>.vtk``, 3. ``ply/rb_data_<i>_<k>.ply``,
     4. ``obj/rb_data_<i>_<k>.obj``: body i's mesh in world space at frame k
     (a static body only at the first frame). The pose per frame is fitted by
     least squares (Kabsch) against the first frame's mesh, vertex by vertex.
  5. none of these: the scene JSON's ``RigidBodies`` with their placement
     (scale, then rotation ``rotationAxis``/``rotationAngle``, then
     ``translation``); only static bodies, as nothing says how dynamic ones moved.

The scene JSON (given, or the only ``*.json`` in OUT or OUT/Scenes) gives the
particle radius (``particleRadius``), the frame rate (``dataExportFPS``;
frame k is at t = (k − 1)/fps), gravity (``gravitation``) and the rest density
(``density0`` of the fluid model's material). SPlisHSPlasH gives each fluid
particle the volume 0.8·(2r)³, so its mass is ρ0·0.8·(2r)³.

A body with ``isWall`` is the case's container; a body that moves (or that the
scene calls ``isDynamic``) is a ``body`` with a pose per fluid frame; any other
is an ``obstacle``. Everything is turned z up with ``io.axes.to_z_up`` when the
solver's up axis is y (SPlisHSPlasH's default).

Every fluid frame is checked for truncation (:func:`whitecap.io.registry.check`, headers
and sizes only) when the case is read, so a frame cut short stops ``import`` before
anything is written; a BIN file cut short says ``truncated`` with the field it stops in.
"""

from __future__ import annotations

import difflib
import json
import math
import re
import warnings
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import read_mesh
from ..io.axes import to_z_up
from ..io.registry import check
from . import Case, CaseShape
from .rigid_bin import bin_files, first_world, read_bin_run, relative_poses
from .rigid_fit import fit_poses

SOLVER = "splishsplash"

#: SPlisHSPlasH's defaults for the scene fields read here (doc/file_format.md of SPlisHSPlasH 2.16)
DEFAULT_PARTICLE_RADIUS = 0.025  # [m]
DEFAULT_EXPORT_FPS = 25.0  # [1/s]
DEFAULT_GRAVITY = (0.0, -9.81, 0.0)  # [m/s²], y up
DEFAULT_DENSITY0 = 1000.0  # [kg/m³]
DEFAULT_FLUID_ID = "Fluid"
#: a fluid particle's volume is V = 0.8·(2r)³ (SPlisHSPlasH FluidModel, "volume of a particle")
PARTICLE_VOLUME_FACTOR = 0.8

#: fluid exports (folder, file pattern), in order of preference: VTK (enableVTKExport), partio (enablePartioExport)
FLUID_FORMS = (("vtk", re.compile(r"^ParticleData_(?P<model>.+)_(?P<k>\d+)\.vtk$")),
               ("partio", re.compile(r"^ParticleData_(?P<model>.+)_(?P<k>\d+)\.bgeo$")))
BIN_FOLDER = "rigid_bodies"
#: per-frame world-space mesh exports, in order of preference after the BIN (folder = extension)
MESH_FORMS = ("vtk", "ply", "obj")
_MESH_FILE = {f: re.compile(rf"^rb_data_(?P<i>\d+)_(?P<k>\d+)\.{f}$") for f in MESH_FORMS}

_MOVING_TOL = 1e-6  # [m] a body whose vertices move less than this in every frame is static

# Fields read from the scene, per block; a field spelled close to one of these is a typo.
_CONFIG_FIELDS = ("particleRadius", "dataExportFPS", "gravitation")
_MATERIAL_FIELDS = ("id", "density0")
_BODY_FIELDS = ("geometryFile", "translation", "rotationAxis", "rotationAngle", "scale", "isDynamic", "isWall")


# ============================================================================ entry points
def is_case(folder: str | Path) -> bool:
    """True when ``folder`` is a SPlisHSPlasH output folder (``vtk/ParticleData_*_<k>.vtk`` or
    ``partio/ParticleData_*_<k>.bgeo``)."""
    return any(_fluid_files(Path(folder) / sub, pattern) for sub, pattern in FLUID_FORMS)


def _fluid_files(d: Path, pattern: re.Pattern) -> dict[str, dict[int, Path]]:
    """{model: {frame: file}} of one fluid export folder."""
    out: dict[str, dict[int, Path]] = {}
    if d.is_dir():
        for p in d.iterdir():
            m = pattern.match(p.name)
            if m:
                out.setdefault(m["model"], {})[int(m["k"])] = p
    return out


def read_output(folder: str | Path, up: str = "y", scene_json: str | Path | None = None,
              model: str | None = None) -> Case:
    """Read a SPlisHSPlasH output folder as a :class:`Case` (see the module doc).

    ``scene_json``: the scene file that was run (default: the only ``*.json`` in
    the folder or in its ``Scenes/``). ``model``: the fluid model's id when the
    folder holds more than one. Raises InputError naming the file and field on
    bad input."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    fluid_model, fluid = _fluid_frames(folder, model)
    for _, path in fluid:
        check(path)  # a frame cut short is refused now, before anything is written (headers and sizes only)
    scene_path = Path(scene_json) if scene_json is not None else _find_scene(folder)
    scene = _Scene(scene_path)
    r = scene.config_number("particleRadius", DEFAULT_PARTICLE_RADIUS)
    fps = scene.config_number("dataExportFPS", DEFAULT_EXPORT_FPS)
    gravity = scene.config_vector("gravitation", DEFAULT_GRAVITY)
    rho0 = scene.density0(fluid_model)
    M = _axes(up)
    shapes = _rigid_shapes(folder, scene, [k for k, _ in fluid], M)
    return Case(
        source=folder,
        solver=SOLVER,
        fluid=fluid,
        frame_dt=1.0 / fps,
        particle_radius=r,
        rest_density=rho0,
        particle_mass=rho0 * PARTICLE_VOLUME_FACTOR * (2.0 * r) ** 3,
        gravity=[float(v) for v in M @ np.asarray(gravity, np.float64)],
        up=up,
        shapes=shapes,
        times=[(k - 1) / fps for k, _ in fluid],
        fluid_reader_options={"by_id": True},
    )


# ============================================================================ fluid
def _fluid_frames(folder: Path, model: str | None) -> tuple[str, list[tuple[int, Path]]]:
    """The fluid model's frames from the first fluid export present (VTK, else partio)."""
    for sub, pattern in FLUID_FORMS:
        d = folder / sub
        by_model = _fluid_files(d, pattern)
        if by_model:
            break
    else:
        raise InputError(f"{folder}: no SPlisHSPlasH fluid files (vtk/ParticleData_<model>_<frame>.vtk or "
                         "partio/ParticleData_<model>_<frame>.bgeo); "
                         "enable enableVTKExport in the scene's Configuration")
    if model is None:
        if len(by_model) > 1:
            raise InputError(f"{d}: several fluid models ({', '.join(sorted(by_model))}); choose one")
        model = next(iter(by_model))
    elif model not in by_model:
        raise InputError(f"{d}: no fluid model '{model}' (found {', '.join(sorted(by_model))})")
    return model, sorted(by_model[model].items())


# ============================================================================ scene JSON
def _find_scene(folder: Path) -> Path:
    found = sorted(folder.glob("*.json")) + sorted((folder / "Scenes").glob("*.json"))
    if len(found) == 1:
        return found[0]
    if not found:
        raise InputError(f"{folder}: no scene JSON beside the output (looked for *.json in it and in Scenes/); "
                         "give the scene file that was run (it holds particleRadius and dataExportFPS)")
    raise InputError(f"{folder}: several scene JSON files ({', '.join(p.name for p in found)}); "
                     "give the one that was run")


class _Scene:
    """The fields of a SPlisHSPlasH scene file this reader uses, checked with the file and field in errors."""

    def __init__(self, path: Path):
        self.path = path
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(f"{path}: scene file not found") from None
        except json.JSONDecodeError as exc:
            raise InputError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"{path}: cannot read the scene file ({exc})") from None
        if not isinstance(data, dict):
            raise InputError(f"{path}: a scene file is a JSON object, got {type(data).__name__}")
        self.config = self._block(data, "Configuration", dict, {})
        self._check_spelling(self.config, "Configuration", _CONFIG_FIELDS)
        self.materials = self._block(data, "Materials", list, [])
        self.bodies = self._block(data, "RigidBodies", list, [])
        for i, b in enumerate(self.materials):
            self._entry(b, f"Materials[{i}]", _MATERIAL_FIELDS)
        for i, b in enumerate(self.bodies):
            self._entry(b, f"RigidBodies[{i}]", _BODY_FIELDS)
        # every body is checked now, whichever export the placement is later taken from
        self._placements = [self._placement(i) for i in range(len(self.bodies))]
        self._flags = [self._body_flags(i) for i in range(len(self.bodies))]

    def fail(self, field: str, what: str) -> InputError:
        return InputError(f"{self.path}: {field}: {what}")

    def _block(self, data: dict, key: str, kind: type, default):
        v = data.get(key, default)
        if not isinstance(v, kind):
            raise self.fail(key, f"expected a JSON {'object' if kind is dict else 'array'}, got {v!r:.60}")
        return v

    def _entry(self, entry, at: str, fields: tuple[str, ...]) -> None:
        if not isinstance(entry, dict):
            raise self.fail(at, f"expected a JSON object, got {entry!r:.60}")
        self._check_spelling(entry, at, fields)

    def _check_spelling(self, block: dict, at: str, fields: tuple[str, ...]) -> None:
        """A key that is not one of ``fields`` but spelled like one that is absent is a typo
        (SPlisHSPlasH would silently use the default): refuse it."""
        lower = {f.lower(): f for f in fields}
        for key in block:
            if key in fields:
                continue
            near = lower.get(key.lower()) or next(iter(difflib.get_close_matches(key, fields, n=1, cutoff=0.8)), None)
            if near is not None and near not in block:
                raise self.fail(f"{at}.{key}", f"unknown field (did you mean '{near}'?)")

    # ---------------------------------------------------------------- typed fields
    def number(self, block: dict, key: str, at: str, default: float, positive: bool = False) -> float:
        v = block.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
            raise self.fail(f"{at}{key}", f"expected a {'positive ' if positive else ''}number, got {v!r:.60}")
        return float(v)

    def vector(self, block: dict, key: str, at: str, default, n: int = 3, scalar_ok: bool = False) -> np.ndarray:
        v = block.get(key, default)
        if scalar_ok and isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v] * n
        ok = isinstance(v, list) and len(v) == n and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        if not ok:
            raise self.fail(f"{at}{key}", f"expected {n} numbers, got {v!r:.60}")
        return np.asarray(v, np.float64)

    def flag(self, block: dict, key: str, at: str, default: bool = False) -> bool:
        v = block.get(key, default)
        if not isinstance(v, bool):
            raise self.fail(f"{at}{key}", f"expected true or false, got {v!r:.60}")
        return v

    def config_number(self, key: str, default: float) -> float:
        return self.number(self.config, key, "Configuration.", default, positive=True)

    def config_vector(self, key: str, default) -> np.ndarray:
        return self.vector(self.config, key, "Configuration.", list(default))

    def density0(self, model: str) -> float:
        """Rest density of the fluid model's material (SPlisHSPlasH matches materials by ``id``)."""
        for i, m in enumerate(self.materials):
            if m.get("id", DEFAULT_FLUID_ID) == model:
                return self.number(m, "density0", f"Materials[{i}].", DEFAULT_DENSITY0, positive=True)
        return DEFAULT_DENSITY0

    def body_placement(self, i: int) -> tuple[Path, np.ndarray, np.ndarray, np.ndarray]:
        """(mesh file, scale, R, t) of RigidBodies[i]: world = R·(scale ∘ v) + t."""
        return self._placements[i]

    def body_flags(self, i: int) -> tuple[bool, bool]:
        """(isWall, isDynamic) of RigidBodies[i]."""
        return self._flags[i]

    def _placement(self, i: int) -> tuple[Path, np.ndarray, np.ndarray, np.ndarray]:
        b, at = self.bodies[i], f"RigidBodies[{i}]."
        mesh = b.get("geometryFile")
        if not isinstance(mesh, str) or not mesh:
            raise self.fail(f"{at}geometryFile", f"expected the body's mesh file, got {mesh!r:.60}")
        scale = self.vector(b, "scale", at, [1.0, 1.0, 1.0], scalar_ok=True)
        t = self.vector(b, "translation", at, [0.0, 0.0, 0.0])
        axis = self.vector(b, "rotationAxis", at, [1.0, 0.0, 0.0])
        angle = self.number(b, "rotationAngle", at, 0.0)  # [rad]
        norm = float(np.linalg.norm(axis))
        if norm == 0.0 and angle != 0.0:
            raise self.fail(f"{at}rotationAxis", "a zero axis with a non-zero rotationAngle")
        return (self.path.parent / mesh), scale, _axis_angle(axis / (norm or 1.0), angle), t

    def _body_flags(self, i: int) -> tuple[bool, bool]:
        b, at = self.bodies[i], f"RigidBodies[{i}]."
        return self.flag(b, "isWall", at), self.flag(b, "isDynamic", at)


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` [rad] about the unit ``axis`` (Rodrigues)."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _axes(up: str) -> np.ndarray:
    """The proper rotation M taking the solver's axes to whitecap's z up (the project's ``to_z_up``)."""
    rows, _ = to_z_up(np.eye(3, dtype=np.float32), None, up)  # row j = M·e_j
    return np.asarray(rows, np.float64).T


# ============================================================================ rigid bodies
def _rigid_shapes(folder: Path, scene: _Scene, frames: list[int], M: np.ndarray) -> list[CaseShape]:
    bins = bin_files(folder / BIN_FOLDER)
    if bins:
        return _from_bin(folder / BIN_FOLDER, bins, scene, frames, M)
    for form in MESH_FORMS:
        files = _mesh_exports(folder / form, form)
        if files:
            return _from_meshes(folder / form, files, scene, frames, M)
    return _from_scene(scene, M)


def _numbered(d: Path, pattern: re.Pattern) -> dict[int, Path]:
    if not d.is_dir():
        return {}
    return {int(m["k"]): p for p in d.iterdir() if (m := pattern.match(p.name))}


def _mesh_exports(d: Path, form: str) -> dict[int, dict[int, Path]]:
    """{body index: {frame: file}} of one per-frame mesh form."""
    out: dict[int, dict[int, Path]] = {}
    if d.is_dir():
        for p in d.iterdir():
            m = _MESH_FILE[form].match(p.name)
            if m:
                out.setdefault(int(m["i"]), {})[int(m["k"])] = p
    return out


def _role(wall: bool, moves: bool) -> str:
    return "container" if wall else ("body" if moves else "obstacle")


#: How a wall that encloses the fluid on every side is rendered: a closed tank drawn opaque would
#: hide the water (SPlisHSPlasH itself does not draw walls), so it is a thin glass pane.
ENCLOSING_WALL_LOOK = {"material": "glass", "color": [0.93, 0.97, 0.96]}


def _look(wall: bool, vertices: np.ndarray, faces: np.ndarray) -> dict | None:
    """The render look of a wall whose mesh is closed (it holds the fluid inside), else the role's."""
    import trimesh

    closed = trimesh.Trimesh(vertices, faces, process=True).is_watertight
    return dict(ENCLOSING_WALL_LOOK) if wall and closed else None


def _names(stems: list[str]) -> list[str]:
    seen: dict[str, int] = {}
    out = []
    for s in stems:
        seen[s] = seen.get(s, 0) + 1
        out.append(s if seen[s] == 1 else f"{s}_{seen[s]}")
    return out


def _welded(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A model mesh with the copies of a vertex that OBJ texture coordinates split off merged again."""
    mesh = read_mesh(path)
    v, inv = np.unique(np.asarray(mesh.vertices, np.float64), axis=0, return_inverse=True)
    f = inv.reshape(-1)[mesh.faces]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    if len(f) == 0:
        raise InputError(f"{path}: no triangles in this mesh")
    return v, f


def _check_bodies_match(source: Path, n: int, scene: _Scene) -> None:
    if scene.bodies and len(scene.bodies) != n:
        raise InputError(f"{source}: {n} rigid bodies, but {scene.path}: RigidBodies lists {len(scene.bodies)}")


def _check_frames(source: Path, have: list[int], frames: list[int], what: str) -> None:
    if sorted(have) != list(frames):
        missing = sorted(set(frames) - set(have))
        extra = sorted(set(have) - set(frames))
        detail = (f"missing frames {_span(missing)}" if missing else "") + \
            ("; " if missing and extra else "") + (f"extra frames {_span(extra)}" if extra else "")
        raise InputError(f"{source}: {what}: {len(have)} frames but the fluid has {len(frames)} ({detail})")


def _span(ks: list[int]) -> str:
    return ", ".join(map(str, ks[:5])) + (", ..." if len(ks) > 5 else "")


# ---------------------------------------------------------------------------- BIN form
def _from_bin(d: Path, bins: dict[int, Path], scene: _Scene, frames: list[int], M: np.ndarray) -> list[CaseShape]:
    first = min(frames)
    if first not in bins:
        raise InputError(f"{d / f'rb_data_{first}.bin'}: missing; its header lists the bodies "
                         f"(found {len(bins)} other rb_data_*.bin)")
    if len(bins) > 1:
        _check_frames(d, list(bins), frames, "rigid-body poses (rb_data_<k>.bin)")
        ks = frames
    else:
        ks = [first]  # a scene of static bodies only: the solver writes the first file alone
    header, Rs, ts = read_bin_run(bins, ks)
    _check_bodies_match(bins[first], len(header), scene)
    names = _names([Path(name).stem for name, _, _ in header])
    shapes = []
    for i, (name, scale, wall) in enumerate(header):
        mesh = d / name
        if not mesh.is_file():
            raise InputError(f"{bins[first]}: body {i}: mesh file {name} not found beside it")
        v, f = _welded(mesh)
        moves = len(ks) > 1 and _moves(v * scale, Rs[i], ts[i])
        dynamic = scene.body_flags(i)[1] if scene.bodies else False
        if dynamic and len(ks) == 1 and len(frames) > 1:
            raise InputError(f"{d}: only rb_data_{first}.bin, but {scene.path}: RigidBodies[{i}].isDynamic "
                             "is true: the poses of later frames are missing")
        shapes.append(CaseShape(
            name=names[i], vertices=first_world(v, scale, Rs[i][0], ts[i][0], M), faces=f,
            role=_role(wall, moves or dynamic),
            poses=relative_poses(Rs[i], ts[i], M) if (moves or dynamic) and len(ks) > 1 else None,
            source=f"rigid body {i} ({d.name}/rb_data_<k>.bin, {name})", look=_look(wall, v, f),
        ))
    return shapes


def _moves(v: np.ndarray, Rs: list[np.ndarray], ts: list[np.ndarray]) -> bool:
    p0 = v @ Rs[0].T + ts[0]
    return any(np.abs(v @ R.T + t - p0).max() > _MOVING_TOL for R, t in zip(Rs[1:], ts[1:]))


# ---------------------------------------------------------------------------- per-frame mesh forms
def _from_meshes(d: Path, files: dict[int, dict[int, Path]], scene: _Scene, frames: list[int],
                 M: np.ndarray) -> list[CaseShape]:
    n = max(files) + 1
    if sorted(files) != list(range(n)):
        raise InputError(f"{d}: rigid-body meshes for bodies {sorted(files)}; bodies "
                         f"{sorted(set(range(n)) - set(files))} are missing")
    _check_bodies_match(d, n, scene)
    stems = [Path(scene.body_placement(i)[0]).stem if scene.bodies else f"body{i}" for i in range(n)]
    names = _names(stems)
    first = min(frames)
    shapes = []
    for i in range(n):
        per_frame = files[i]
        if first not in per_frame:
            raise InputError(f"{d}: body {i}: no mesh at the first frame ({first})")
        wall, dynamic = scene.body_flags(i) if scene.bodies else (False, False)
        rest = read_mesh(per_frame[first])
        rest_v = np.asarray(rest.vertices, np.float64) @ M.T
        poses = None
        if len(per_frame) > 1 or (dynamic and len(frames) > 1):
            _check_frames(d, list(per_frame), frames, f"body {i} meshes (rb_data_{i}_<k>)")
            moved = []
            for k in frames:
                mk = read_mesh(per_frame[k])
                if len(mk.vertices) != len(rest_v):
                    raise InputError(f"{per_frame[k]}: {len(mk.vertices)} vertices, but the first frame's mesh "
                                     f"has {len(rest_v)}: vertex correspondence is needed to fit the pose")
                moved.append(np.asarray(mk.vertices, np.float64) @ M.T)
            poses = fit_poses(rest_v, moved)
            moves = any(np.abs(q - rest_v).max() > _MOVING_TOL for q in moved)
            if not (moves or dynamic):
                poses = None
        shapes.append(CaseShape(
            name=names[i], vertices=rest_v, faces=np.asarray(rest.faces), role=_role(wall, poses is not None),
            poses=poses, source=f"rigid body {i} ({d.name}/rb_data_{i}_<k>.{d.name})",
            look=_look(wall, rest_v, np.asarray(rest.faces)),
        ))
    return shapes


# ---------------------------------------------------------------------------- scene JSON only
def _from_scene(scene: _Scene, M: np.ndarray) -> list[CaseShape]:
    names = _names([Path(scene.body_placement(i)[0]).stem for i in range(len(scene.bodies))])
    shapes = []
    for i in range(len(scene.bodies)):
        mesh, scale, R, t = scene.body_placement(i)
        wall, dynamic = scene.body_flags(i)
        if dynamic:
            warnings.warn(f"{scene.path}: RigidBodies[{i}] is dynamic but the output has no rigid-body export "
                          "(enableRigidBodyExport); its motion is unknown, so it is left out", stacklevel=2)
            continue
        if not mesh.is_file():
            raise InputError(f"{scene.path}: RigidBodies[{i}].geometryFile: {mesh} not found")
        v, f = _welded(mesh)
        world = (v * scale) @ R.T + t
        shapes.append(CaseShape(name=names[i], vertices=world @ M.T, faces=f, role=_role(wall, False),
                                source=f"rigid body {i} ({scene.path.name} RigidBodies[{i}])", look=_look(wall, v, f)))
    return shapes
