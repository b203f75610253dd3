"""Shared fixtures. Everything runs on the CPU (Taichi arch=cpu)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("WHITECAP_PROGRESS", "0")
ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parent / "data"


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
