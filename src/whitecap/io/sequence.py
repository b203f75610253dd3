"""Numbered particle sequences: ``dir/`` or ``dir/name_*.ply`` -> [(index, path)].

Folders and files that exist are taken literally (a folder named ``run[1]`` is not a
pattern); wildcards apply to what does not exist as a path.

A sequence is any set of files the io registry reads whose names end in a
frame number (``fluid_00012.ply``, ``PartFluid_0012.vtk``, ``frame12.npz``).
"""

from __future__ import annotations

import glob
import os
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


def particle_files(folder: Path) -> list[Path]:
    """The files of ``folder`` the io registry reads as particles, sorted (hidden ones left out)."""
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".") and _readable(p))


def glob_paths(spec: str | Path) -> list[Path]:
    """The files a glob pattern matches, sorted. Its leading folders that exist are taken
    literally, so a folder whose name holds ``[`` ``]`` (``run[1]/*.vtk``) is that folder,
    not a character class; the rest of the pattern keeps its wildcards."""
    parts = Path(spec).parts
    for k in range(len(parts) - 1, 0, -1):
        base = Path(*parts[:k])
        if base.is_dir():
            return [Path(p) for p in sorted(glob.glob(os.path.join(glob.escape(str(base)), *parts[k:])))]
    return [Path(p) for p in sorted(glob.glob(str(spec)))]


def find_sequence(spec: str | Path) -> list[tuple[int, Path]]:
    """Frames of a sequence, sorted by frame number.

    ``spec`` is a directory (every readable numbered file in it, which must
    share one extension), one file, or a glob pattern (:func:`glob_paths`). A path
    that exists is taken as it is, whatever characters its name holds. Raises
    InputError when nothing matches or two files claim the same frame number.
    """
    s = str(spec)
    if any(c in s for c in "*?[") and not Path(s).exists():
        paths = glob_paths(s)
        if not paths:
            raise InputError(f"{s}: no files match this pattern")
    else:
        d = Path(s)
        if not d.exists():
            raise InputError(f"{d}: no such file or directory")
        if d.is_file():
            paths = [d]
        else:
            paths = particle_files(d)
            exts = {p.suffix.lower() for p in paths}
            if len(exts) > 1:
                raise InputError(f"{d}: mixed file types {sorted(exts)}; pass a glob such as "
                                 f"'{d / ('*' + sorted(exts)[0])}'")
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
