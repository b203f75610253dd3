"""Compaction of the diffuse particles on the device (issue 31, goal 1): the exclusive prefix sum
(kernels.scan_sums / scan_offsets) and FoamGenerator._compact keep every live particle exactly once,
with its id, survivors first in their order, then the new ones in candidate order, as a NumPy
reference does with the same random keep flags."""

from __future__ import annotations

import numpy as np
import pytest
import taichi as ti

from whitecap.diffuse.params import resolve

R = 0.01


def _generator(capacity: int):
    from dataclasses import replace

    from whitecap.diffuse.generator import FoamGenerator

    p = replace(resolve(preset="ihmsen2012"), max_particles=capacity)
    gen = FoamGenerator(p, R, ([0, 0, 0], [1, 1, 1]), (0, 0, -9.81), seed=3)
    gen._size(1000)
    return gen


@pytest.mark.parametrize("n", [0, 1, 255, 256, 257, 5000, 1_300_000])
def test_the_prefix_sum_is_numpys_exclusive_cumsum(n):
    gen = _generator(10)
    a = np.random.default_rng(n).integers(0, 5, max(n, 1)).astype(np.int32)
    src, out = ti.ndarray(ti.i32, max(n, 1)), ti.ndarray(ti.i32, max(n, 1))
    src.from_numpy(a)
    total = gen._scan(n, src, out)
    assert total == int(a[:n].sum())
    np.testing.assert_array_equal(out.to_numpy()[:n], np.concatenate([[0], np.cumsum(a[:n])[:-1]])[:n])


def _data(nd: int, total: int) -> dict:
    rng = np.random.default_rng(7)
    return {
        "x": rng.uniform(0.1, 0.9, (nd, 3)).astype(np.float32), "v": rng.normal(0, 1, (nd, 3)).astype(np.float32),
        "life": rng.uniform(0, 5, nd).astype(np.float32), "ids": rng.permutation(10 * nd)[:nd].astype(np.uint32),
        "keep": (rng.random(nd) < 0.6).astype(np.int32), "kind": rng.integers(0, 3, nd).astype(np.int32),
        "cx": rng.uniform(-0.1, 1.1, (total, 3)).astype(np.float32),  # some outside the domain [0, 1]³
        "cv": rng.normal(0, 1, (total, 3)).astype(np.float32), "cl": rng.uniform(0, 5, total).astype(np.float32),
        "ck": np.where(rng.random(total) < 0.5, rng.integers(0, 3, total), -1).astype(np.int8),
    }


def _compact(d: dict, room: int | None):
    """The generator's live arrays set to ``d`` (survivors flagged by keep, kept candidates by ck ≥ 0),
    then one compaction; returns (the frame, the counts by type, the generator)."""
    gen = _generator(100_000)
    nd, total = len(d["x"]), len(d["cx"])
    st = gen.state
    st.positions, st.velocities, st.lifetime, st.ids = d["x"], d["v"], d["life"], d["ids"]
    st.next_id = 10 * nd
    gen._sync_in()
    rows = gen._bufs["live_keep"].shape[0]
    gen._bufs["live_keep"].from_numpy(np.pad(d["keep"], (0, rows - nd)))
    gen._live[gen._cur]["kind"].from_numpy(np.pad(d["kind"], (0, rows - nd)))
    gen._candidates = {"total": total, "n": 1}
    for name, a, kw in (("cand_x", d["cx"], {"vec": True}), ("cand_v", d["cv"], {"vec": True}), ("cand_life", d["cl"], {}),
                        ("cand_kind", d["ck"], {"dtype": ti.i8}), ("cand_owner", np.zeros(total, np.int32), {"dtype": ti.i32}),
                        ("offset", np.zeros(1, np.int32), {"dtype": ti.i32}),
                        ("fluid_id", np.zeros(1, np.uint32), {"dtype": ti.u32}), ("e_k", np.zeros(1, np.float32), {}),
                        ("tau", np.ones(8, np.float32), {})):
        gen._upload(name, a, **({"dtype": ti.f32} | kw))
    if room is not None:
        gen.capacity = int(d["keep"].sum()) + room
    counts = gen._compact(int((d["ck"] >= 0).sum()), 0, 0)
    return gen._download(), counts, gen


@pytest.mark.parametrize("room", [None, 37])
def test_compaction_keeps_every_live_particle_once_with_its_id_in_a_fixed_order(room):
    """Random survivors of 3000 live particles and random kept candidates of 2000 (some born outside
    the domain): the live arrays afterwards hold the survivors in their order, then the kept candidates
    that fit the capacity (``room`` beyond the survivors) and lie in the domain, in candidate order, with
    ids next_id + their rank among the kept. A second run gives the same bytes."""
    d = _data(3000, 2000)
    out, counts, gen = _compact(d, room)
    sel = d["keep"].astype(bool)
    kept = np.flatnonzero(d["ck"] >= 0)
    fit = kept[: (len(kept) if room is None else room)]
    ids_new = (10 * 3000 + np.arange(len(fit))).astype(np.uint32)
    inside = ((d["cx"][fit] >= 0) & (d["cx"][fit] <= 1)).all(1)
    assert sel.sum() > 1000 and len(fit) > 30 and not inside.all()
    np.testing.assert_array_equal(out.positions, np.concatenate([d["x"][sel], d["cx"][fit][inside]]))
    np.testing.assert_array_equal(out.velocities, np.concatenate([d["v"][sel], d["cv"][fit][inside]]))
    np.testing.assert_array_equal(out.arrays["lifetime"], np.concatenate([d["life"][sel], d["cl"][fit][inside]]))
    np.testing.assert_array_equal(out.ids, np.concatenate([d["ids"][sel], ids_new[inside]]))
    types = np.concatenate([d["kind"][sel], d["ck"][fit][inside]]).astype(np.uint8)
    np.testing.assert_array_equal(out.arrays["type"], types)
    assert counts == np.bincount(types, minlength=3).tolist()
    assert len(np.unique(out.ids)) == len(out.ids)  # each particle once
    assert gen.state.next_id == 10 * 3000 + len(fit)  # ids of those born outside are used up, as before
    assert room is None or len(fit) == room < len(kept)
    again, _, _ = _compact(d, room)
    for a, b in ((out.positions, again.positions), (out.ids, again.ids), (out.arrays["type"], again.arrays["type"])):
        assert a.tobytes() == b.tobytes()


def test_the_live_particles_survive_the_capacity_growing_with_the_fluid():
    """Inflow: when the fluid outgrows the count the capacity was sized for, the live arrays are made
    again larger (once) and the live particles carried over unchanged."""
    from dataclasses import replace

    from whitecap.diffuse.generator import FoamGenerator

    gen = FoamGenerator(replace(resolve(preset="auto"), budget=2.0), R, ([0, 0, 0], [1, 1, 1]), (0, 0, -9.81), seed=3)
    gen._size(100)
    d = _data(600, 1)
    st = gen.state
    st.positions, st.velocities, st.lifetime, st.ids = d["x"], d["v"], d["life"], d["ids"]
    gen._sync_in()
    small = gen._live[0]["x"].shape[0]
    assert 600 <= small < 2000
    gen._size(10_000)
    assert gen._live[0]["x"].shape[0] == gen.capacity > 20_000
    out = gen._download()
    for a, b in ((out.positions, d["x"]), (out.velocities, d["v"]), (out.arrays["lifetime"], d["life"]), (out.ids, d["ids"])):
        assert a.tobytes() == b.tobytes()
