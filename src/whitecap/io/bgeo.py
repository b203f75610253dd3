"""Houdini BGEO particle files (``.bgeo``): the partio format that SPlisHSPlasH's
partio exporter writes (``partio/ParticleData_Fluid_N.bgeo``, gzip-compressed
BGEO version 5, y up by default: read them with ``up='y'``).

Parsed by the BGEO V5 reader that ships with pysplashsurf (already a
dependency for meshing; partio's own Python bindings have no wheels). Point
attributes are matched by name as in the VTK readers: ``velocity``/``v``,
``density``, ``id``; the rest stay in ``arrays``. Its failures are turned
into one-line errors that name the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .axes import to_z_up
from .frame import ParticleFrame
from .registry import DENSITY_NAMES, ID_NAMES, VELOCITY_NAMES, find_array, register

GZIP_MAGIC = b"\x1f\x8b"


def read_bgeo(path: Path, up: str = "z", require_velocity: bool = True, by_id: bool = False) -> ParticleFrame:
    """One partio BGEO frame; ``by_id``: rows in increasing id order (the file must hold ids,
    see :meth:`ParticleFrame.sorted_by_id`)."""
    from pysplashsurf.bgeo import readbgeo_to_meshio

    with open(path, "rb") as f:
        head = f.read(2)
    if head != GZIP_MAGIC:
        # pysplashsurf reads the gzip-compressed files partio writes with compression on (SPlisHSPlasH does).
        raise InputError(f"{path}: not a gzip-compressed BGEO file (SPlisHSPlasH/partio write them compressed); "
                         f"compress it with gzip and keep the .bgeo name")
    try:
        m = readbgeo_to_meshio(str(path))
    except Exception as exc:  # EOFError, ValueError from a truncated body, its own format checks
        raise InputError(f"{path}: not a readable BGEO V5 particle file ({exc or type(exc).__name__})") from None
    arrays = {k: np.asarray(v) for k, v in m.point_data.items()}
    vk, rk, ik = find_array(arrays, VELOCITY_NAMES), find_array(arrays, DENSITY_NAMES), find_array(arrays, ID_NAMES)
    if vk is None and require_velocity:
        raise InputError(f"{path}: missing attribute 'velocity'; found {sorted(arrays) or 'no attributes'} "
                         "(SPlisHSPlasH: add velocity to particleAttributes)")
    if by_id and ik is None:
        raise InputError(f"{path}: missing attribute 'id' (persistent particle ids) to order the particles by; "
                         f"found {sorted(arrays) or 'no attributes'} (SPlisHSPlasH: add id to particleAttributes)")
    # The file is big-endian; ParticleFrame converts to native float32/uint32.
    vel = arrays[vk].reshape(-1, 3) if vk else None
    pos, vel = to_z_up(np.asarray(m.points).reshape(-1, 3), vel, up)
    frame = ParticleFrame(
        positions=pos,
        velocities=vel,
        ids=arrays[ik] if ik else None,
        density=arrays[rk] if rk else None,
        arrays={k: v for k, v in arrays.items() if k not in (vk, rk, ik) and v.ndim == 1},
        source=str(path),
    )
    return frame.sorted_by_id() if by_id else frame


register("bgeo", (".bgeo",), read_bgeo, None)
