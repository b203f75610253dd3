"""The one format registry: readers and writers per format, one module each (as meshio does).

A format module calls :func:`register` at import time with the kind of data it
holds: ``particles`` (a :class:`~whitecap.io.frame.ParticleFrame`), ``mesh``
(a :class:`~whitecap.io.mesh.SurfaceMesh`) or ``scene`` (a whole run as one
animated scene, :class:`~whitecap.io.cache.SceneCache`: USD, Alembic). One extension may serve both kinds
(``.ply``); the caller says which it wants. :func:`read` / :func:`write` move
particle frames, :func:`read_mesh` / :func:`write_mesh` surface meshes; each
picks the format from the file extension or an explicit name; :func:`write_scene`
writes a whole run.

Every reader refuses a file that was cut short (an array shorter than its header
declares) with one line naming the file and saying ``truncated``; :func:`check`
makes that test from headers and sizes alone, to check a whole sequence before
anything is written.

Solvers name the same array differently (``Vel``, ``velocity``, ``v``); every
reader finds the standard arrays with :func:`find_array` and the alias tables
below, so a new alias is added once for every format.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from ..errors import InputError
from .atomic import atomic_path
from .frame import ParticleFrame

if TYPE_CHECKING:
    from .cache import SceneCache
    from .mesh import SurfaceMesh

PARTICLES = "particles"
MESH = "mesh"
SCENE = "scene"
KINDS = (PARTICLES, MESH, SCENE)

# Point-array names per quantity, lower case, in order of preference:
# DualSPHysics (Vel, Rhop/Rho, Idp), SPlisHSPlasH (velocity, density, id), short forms.
VELOCITY_NAMES = ("vel", "velocity", "v")
DENSITY_NAMES = ("rhop", "rho", "density")
ID_NAMES = ("idp", "id")


def find_array(arrays: dict, names: tuple[str, ...]) -> str | None:
    """The key of ``arrays`` that matches one of ``names`` case-insensitively (the first
    name that matches wins), or None."""
    low = {k.lower(): k for k in arrays}
    return next((low[n] for n in names if n in low), None)


Reader = Callable[..., "ParticleFrame | SurfaceMesh"]
Writer = Callable[..., None]
Check = Callable[[Path], None]
AsRead = Callable[..., bool]


@dataclass(frozen=True)
class Format:
    name: str
    extensions: tuple[str, ...]
    reader: Reader | None
    writer: Writer | None
    kind: str = PARTICLES
    #: a cheap completeness check (headers and sizes, no parse of the data) that raises InputError
    #: naming the file when it was cut short; the reader makes the same check and more
    check: Check | None = None
    #: whether the writer would write a frame read from a file of this format (with these reader options) as that
    #: file's very bytes (:func:`write_copy` then copies the file)
    as_read: AsRead | None = None


# Keyed by (kind, name): "ply" is both a particle and a mesh format.
FORMATS: dict[tuple[str, str], Format] = {}


def register(
    name: str, extensions: tuple[str, ...], reader: Reader | None = None, writer: Writer | None = None,
    kind: str = PARTICLES, check: Check | None = None, as_read: AsRead | None = None,
) -> None:
    if kind not in KINDS:
        raise ValueError(f"format {name}: kind must be one of {KINDS}, not {kind!r}")
    FORMATS[(kind, name)] = Format(name, extensions, reader, writer, kind, check, as_read)


def formats(kind: str = PARTICLES) -> dict[str, Format]:
    """The registered formats of one kind, by name."""
    return {name: f for (k, name), f in FORMATS.items() if k == kind}


def format_for(path: str | Path, fmt: str | None = None, kind: str = PARTICLES) -> Format:
    known = formats(kind)
    if fmt is not None:
        if fmt not in known:
            raise InputError(f"{path}: unknown format '{fmt}' ({kind} formats known: {', '.join(sorted(known))})")
        return known[fmt]
    name = Path(path).name.lower()
    for f in known.values():
        if any(name.endswith(ext) for ext in f.extensions):
            return f
    raise InputError(f"{path}: no reader for this file type ({kind} formats known: {', '.join(sorted(known))})")


def _read(path: str | Path, fmt: str | None, kind: str, **options):
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found")
    f = format_for(p, fmt, kind)
    if f.reader is None:
        raise InputError(f"{p}: {kind} format '{f.name}' cannot be read")
    return f.reader(p, **options)


def _write(path: str | Path, data, fmt: str | None, kind: str, **options) -> None:
    f = format_for(path, fmt, kind)
    if f.writer is None:
        raise InputError(f"{path}: {kind} format '{f.name}' cannot be written")
    f.writer(Path(path), data, **options)


def check(path: str | Path, fmt: str | None = None, kind: str = PARTICLES) -> None:
    """Raise InputError (one line naming the file and saying ``truncated``) when a file was cut
    short, from its headers and size alone: cheap enough to run over every frame of a sequence
    before anything is written. Formats without such a check pass; their reader still checks."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found")
    f = format_for(p, fmt, kind)
    if f.check is not None:
        f.check(p)


def read(path: str | Path, fmt: str | None = None, **options) -> ParticleFrame:
    """Read one particle frame. Options are format specific (``up='y'``...)."""
    return _read(path, fmt, PARTICLES, **options)


def write(path: str | Path, frame: ParticleFrame, fmt: str | None = None, **options) -> None:
    """Write one particle frame atomically (temporary file, then rename)."""
    _write(path, frame, fmt, PARTICLES, **options)


def write_copy(path: str | Path, frame: ParticleFrame, source: str | Path, **read_options) -> None:
    """``frame``, read from the file ``source`` with ``read_options`` and not changed since, written to ``path``
    atomically: as a copy of ``source`` (the kernel's copy: nothing packed, no bytes through Python) where
    ``path``'s format is ``source``'s and would write the frame as those very bytes (its ``as_read`` test), else
    by :func:`write`. A run's fluid frames copied along into another folder (``whitecap foam --out``) are the
    same files either way."""
    f = format_for(path, None, PARTICLES)
    try:
        same = format_for(source, None, PARTICLES) is f
    except InputError:
        same = False
    if same and f.as_read is not None and f.as_read(Path(source), frame, **read_options):
        with atomic_path(path) as tmp:
            shutil.copyfile(source, tmp)
    else:
        write(path, frame)


def read_mesh(path: str | Path, fmt: str | None = None) -> "SurfaceMesh":
    """Read one surface mesh; the format comes from the extension unless named."""
    return _read(path, fmt, MESH)


def write_mesh(path: str | Path, mesh: "SurfaceMesh", fmt: str | None = None) -> None:
    """Write a surface mesh atomically; the format comes from the extension unless named."""
    _write(path, mesh, fmt, MESH)


def write_scene(path: str | Path, cache: "SceneCache", fmt: str | None = None, **options) -> None:
    """Write a whole run as one animated scene (USD, Alembic); the format comes from the
    extension unless named. The file at ``path`` appears complete or not at all."""
    _write(path, cache, fmt, SCENE, **options)
