"""Compaction of the diffuse particles on the device (issue 31, goal 1): the exclusive prefix sum
(sim/scan.py, through FoamGenerator._scan) and FoamGenerator._compact keep every live particle exactly once,
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


@pytest.mark.parametrize("n", [1, 16, 17, 5000, 16 * 512 + 1, 3_000_000])
def test_the_gpus_layout_of_the_prefix_sum_gives_the_same_sums(n):
    """The layout a GPU runs (many short blocks, their sums scanned in groups: sim.scan.scan_block), here on the
    CPU: the same exclusive cumsum, across block and group edges (16 * 512 elements fill one group of blocks)."""
    from whitecap.sim.scan import SCAN_GROUP, SCAN_SUMS, exclusive_scan, scan_block

    block = scan_block(n, gpu=True)
    assert block < scan_block(n, gpu=False) or n < 256
    if n > 16 * SCAN_GROUP:  # the largest cases span several groups of blocks
        assert -(-n // block) > SCAN_GROUP
    a = np.random.default_rng(n).integers(0, 5, n).astype(np.int32)
    src, out, sums = ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, SCAN_SUMS)
    src.from_numpy(a)
    assert exclusive_scan(n, src, sums, out, gpu=True) == int(a.sum())
    np.testing.assert_array_equal(out.to_numpy(), np.concatenate([[0], np.cumsum(a)[:-1]]))


def _data(nd: int) -> dict:
    rng = np.random.default_rng(7)
    return {
        "x": rng.uniform(0.1, 0.9, (nd, 3)).astype(np.float32), "v": rng.normal(0, 1, (nd, 3)).astype(np.float32),
        "life": rng.uniform(0, 5, nd).astype(np.float32), "ids": rng.permutation(10 * nd)[:nd].astype(np.uint32),
        "keep": (rng.random(nd) < 0.6).astype(np.int32), "kind": rng.integers(0, 3, nd).astype(np.int32),
    }


def _compact(d: dict):
    """The generator's live arrays set to ``d``, survivors flagged by keep, then one compaction without new
    particles; returns (the frame, the counts by type)."""
    gen = _generator(100_000)
    nd = len(d["x"])
    st = gen.state
    st.positions, st.velocities, st.lifetime, st.ids = d["x"], d["v"], d["life"], d["ids"]
    gen._sync_in()
    rows = gen._bufs["live_keep"].shape[0]
    gen._bufs["live_keep"].from_numpy(np.pad(d["keep"], (0, rows - nd)))
    gen._live[gen._cur]["kind"].from_numpy(np.pad(d["kind"], (0, rows - nd)))
    counts = gen._compact(0, 0, 0)
    return gen._download(), counts


def test_compaction_keeps_every_survivor_once_with_its_id_in_its_order():
    """Random keep flags on 30 000 live particles (more than one block of the prefix sum per thread): the
    live arrays afterwards hold exactly the flagged ones, in their order, with their ids, velocities,
    lifetimes and types, as NumPy's boolean indexing gives them; a second run gives the same bytes."""
    d = _data(30_000)
    out, counts = _compact(d)
    sel = d["keep"].astype(bool)
    np.testing.assert_array_equal(out.positions, d["x"][sel])
    np.testing.assert_array_equal(out.velocities, d["v"][sel])
    np.testing.assert_array_equal(out.arrays["lifetime"], d["life"][sel])
    np.testing.assert_array_equal(out.ids, d["ids"][sel])
    np.testing.assert_array_equal(out.arrays["type"], d["kind"][sel].astype(np.uint8))
    assert counts == np.bincount(d["kind"][sel], minlength=3).tolist()
    again, _ = _compact(d)
    assert again.positions.tobytes() == out.positions.tobytes() and again.ids.tobytes() == out.ids.tobytes()


def test_survivors_come_first_in_their_order_then_the_new_with_the_next_ids():
    """Frames of a splash: each frame's particles are the last frame's survivors, in the order they had,
    then the new ones with ids next_id, next_id + 1, ... (none is born outside this domain); every id once."""
    from dataclasses import replace

    from .test_diffuse_generate import DT, _generator as splash_generator, _splash

    gen = splash_generator((30.0, 1.0, 1.0))
    gen.p = replace(gen.p, spray_lifetime=(0.005, 0.02))  # spray lives one to three frames
    prev = None
    for k in range(4):
        f = _splash()
        f.positions = f.positions + k * DT * f.velocities
        first_new = gen.state.next_id
        d = gen.step(f, k, DT)
        old = d.ids < first_new
        n_old = int(old.sum())
        assert old[:n_old].all() and not old[n_old:].any()  # survivors first
        np.testing.assert_array_equal(d.ids[n_old:], np.arange(first_new, gen.state.next_id, dtype=np.uint32))
        if prev is not None:
            assert n_old > 100 and n_old < len(prev)  # some survived, some went
            np.testing.assert_array_equal(d.ids[:n_old], prev[np.isin(prev, d.ids[:n_old])])  # in their order
        assert len(np.unique(d.ids)) == len(d)
        prev = d.ids


def test_the_live_particles_survive_the_capacity_growing_with_the_fluid():
    """Inflow: when the fluid outgrows the count the capacity was sized for, the live arrays are made
    again larger (once) and the live particles carried over unchanged."""
    from dataclasses import replace

    from whitecap.diffuse.generator import FoamGenerator

    gen = FoamGenerator(replace(resolve(preset="auto"), budget=2.0), R, ([0, 0, 0], [1, 1, 1]), (0, 0, -9.81), seed=3)
    gen._size(100)
    d = _data(600)
    st = gen.state
    st.positions, st.velocities, st.lifetime, st.ids = d["x"], d["v"], d["life"], d["ids"]
    gen._sync_in()
    small = gen._live[0]["x"].shape[0]
    assert 600 <= small < 2000
    gen._size(10_000)
    assert gen._live[0]["x"].shape[0] == gen.capacity > 20_000
    out = gen._download()
    for a, b in ((out.positions, d["x"]), (out.velocities, d["v"]), (out.arrays["lifetime"], d["life"]),
                 (out.ids, d["ids"])):
        assert a.tobytes() == b.tobytes()
