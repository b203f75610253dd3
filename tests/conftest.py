"""Shared fixtures. Everything runs on the CPU (Taichi arch=cpu)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("WHITECAP_PROGRESS", "0")
ROOT = Path(__file__).resolve().parents[1]
#: Appended to a bpy script run with ``python -c`` (whitecap on its path): it ends as whitecap's own Blender
#: workers do (whitecap.workers.end_process), past bpy's teardown, which now and then crashed after the script
#: had printed its results. A script that raises still ends with its traceback and status 1.
BPY_END = "\nfrom whitecap.workers import end_process as _end\n_end(0)\n"
DATA = Path(__file__).resolve().parent / "data"


def kill_when(child, signal_file: Path, what: str) -> None:
    """SIGKILL the subprocess ``child`` once it has made ``signal_file`` (it waits there, mid-write: ``what``);
    its output is the error where it ends first. Returns once it is dead, killed by that signal."""
    import signal
    import time

    try:
        deadline = time.monotonic() + 300
        while not signal_file.exists():
            assert child.poll() is None, child.stdout.read().decode()
            assert time.monotonic() < deadline, f"the child never reached {what}"
            time.sleep(0.05)
        child.send_signal(signal.SIGKILL)
        child.wait(60)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == -signal.SIGKILL


def tiny_scene_dict(**over) -> dict:
    """A small dam break: about 2.3k particles, r = 1 cm, 3 frames at 30 fps."""
    d = {
        "name": "tiny",
        "seed": 3,
        "domain": {"lower": [0.0, 0.0, 0.0], "upper": [0.6, 0.2, 0.4]},
        "solver": {"particle_radius": 0.01, "iterations": 4},
        "fluid": [{"lower": [0.0, 0.0, 0.0], "upper": [0.2, 0.2, 0.3]}],
        "output": {"frames": 3},
    }
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(d.get(k), dict):
            d[k] = {**d[k], **v}
        else:
            d[k] = v
    return d


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> Path:
    """A run directory produced by `simulate` on the tiny dam break (fluid frames 0..3).

    Read-only for tests: copy it before writing into it."""
    from whitecap.config import scene_from_dict
    from whitecap.pipeline import simulate

    out = tmp_path_factory.mktemp("tiny_run")
    simulate(scene_from_dict(tiny_scene_dict()), out=out, show_progress=False)
    return out


def write_partio_bgeo(path, positions, attributes: dict, compress: bool = True) -> None:
    """A BGEO version 5 file laid out as partio writes it (SPlisHSPlasH's partio exporter):
    big-endian header, one descriptor per point attribute, then per point x y z w and
    the attribute values, then the two end bytes. ``attributes`` maps a name to an
    (N,) int32 array (partio INT), an (N,) float array (FLOAT) or an (N, 3) float array
    (VECTOR). Test data only: whitecap itself never writes BGEO."""
    import gzip
    import struct

    import numpy as np

    pos = np.asarray(positions, ">f4").reshape(-1, 3)
    n = len(pos)
    head = b"BgeoV" + struct.pack(">9i", 5, n, 0, 0, 0, len(attributes), 0, 0, 0)
    cols = [pos, np.ones((n, 1), ">f4")]
    for name, a in attributes.items():
        a = np.asarray(a)
        if a.dtype.kind in "iu":
            size, kind, col = 1, 1, a.astype(">i4").reshape(n, 1).view(">f4")
        else:
            col = a.astype(">f4").reshape(n, -1)
            size, kind = col.shape[1], (5 if col.shape[1] == 3 else 0)
        head += struct.pack(">h", len(name)) + name.encode() + struct.pack(">hi", size, kind) + b"\0" * (4 * size)
        cols.append(col)
    body = head + np.hstack(cols).astype(">f4").tobytes() + b"\x00\xff"
    Path(path).write_bytes(gzip.compress(body) if compress else body)


# The head of a Blender script (run with `python -c`) that loads the add-on from argv[1] (its
# __init__.py), registers it and loads the run or sequence argv[2]; `addon` and `sc` are then set.
ADDON_LOAD_SCRIPT = r"""
import sys, json, importlib.util, bpy
spec = importlib.util.spec_from_file_location("whitecap_sequences", sys.argv[1])
addon = importlib.util.module_from_spec(spec); sys.modules["whitecap_sequences"] = addon; spec.loader.exec_module(addon)
bpy.ops.wm.read_factory_settings(use_empty=True)
addon.register()
bpy.ops.whitecap.load(filepath=sys.argv[2])
sc = bpy.context.scene
"""
