"""The run record: what ``run.json`` holds, as types, with each field's default in one place.

- :class:`RunRecord`: the run (particle radius, rest density and mass, gravity, domain box, frame
  rate, the simulation's identity, the frame table, the obstacles); ``io/run.py``'s ``RunInfo``
  adds reading, writing and the frame table's look-ups to it;
- :class:`Frame`: one frame's index, simulated time, files by kind, the simulation each was made
  from, the bodies' poses and what the stages noted about it;
- :class:`Obstacle`: an obstacle's meshes, rest placement (``geometry.obstacle_transform``) and look;
- :class:`Pose`: a moving body's pose at a frame (``geometry.pose_matrix``);
- :data:`Domain`, :data:`Extra`: the domain box and the free-form ``extra`` object, plain dicts
  whose known keys are typed.

With pydantic (whitecap's own Python) the records are pydantic models: reading checks every field,
and a bad one is a ``ValidationError`` whose location names it (``RunInfo.load`` makes it one line
naming run.json and the field). Blender's own Python has no pydantic (the add-on carries only
pure-Python wheels): there the same classes are plain records (:class:`_Plain`) filled from the
file as it is, with the same fields and defaults, unchecked.

A record written back is the object it was read from, byte for byte: numbers keep their JSON type
(an int stays an int), a frame's or an obstacle's keys keep their order, fields the file did not
have stay out of it, and keys whitecap does not know are kept.
"""

from __future__ import annotations

import copy
import math
import typing
from typing import Annotated, Any

try:
    from typing_extensions import TypedDict  # pydantic wants it below Python 3.12
except ImportError:  # Blender's Python
    from typing import TypedDict

FORMAT = "whitecap-run"
FORMAT_VERSION = 1
#: The base colour of an obstacle whose entry has none (linear RGB; the "glass" preset has its own:
#: blender/looks.GLASS_COLOR), as the scene's ``[[obstacle]] color`` defaults to.
OBSTACLE_COLOR = (0.8, 0.78, 0.72)
#: A pose's quaternion is unit within this much of |q|² (poses are written in float64).
UNIT_QUATERNION_TOLERANCE = 1e-3


