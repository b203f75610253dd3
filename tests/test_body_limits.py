"""A dynamic body's density must be physical, and a body that leaves the domain stops the run with
one line (issue 30, item 11)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from whitecap.cli import main
from whitecap.config import scene_from_dict
from whitecap.errors import InputError, SimulationError
from whitecap.sim.driver import build_solver

from .test_bodies import slab_scene


@pytest.mark.parametrize("density", [1e-9, 0.5, 1e6])
def test_a_density_outside_the_physical_range_is_refused_naming_the_field(tmp_path, density):
    with pytest.raises(InputError, match=r"obstacle\[0\]\.density"):
        slab_scene(tmp_path, density, 0.18)


def test_a_mass_giving_an_unphysical_density_is_refused(tmp_path):
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=[0.1, 0.1, 0.1]).export(str(path))
    sc = scene_from_dict({
        "domain": {"upper": [0.5, 0.1, 0.35]}, "solver": {"particle_radius": 0.01},
        "fluid": [{"lower": [0, 0, 0], "upper": [0.5, 0.1, 0.1]}],
        "obstacle": [{"mesh": str(path), "translate": [0.25, 0.05, 0.2], "dynamic": True, "mass": 1e-9}],
        "foam": {"enabled": False},
    })
    with pytest.raises(InputError, match=r"obstacle\[0\] \(.*box.stl\): mass: .*outside 1\.\.25000"):
        build_solver(sc)


def test_a_body_thrown_out_of_the_domain_stops_with_one_line(tmp_path):
    sc = slab_scene(tmp_path, 500.0, 0.25)
    s = build_solver(sc)
    body = s.colliders[0].bodies[0]
    body.advance(1e-3)  # a normal step stays inside
    assert (body.c >= body.lo).all() and (body.c <= body.hi).all()
    body.V = np.array([0.0, 0.0, 1e5])  # kicked hard: the walls still hold it
    body.advance(1e-3)
    assert (body.c >= body.lo).all() and (body.c <= body.hi).all()
    body.collide_walls = lambda: None  # walls that failed to hold it: the run stops, naming the body
    body.V = np.array([0.0, 0.0, 100.0])
    with pytest.raises(SimulationError, match=r"obstacle\[0\] \(.*slab.stl\): left the domain"):
        body.advance(1e-2)


def test_a_coupling_that_blew_up_stops_with_one_line_and_no_numpy_warning(tmp_path):
    import warnings

    s = build_solver(slab_scene(tmp_path, 500.0, 0.25))
    body = s.colliders[0].bodies[0]
    body.F = np.array([np.inf, 0.0, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning from NumPy would be printed before the error line
        with pytest.raises(SimulationError,
                           match=r"obstacle\[0\] \(.*slab.stl\): the fluid's force on it is not finite"):
            body.advance(1e-3)


def test_the_cli_names_the_scene_file_and_the_field(tmp_path, capsys):
    sc = slab_scene(tmp_path, 500.0, 0.18)
    text = sc.to_toml().replace("density = 500.0", "density = 1e-9")
    (tmp_path / "s.toml").write_text(text)
    assert main(["simulate", str(tmp_path / "s.toml"), "-o", str(tmp_path / "R")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "s.toml: obstacle[0].density" in err, err
