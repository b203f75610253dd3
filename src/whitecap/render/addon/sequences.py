"""Numbered file sequences: ``PartFluid_0012.vtk`` -> prefix ``PartFluid_``, frame 12, suffix ``.vtk``.

A pattern names a sequence with ``@`` where the frame number stands (``PartFluid_@.vtk``);
a filter keeps the files whose name holds it (or matches it, with ``*`` or ``?``); a folder is
searched alone or with its subfolders.
"""

import fnmatch
import os
import re

from . import readers


def extensions():
    """Every extension the add-on reads: its own readers', then meshio's."""
    return tuple(readers.READERS) + readers.meshio_extensions()


def _numbered():
    exts = sorted(extensions(), key=len, reverse=True)
    return re.compile(r"^(.*?)(\d+)(" + "|".join(re.escape(e) for e in exts) + r")$", re.IGNORECASE)


def known():
    return ", ".join(readers.READERS) + " and meshio's formats"


def frames_of(directory, prefix, suffix):
    """{frame number: file name} of one sequence in a folder."""
    out, numbered = {}, _numbered()
    for f in os.listdir(directory):
        m = numbered.match(f)
        if m and m.group(1) == prefix and m.group(3).lower() == suffix.lower():
            out[int(m.group(2))] = f
    return out


def from_pattern(pattern):
    """(directory, prefix, suffix) of a pattern with ``@`` for the frame number (``data/PartFluid_@.vtk``)."""
    d, name = os.path.split(os.path.abspath(pattern))
    if name.count("@") != 1:
        raise ValueError(f"{pattern}: a pattern holds one '@' where the frame number stands (as in PartFluid_@.vtk)")
    prefix, suffix = name.split("@")
    if not os.path.isdir(d):
        raise ValueError(f"{d}: no such folder")
    if not frames_of(d, prefix, suffix):
        raise ValueError(f"{pattern}: no files match the pattern in {d}")
    return d, prefix, suffix


def sequence_of(path):
    """(directory, prefix, suffix) of the numbered sequence a file (or an ``@`` pattern) belongs to."""
    if "@" in os.path.basename(path):
        return from_pattern(path)
    d, name = os.path.split(os.path.abspath(path))
    if not os.path.exists(path):
        raise ValueError(f"{path}: no such file or folder")
    m = _numbered().match(name)
    if not m:
        raise ValueError(f"{path}: the name has no frame number before its extension (as in PartFluid_0001.vtk; "
                         f"readable: {known()})")
    return d, m.group(1), m.group(3)


def passes(name, text):
    """A file name passes a filter: empty passes all; ``*``/``?`` match as in a shell; else a part of the name."""
    if not text:
        return True
    return fnmatch.fnmatch(name, text) if any(c in text for c in "*?[") else text in name


def sequences_in(directory, filter_text="", recursive=False):
    """[(folder, prefix, suffix)] of every numbered sequence in a folder (and its subfolders with
    ``recursive``) whose files pass the filter, sorted."""
    if not os.path.isdir(directory):
        raise ValueError(f"{directory}: no such folder")
    found, numbered = set(), _numbered()
    walk = os.walk(directory) if recursive else [(directory, [], os.listdir(directory))]
    for d, dirs, files in walk:
        dirs.sort()
        for f in files:
            m = numbered.match(f)
            if m and passes(f, filter_text) and os.path.isfile(os.path.join(d, f)):
                found.add((d, m.group(1), m.group(3).lower()))
    if not found:
        what = f" passing the filter '{filter_text}'" if filter_text else ""
        raise ValueError(f"{directory}: no numbered files{what} in this folder (readable: {known()})")
    return sorted(found)
