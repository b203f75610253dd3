"""The frame-hook contract of `simulate` (whitecap.sim.driver.FrameHook): what a hook must define,
the order the loop calls it in, and the foam hook working on the solver's own obstacles."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from whitecap.config import scene_from_dict
from whitecap.sim.driver import FrameHook, run_simulation


def tiny_scene(tmp_path, frames=3, **more):
    return scene_from_dict({
        "domain": {"upper": [0.3, 0.1, 0.2]},
        "solver": {"particle_radius": 0.01},
        "fluid": [{"lower": [0, 0, 0], "upper": [0.1, 0.1, 0.1]}],
        "foam": {"enabled": False},
        "output": {"frames": frames, "checkpoint_interval": 1},
        **more,
    })


class Recorder(FrameHook):
    """Writes nothing; records each call and keeps a count of frames as its checkpointed state."""

    name = "recorder"

    def __init__(self):
        self.calls: list = []
        self.seen = 0

    def on_start(self, solver, out, info, last_frame):
        self.calls.append(("on_start", last_frame))

    def on_frame(self, frame, index, dt, out, info):
        self.seen += 1
        self.calls.append(("on_frame", index))
        return None

    def write(self, writer=None):
        self.calls.append(("write",))

    def checkpoint(self):
        self.calls.append(("checkpoint",))
        return {"seen": np.int64(self.seen)}

    def restore(self, data):
        self.seen = int(data["seen"])
        self.calls.append(("restore", self.seen))

    def finish(self):
        self.calls.append(("finish",))


def test_a_hook_missing_a_method_cannot_be_made():
    class NoCheckpoint(FrameHook):
        name = "half"

        def on_start(self, solver, out, info, last_frame):
            pass

        def on_frame(self, frame, index, dt, out, info):
            return None

        def restore(self, data):
            pass

    with pytest.raises(TypeError, match="checkpoint"):  # at construction, not at the first checkpoint
        NoCheckpoint()
    with pytest.raises(TypeError, match="'name'"):  # a hook without a name cannot even be defined

        class Nameless(Recorder):
            name = None


def test_simulate_refuses_an_object_that_is_not_a_frame_hook(tmp_path):
    class Duck:  # the methods, but not the contract
        name = "duck"

    with pytest.raises(TypeError, match="Duck"):
        run_simulation(tiny_scene(tmp_path), tmp_path / "run", hooks=[Duck()], show_progress=False)
    assert not (tmp_path / "run").exists()  # refused before anything was made


def test_the_loop_calls_a_hook_in_its_documented_order(tmp_path):
    sc, out = tiny_scene(tmp_path, frames=4), tmp_path / "run"
    first = Recorder()
    run_simulation(sc, out, frames=2, hooks=[first], show_progress=False)
    per_frame = lambda i: [("on_frame", i), ("write",), ("checkpoint",)]  # noqa: E731 (checkpoint_interval 1)
    assert first.calls == [("on_start", 2), *per_frame(0), *per_frame(1), *per_frame(2), ("finish",)]
    resumed = Recorder()
    run_simulation(sc, out, resume=True, hooks=[resumed], show_progress=False)
    assert resumed.calls == [("restore", 3), ("on_start", 4), *per_frame(3), *per_frame(4), ("finish",)]
    assert resumed.seen == 5  # its state went on from the checkpoint


def test_the_foam_hook_takes_the_solvers_obstacles(tmp_path, monkeypatch):
    """Inside `simulate` the obstacles are loaded once, by the solver, and the diffuse particles
    collide with those very SDFs and motion laws (the post-processing path loads its own)."""
    from whitecap.diffuse import simulation_hook
    from whitecap.sim import obstacles as obs

    path = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=2, radius=0.03).export(str(path))
    sc = tiny_scene(tmp_path, frames=2, obstacle=[{"mesh": str(path), "translate": [0.2, 0.05, 0.04]}],
                    foam={"enabled": True})
    loads, built = [], []
    real_load, real_init = obs.load_obstacles, obs.ObstacleCollider.__init__

    def counting_load(scene):
        loads.append(scene)
        return real_load(scene)

    def keep_collider(self, obst, solver):
        built.append(obst)
        real_init(self, obst, solver)

    monkeypatch.setattr(obs, "load_obstacles", counting_load)
    monkeypatch.setattr(obs.ObstacleCollider, "__init__", keep_collider)
    hook = simulation_hook(sc)
    assert hook.obstacles is None  # nothing loaded before the solver exists
    run_simulation(sc, tmp_path / "run", hooks=[hook], show_progress=False)
    assert len(loads) == 1 and len(built) == 1
    (g,) = hook.obstacles
    assert g.grid is built[0].grids[0] and g.law is built[0].laws[0]
    assert (tmp_path / "run/diffuse/diffuse_00002.ply").is_file()


def test_the_live_views_foam_takes_the_solvers_obstacles(tmp_path):
    from whitecap.view.sources import LiveSource

    path = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=2, radius=0.03).export(str(path))
    sc = tiny_scene(tmp_path, obstacle=[{"mesh": str(path), "translate": [0.2, 0.05, 0.04]}], foam={"enabled": True})
    src = LiveSource(sc)
    (g,) = src.hook.obstacles
    assert g.grid is src.solver.obstacles.grids[0]
    src.advance()
    src.current()
    assert src.hook is not None and src.hook.gen.state.counts  # the generator ran with them (it drops out on errors)
