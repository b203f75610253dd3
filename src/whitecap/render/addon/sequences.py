"""Numbered file sequences: ``PartFluid_0012.vtk`` -> prefix ``PartFluid_``, frame 12, suffix ``.vtk``."""

import os
import re

from .formats import EXTENSIONS

NUMBERED = re.compile(r"^(.*?)(\d+)(" + "|".join(re.escape(e) for e in EXTENSIONS) + r")$", re.IGNORECASE)
KNOWN = ", ".join(EXTENSIONS)


def frames_of(directory, prefix, suffix):
    """{frame number: file name} of one sequence in a folder."""
    out = {}
    for f in os.listdir(directory):
        m = NUMBERED.match(f)
        if m and m.group(1) == prefix and m.group(3).lower() == suffix.lower():
            out[int(m.group(2))] = f
    return out


def sequence_of(path):
    """(directory, prefix, suffix) of the numbered sequence a file belongs to."""
    d, name = os.path.split(os.path.abspath(path))
    if not os.path.exists(path):
        raise ValueError(f"{path}: no such file or folder")
    m = NUMBERED.match(name)
    if not m:
        raise ValueError(f"{path}: the name has no frame number before its extension (as in PartFluid_0001.vtk; "
                         f"readable: {KNOWN})")
    return d, m.group(1), m.group(3)


def sequences_in(directory):
    """[(prefix, suffix)] of every numbered sequence in a folder, sorted by name."""
    if not os.path.isdir(directory):
        raise ValueError(f"{directory}: no such folder")
    found = set()
    for f in os.listdir(directory):
        m = NUMBERED.match(f)
        if m and os.path.isfile(os.path.join(directory, f)):
            found.add((m.group(1), m.group(3).lower()))
    if not found:
        raise ValueError(f"{directory}: no numbered files in this folder (readable: {KNOWN})")
    return sorted(found)
