"""Surface checks that catch realistic one-line bugs the other tests let through
(scripts/mutation_audit.py)."""

from __future__ import annotations

from whitecap.cli import main
from whitecap.io.run import RunInfo

from .test_surface import settled_tank_run, wall_gaps


def test_only_the_walls_the_run_names_close_the_surface(tmp_path):
    """A tank open at its +x end (a flume whose far end lets the water go): the surface is closed
    against the four solid walls it touches and left where splashsurf put it at the open end.
    (With every wall solid, swapping each wall's side for the opposite one gives the same six
    planes; here it would snap the open end and leave the floor.)"""
    run, lo, hi = settled_tank_run(tmp_path, {"solid_walls": ["x-", "y-", "y+", "z-"]})
    assert RunInfo.load(run).solid_walls() == ["x-", "y-", "y+", "z-"]
    assert main(["mesh", str(run), "--jobs", "1"]) == 0
    gaps = wall_gaps(run, lo, hi)
    assert max(gaps[w] for w in ("x-", "y-", "y+", "z-")) <= 0.25, gaps
    assert gaps["x+"] > 0.4, gaps  # the open end keeps splashsurf's gap (test_surface: > 0.4 r unsnapped)
