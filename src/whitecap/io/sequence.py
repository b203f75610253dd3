"""Numbered particle sequences: ``dir/`` or ``dir/name_*.ply`` -> [(index, path)].

A sequence is any set of files the io registry reads whose names end in a
frame number (``fluid_00012.ply``, ``PartFluid_0012.vtk``, ``frame12.npz``).
"""

from __future__ import annotations

import glob
import re
from pathlib import Path

from ..errors import InputError
from .registry import PARTICLES, formats

_NUMBER = re.compile(r"(\d+)(?=\.[^.]+$|\.[^.]+\.[^.]+$)")


def frame_number(path: str | Path) -> int | None:
    """The frame number at the end of a file's stem, or None."""
    m = _NUMBER.search(Path(path).name)
    return int(m.group(1)) if m else None


def _readable(p: Path) -> bool:
    name = p.name.lower()
    return any(name.endswith(ext) for f in formats(PARTICLES).values() if f.reader for ext in f.extensions)


def find_sequence(spec: str | Path) -> list[tuple[int, Path]]:
    """Frames of a sequence, sorted by frame number.

    ``spec`` is a directory (every readable numbered file in it, which must
    share one extension) or a glob pattern. Raises InputError when nothing
    matches or two files claim the same frame number.
    """
    s = str(spec)
    if any(c in s for c in "*?["):
        paths = [Path(p) for p in sorted(glob.glob(s))]
        if not paths:
            raise InputError(f"{s}: no files match this pattern")
    else:
        d = Path(s)
        if not d.exists():
            raise InputError(f"{d}: no such file or directory")
        if d.is_file():
            paths = [d]
        else:
            paths = sorted(p for p in d.iterdir() if p.is_file() and not p.name.startswith(".") and _readable(p))
            exts = {p.suffix.lower() for p in paths}
            if len(exts) > 1:
                raise InputError(f"{d}: mixed file types {sorted(exts)}; pass a glob such as '{d}/*.ply'")
    frames: dict[int, Path] = {}
    for k, p in enumerate(paths):
        n = frame_number(p)
        n = k if n is None and len(paths) == 1 else n
        if n is None:
            raise InputError(f"{p}: no frame number in the file name")
        if n in frames:
            stem = _NUMBER.sub("*", p.name, count=1)
            raise InputError(f"{p}: frame {n} also given by {frames[n].name}; pass a glob such as '{p.parent / stem}'")
        frames[n] = p
    if not frames:
        raise InputError(f"{s}: no particle files found")
    return sorted(frames.items())
