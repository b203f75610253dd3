"""The solver step as Taichi compute graphs (sim/launch.py): the same launches as kernel by kernel,
bit for bit, with obstacles, a dynamic body, an odd iteration count and a live change of it."""

from __future__ import annotations

import numpy as np
import pytest
import taichi as ti
import trimesh

from whitecap.config import scene_from_dict
from whitecap.sim import launch
from whitecap.sim.driver import build_solver


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("WHITECAP_CACHE", str(tmp_path / "cache"))


def scene(tmp_path, **solver):
    """A small tank with a floating slab (two-way coupled) and a static block: every collider hook."""
    slab, block = tmp_path / "slab.stl", tmp_path / "block.stl"
    trimesh.creation.box(extents=[0.2, 0.1, 0.06]).export(str(slab))
    trimesh.creation.box(extents=[0.06, 0.1, 0.1]).export(str(block))
    return scene_from_dict({
        "domain": {"upper": [0.5, 0.1, 0.3]},
        "solver": {"particle_radius": 0.01, "substeps": 4, **solver},
        "fluid": [{"lower": [0, 0, 0], "upper": [0.3, 0.1, 0.15]}],
        "obstacle": [
            {"mesh": str(slab), "translate": [0.2, 0.05, 0.2], "dynamic": True, "density": 600.0},
            {"mesh": str(block), "translate": [0.44, 0.05, 0.05]},
        ],
        "foam": {"enabled": False},
    })


def run(sc, use_graph: bool, frames: int = 3, then_iterations: int | None = None):
    s = build_solver(sc.model_copy(deep=True))  # the live change below must not reach the next run
    s.use_graph = use_graph
    for f in range(1, frames + 1):
        if then_iterations is not None and f == frames:
            s.params.iterations = then_iterations  # as the live viewer's slider does
        s.advance_frame(f)
    body = s.colliders[0].bodies[0]
    return s, s.state.x.to_numpy(), s.state.v.to_numpy(), body.state()


def test_graph_step_gives_the_bytes_of_kernel_by_kernel_launches(tmp_path):
    sc = scene(tmp_path, iterations=3)  # odd: the corrected x* ends in the scratch array
    s, x, v, body = run(sc, True, then_iterations=2)
    _, x0, v0, body0 = run(sc, False, then_iterations=2)
    assert np.array_equal(x, x0) and np.array_equal(v, v0)
    assert np.array_equal(body, body0)
    assert body[2] != pytest.approx(0.2, abs=1e-3)  # the body moved: the coupling ran
    assert {k for k in s._graphs if k[0] == "pbf.constraints"} == {("pbf.constraints", (3,)), ("pbf.constraints", (2,))}


def test_a_graph_step_launches_no_kernel_from_python(tmp_path, monkeypatch):
    """Between reorders, a step's kernels run from the compiled graphs only (the body's pose upload
    and momentum sums cleared are Taichi's own ndarray helpers, on the host's side of the step)."""
    sc = scene(tmp_path)
    sc.solver.reorder_interval = 0
    s = build_solver(sc)
    s.step(1e-3)  # compiles the graphs
    calls = []
    real = ti.lang.kernel_impl.Kernel.__call__

    def counting(self, *args, **kwargs):
        if self.func.__module__.startswith("whitecap"):  # not Taichi's own from_numpy/fill helpers
            calls.append(self.func.__name__)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(ti.lang.kernel_impl.Kernel, "__call__", counting)
    s.step(1e-3)
    assert calls == [], calls
    s.use_graph = False
    s.step(1e-3)
    assert "correct_positions" in calls  # and the counter does see launches


def test_overflow_is_counted_through_the_graph(tmp_path):
    sc = scene(tmp_path, max_neighbors=16)
    counts = []
    for use_graph in (True, False):
        s = build_solver(sc)
        s.use_graph = use_graph
        s.advance_frame(1)
        counts.append(s.stats.neighbor_overflow)
    assert counts[0] > 0 and counts[0] == counts[1]


def test_recorder_roles_follow_the_ping_pong():
    rec = launch.Recorder()
    rec.swap("p", "t")
    assert rec["p"].name == "t" and rec["t"].name == "p"
    rec.swap("p", "t")
    rec.swap("v", "t")
    assert launch.permuted({"p": 1, "t": 2, "v": 3}, rec.roles) == {"p": 1, "t": 3, "v": 2}


def test_without_compute_graphs_the_step_launches_kernel_by_kernel(tmp_path, monkeypatch, capfd):
    """A backend that cannot build a graph: one warning, then the same launches one by one."""
    from whitecap.sim import pbf

    sc = scene(tmp_path)
    _, x0, _, _ = run(sc, False, frames=1)

    def refuse(record):
        raise RuntimeError("graphs are not supported here")

    monkeypatch.setattr(pbf, "KernelGraph", refuse)
    s, x, _, _ = run(sc, True, frames=1)
    assert s.use_graph is False and np.array_equal(x, x0)
    out = "".join(capfd.readouterr())
    assert out.count("no Taichi compute graph") == 1 and "graphs are not supported here" in out
