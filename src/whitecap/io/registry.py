"""Readers and writers registered per format, one module each (as meshio does).

A format module calls :func:`register` at import time. :func:`read` and
:func:`write` pick the format from the file extension or an explicit name.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..errors import InputError
from .frame import ParticleFrame

Reader = Callable[..., ParticleFrame]
Writer = Callable[..., None]


@dataclass(frozen=True)
class Format:
    name: str
    extensions: tuple[str, ...]
    reader: Reader | None
    writer: Writer | None


FORMATS: dict[str, Format] = {}


def register(name: str, extensions: tuple[str, ...], reader: Reader | None = None, writer: Writer | None = None) -> None:
    FORMATS[name] = Format(name, extensions, reader, writer)


def format_for(path: str | Path, fmt: str | None = None) -> Format:
    if fmt is not None:
        if fmt not in FORMATS:
            raise InputError(f"{path}: unknown format '{fmt}' (known: {', '.join(sorted(FORMATS))})")
        return FORMATS[fmt]
    name = str(path).lower()
    for f in FORMATS.values():
        if any(name.endswith(ext) for ext in f.extensions):
            return f
    raise InputError(f"{path}: no reader for this file type (known: {', '.join(sorted(FORMATS))})")


def read(path: str | Path, fmt: str | None = None, **options) -> ParticleFrame:
    """Read one particle frame. Options are format specific (``up='y'``...)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found")
    f = format_for(p, fmt)
    if f.reader is None:
        raise InputError(f"{p}: format '{f.name}' cannot be read")
    return f.reader(p, **options)


def write(path: str | Path, frame: ParticleFrame, fmt: str | None = None, **options) -> None:
    """Write one particle frame atomically (temporary file, then rename)."""
    f = format_for(path, fmt)
    if f.writer is None:
        raise InputError(f"{path}: format '{f.name}' cannot be written")
    f.writer(Path(path), frame, **options)
