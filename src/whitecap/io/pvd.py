"""ParaView collections: ``.pvd`` (XML files) and ``.series`` (any reader).

A ``.pvd`` lists one dataset per time step; ParaView plays it with the real
simulated times. ParaView's PVD reader only takes VTK XML files, so PLY
series get a ``.series`` JSON file instead, which ParaView's file-series
support reads for any format.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

from .atomic import write_text


def write_pvd(path: str | Path, entries: list[tuple[float, str]]) -> None:
    """``entries``: (time [s], file path relative to the .pvd)."""
    root = ET.Element("VTKFile", type="Collection", version="1.0", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for t, rel in entries:
        ET.SubElement(coll, "DataSet", timestep=repr(float(t)), group="", part="0", file=str(rel))
    ET.indent(root)
    write_text(path, '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n")


def write_series(path: str | Path, entries: list[tuple[float, str]]) -> None:
    """ParaView ``.series`` JSON: the same (time, file) list for non-XML files."""
    data = {"file-series-version": "1.0", "files": [{"name": str(rel), "time": float(t)} for t, rel in entries]}
    write_text(path, json.dumps(data, indent=1) + "\n")