# ----------------------------------------------------------------------------- checks of one value
def _number(v: Any) -> Any:
    """A finite JSON number, kept as it is (int or float)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"expected a number, got {v!r}")
    return v


def _positive(v: Any) -> Any:
    if _number(v) <= 0:
        raise ValueError(f"expected a positive number, got {v!r}")
    return v


def _integer(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"expected an integer, got {v!r}")
    return v


def _frame_index(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise ValueError(f"expected a frame number, got {v!r}")
    return v


def _numbers(n: int, what: str):
    def check(v: Any) -> list:
        if not isinstance(v, (list, tuple)) or len(v) != n:
            raise ValueError(f"expected {what}, got {v!r}")
        for x in v:
            _number(x)
        return list(v)
    return check


def _unit_quaternion(v: Any) -> list:
    q = _numbers(4, "a unit quaternion (w, x, y, z)")(v)
    if abs(math.fsum(x * x for x in q) - 1.0) >= UNIT_QUATERNION_TOLERANCE:
        raise ValueError(f"expected a unit quaternion (w, x, y, z), got {v!r}")
    return q


def relpath_problem(rel: Any) -> str | None:
    """Why ``rel`` is not a file path relative to the run and inside it (None: it is)."""
    if not isinstance(rel, str) or not rel or "\0" in rel:
        return f"expected a file path, got {rel!r}"
    parts = rel.replace("\\", "/").split("/")
    if rel.startswith(("/", "\\")) or ".." in parts or (len(parts[0]) >= 2 and parts[0][1] == ":"):
        return f"{rel!r} is not a relative path inside the run"
    return None


def _relpath(v: Any) -> str:
    problem = relpath_problem(v)
    if problem:
        raise ValueError(problem)
    return v


try:
    from pydantic import (
        BaseModel,
        ConfigDict,
        PlainSerializer,
        PlainValidator,
        PrivateAttr,
        WrapValidator,
        model_serializer,
        model_validator,
        with_config,
    )

    HAVE_PYDANTIC = True
except ImportError:  # Blender's Python: plain records, below
    HAVE_PYDANTIC = False

# To a type checker the records are the pydantic models (the plain ones below share their fields).
if typing.TYPE_CHECKING or HAVE_PYDANTIC:
    def _checked(check):
        """A value checked by ``check`` and written back as it was read."""
        return (PlainValidator(check), PlainSerializer(lambda v: v))

    Number = Annotated[float, *_checked(_number)]
    PositiveNumber = Annotated[float, *_checked(_positive)]
    Integer = Annotated[int, *_checked(_integer)]
    FrameIndex = Annotated[int, *_checked(_frame_index)]
    Vec3 = Annotated[list[float], *_checked(_numbers(3, "3 numbers"))]
    Quaternion = Annotated[list[float], *_checked(_unit_quaternion)]
    RelPath = Annotated[str, *_checked(_relpath)]

    def _keep_order(v: Any, handler) -> Any:
        """A typed dict validated, its keys in the order they came (pydantic puts the known ones first)."""
        out = handler(v)
        return {**{k: out[k] for k in v if k in out}, **out} if isinstance(v, dict) else out

    def _ordered(t: Any) -> Any:
        return Annotated[t, WrapValidator(_keep_order)]

    class _Record(BaseModel):
        """A JSON object of run.json: written back with its keys in the order they were read, without
        the fields it did not have (new records: in the order declared), keys not declared kept."""

        model_config = ConfigDict(extra="allow", validate_assignment=True)
        _keys: tuple = PrivateAttr(())

        @model_validator(mode="wrap")
        @classmethod
        def _remember_keys(cls, data: Any, handler):
            rec = handler(data)
            if isinstance(data, dict):
                rec._keys = tuple(data)
            return rec

        @model_serializer(mode="wrap")
        def _as_read(self, handler) -> dict:
            out = handler(self)
            have = self.model_fields_set | set(self.model_extra or ())
            order = [k for k in self._keys if k in out] + [k for k in out if k not in self._keys]
            return {k: out[k] for k in order if k in have}

        def dump(self) -> dict:
            return self.model_dump()

    class _Run(BaseModel):
        model_config = ConfigDict(validate_assignment=True)

    #: A typed dict that keeps the keys it does not declare.
    _keeps_extra = with_config(ConfigDict(extra="allow"))
else:
    Number = PositiveNumber = float
    Integer = FrameIndex = int
    Vec3 = Quaternion = list
    RelPath = str

    def _ordered(t: Any) -> Any:
        return t

    def _keeps_extra(cls: Any) -> Any:
        return cls

    class _Plain:
        """A record without pydantic: the declared fields (default where missing, nested records
        made from their dicts), the other keys of the object kept as attributes; nothing checked."""

        def __init__(self, **data: Any) -> None:
            self._keys = tuple(data)
            for name, hint in _hints(type(self)).items():
                if name in data:
                    setattr(self, name, _build(hint, data[name]))
                else:
                    setattr(self, name, copy.deepcopy(getattr(type(self), name)))
            for name in data.keys() - _hints(type(self)).keys():
                setattr(self, name, data[name])

        @classmethod
        def model_validate(cls, data: dict):
            return cls(**data)

    def _hints(cls) -> dict:
        return {k: v for k, v in typing.get_type_hints(cls).items() if not k.startswith("_")}

    def _build(hint: Any, v: Any) -> Any:
        """``v`` with the dicts that ``hint`` says are records made into them."""
        rec = next((t for t in _walk(hint) if isinstance(t, type) and issubclass(t, _Plain)), None)
        if rec is None:
            return v
        if isinstance(v, dict):
            return rec(**v)
        if isinstance(v, list):
            return [rec(**x) if isinstance(x, dict) else x for x in v]
        return v

    def _walk(hint: Any):
        yield hint
        for a in typing.get_args(hint):
            yield from _walk(a)

    _Record = _Run = _Plain


# ----------------------------------------------------------------------------- the records
class Domain(TypedDict):
    """The domain box [m]: its lower and upper corners."""

    lower: Vec3
    upper: Vec3


@_keeps_extra
class Extra(TypedDict, total=False):
    """``extra``: what a stage noted about the run. Its known keys are typed; the rest are free."""

    seed: Integer
    scene_dir: str
    kernel_support: Number


if typing.TYPE_CHECKING:  # to a type checker: the typed dicts; ``extra`` takes any key a stage notes
    DomainBox = Domain
    ExtraDict = dict[str, Any]
else:
    DomainBox = _ordered(Domain)
    ExtraDict = _ordered(Extra)


class Pose(_Record):
    """A moving body's pose at a frame: the rigid motion x_world = R(quaternion)·x_rest + position
    from its rest placement (position [m], unit quaternion w, x, y, z)."""

    position: Vec3
    quaternion: Quaternion


class Obstacle(_Record):
    """An obstacle as run.json lists it: its collision ``mesh`` and ``render_mesh`` (None: the
    collision mesh), rest placement x_rest = T(translate)·Rz·Ry·Rx·S(scale)·x_mesh (``rotate`` in
    degrees about x, then y, then z) and look (``material`` preset, ``color``: None, the preset's;
    ``texture``). An imported case's shapes have a ``name``, a ``role`` and their ``source``; a
    simulated run's obstacles keep the rest of the scene's ``[[obstacle]]`` (friction, motion...)."""

    mesh: str = ""
    render_mesh: str | None = None
    translate: Vec3 = [0.0, 0.0, 0.0]
    rotate: Vec3 = [0.0, 0.0, 0.0]
    scale: PositiveNumber = 1.0
    material: str = "stone"
    color: Vec3 | None = None
    texture: str | None = None
    name: str | None = None
    role: str | None = None

    @property
    def render_file(self) -> str:
        """The mesh the renderer draws: ``render_mesh``, else the collision ``mesh``."""
        return self.render_mesh or self.mesh


class Frame(_Record):
    """One frame of the run: its ``index``, simulated ``time`` [s] (None: index / frame rate, see
    ``RunInfo.time``), its ``files`` by kind (paths inside the run), ``made_from``: the identity of
    the simulation each file came from, the moving bodies' ``bodies`` poses (None: all at rest),
    and what the stages noted: the fluid's ``particles`` count, the ``mesh_settings`` and
    ``render_key`` that made its mesh and its picture."""

    index: FrameIndex
    time: Number | None = None
    files: dict[str, RelPath]
    made_from: dict[str, str] = {}
    bodies: list[Pose] | None = None
    particles: Integer | None = None
    mesh_settings: str | None = None
    render_key: str | None = None
    #: the entry's run.json text as RunInfo.dumps last wrote it (None: changed since, written anew)
    _text: str | None = None

    def __setattr__(self, name: str, value: Any) -> None:
        super().__setattr__(name, value)
        if not name.startswith("_"):
            self._text = None  # a field assigned: the text is rewritten on the next save

    def changed(self) -> None:
        """Say that ``files``, ``made_from`` or a pose was changed in place (an assignment says so itself)."""
        self._text = None


class RunRecord(_Run):
    """run.json: the run's constants, its domain, its frames and obstacles (see io/run.py)."""

    particle_radius: PositiveNumber
    rest_density: PositiveNumber
    particle_mass: PositiveNumber
    gravity: Vec3
    domain: DomainBox
    frame_rate: PositiveNumber
    frames: list[Frame] = []
    obstacles: list[Obstacle] = []
    extra: ExtraDict = {}
    format: str = FORMAT
    version: Integer = FORMAT_VERSION
    up: str = "z"
    simulation: str = ""  # identity of the simulation the fluid frames come from
