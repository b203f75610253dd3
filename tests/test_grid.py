"""The one neighbour query (sim/grid.py for_each_neighbor), checked against brute force.

The solver's neighbour lists and the diffuse stage's fluid neighbourhood both
come from it; each must find exactly the pairs closer than h that an all-pairs
search finds, wherever the point lies (cell borders, domain borders, outside).
"""

import numpy as np
import pytest

H = 0.1


def _points(n: int, seed: int) -> np.ndarray:
    """Clustered points in the unit box: dense blobs (many per cell) and a sparse rest."""
    rng = np.random.default_rng(seed)
    blobs = rng.uniform(0.1, 0.9, (6, 3))
    dense = blobs[rng.integers(0, 6, n // 2)] + rng.normal(0, 0.03, (n // 2, 3))
    sparse = rng.uniform(0.0, 1.0, (n - n // 2, 3))
    return np.clip(np.concatenate([dense, sparse]), 0.0, 1.0).astype(np.float32)


def _within(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pairs closer than h, pairs so near the cut that float rounding may decide) over a × b."""
    d2 = ((a[:, None, :].astype(np.float64) - b[None, :, :]) ** 2).sum(-1)
    return d2 < H * H, np.abs(d2 - H * H) < 1e-6 * H * H


@pytest.fixture(scope="module")
def grid_and_points():
    import taichi as ti

    from whitecap.sim import runtime
    from whitecap.sim.grid import NeighborGrid, grid_spec

    runtime.init("cpu")
    x = _points(3000, seed=5)
    g = NeighborGrid(grid_spec((0, 0, 0), (1, 1, 1), H / 2), len(x), 512, H, compact=True)
    xs = ti.Vector.ndarray(3, ti.f32, len(x))
    xs.from_numpy(x)
    g.build(xs, len(x))
    return g, xs, x


def test_neighbor_lists_are_exactly_the_pairs_within_h(grid_and_points):
    import taichi as ti

    g, _, x = grid_and_points
    near, edge = _within(x, x)
    np.fill_diagonal(near, False)
    counts, nb = g.lists(len(x))
    assert g.overflow == 0 and not g.wide and g.nb.dtype == ti.i16  # the offsets fit in 16 bits
    assert near.sum(1).max() > 50  # the blobs really fill many cells
    for i in range(len(x)):
        found = np.zeros(len(x), bool)
        found[nb[i, : counts[i]]] = True
        assert len(set(nb[i, : counts[i]])) == counts[i]  # no particle twice
        assert not ((found != near[i]) & ~edge[i]).any(), f"particle {i}"


def test_full_lists_count_the_overflow_and_keep_true_neighbours():
    import taichi as ti

    from whitecap.sim import runtime
    from whitecap.sim.grid import NeighborGrid, grid_spec

    runtime.init("cpu")
    x = _points(1500, seed=9)
    cap = 8
    g = NeighborGrid(grid_spec((0, 0, 0), (1, 1, 1), H / 2), len(x), cap, H)
    xs = ti.Vector.ndarray(3, ti.f32, len(x))
    xs.from_numpy(x)
    overflow = g.build(xs, len(x))
    near, edge = _within(x, x)
    np.fill_diagonal(near, False)
    true = near.sum(1)
    counts, nb = g.lists(len(x))
    sure = ~edge.any(1)
    assert (counts[sure] == np.minimum(true[sure], cap)).all()
    assert overflow == (np.maximum(true - cap, 0)).sum() and overflow > 0
    for i in np.flatnonzero(sure)[:300]:
        assert near[i, nb[i, : counts[i]]].all()


def test_offsets_too_large_for_16_bits_fall_back_to_the_same_lists_in_32_bits():
    """The lists hold j − i in 16 bits; a build with any offset over the limit fills 32-bit lists
    instead, with the same neighbours in the same order, and says how many did not fit. The next
    build goes straight to 32 bits, and back to 16 once the offsets fit. The limit is lowered here
    (the points are in no order: their offsets run to ~3000) so that some do not fit."""
    import taichi as ti

    from whitecap.sim import runtime
    from whitecap.sim.grid import NeighborGrid, grid_spec

    runtime.init("cpu")
    x = _points(3000, seed=5)
    xs = ti.Vector.ndarray(3, ti.f32, len(x))
    xs.from_numpy(x)
    ref = NeighborGrid(grid_spec((0, 0, 0), (1, 1, 1), H / 2), len(x), 512, H)  # 32-bit from the start
    ref.build(xs, len(x))
    c0, nb0 = ref.lists(len(x))
    off = np.abs(nb0 - np.arange(len(x))[:, None])[np.arange(512)[None, :] < c0[:, None]]
    assert ref.wide and ref.far == 0 and ref.nb_narrow is None and off.max() > 1000
    limit = 1000
    g = NeighborGrid(grid_spec((0, 0, 0), (1, 1, 1), H / 2), len(x), 512, H, compact=True)
    g.offset_limit = limit
    for _ in range(2):  # the 16-bit attempt, then straight to 32 bits
        g.build(xs, len(x))
        assert g.wide and g.nb.dtype == ti.i32 and not g.try_narrow
        assert g.far == (off > limit).sum()
        c, nb = g.lists(len(x))
        assert (c == c0).all()
        for i in range(len(x)):
            assert (nb[i, : c[i]] == nb0[i, : c0[i]]).all(), i
    g.offset_limit = 2**15 - 1
    g.build(xs, len(x))  # the offsets fit: this build is still 32-bit, the next one 16-bit
    assert g.wide and g.far == 0 and g.try_narrow
    g.build(xs, len(x))
    assert not g.wide and g.nb.dtype == ti.i16
    c, nb = g.lists(len(x))
    assert all((nb[i, : c[i]] == nb0[i, : c0[i]]).all() for i in range(len(x)))


def test_slice_span_bounds_the_offsets_right_after_a_sort():
    """slice_span (how the solver decides on 16-bit lists) is an upper bound on |j − i| for
    particles numbered in cell order, and not a loose one."""
    import taichi as ti

    from whitecap.sim import runtime
    from whitecap.sim.grid import NeighborGrid, grid_spec, slice_span

    runtime.init("cpu")
    spec = grid_spec((0, 0, 0), (1, 1, 1), H / 2)
    g0 = NeighborGrid(spec, 3000, 512, H)
    x = _points(3000, seed=7)
    xs = ti.Vector.ndarray(3, ti.f32, len(x))
    xs.from_numpy(x)
    g0.sort(xs, len(x))
    x = x[g0.order.to_numpy()[: len(x)]]  # renumbered in cell order
    xs.from_numpy(x)
    g = NeighborGrid(spec, len(x), 512, H, compact=True)
    g.build(xs, len(x))
    c, nb = g.lists(len(x))
    off = np.abs(nb - np.arange(len(x))[:, None])[np.arange(512)[None, :] < c[:, None]]
    span = slice_span(x, spec, g.reach)
    assert off.max() <= span < 2 * off.max()


def test_fluid_neighbourhood_of_any_point_matches_brute_force(grid_and_points):
    import taichi as ti

    from whitecap.diffuse.kernels import fluid_neighbourhood

    g, _, x = grid_and_points
    rng = np.random.default_rng(2)
    # Points anywhere, also on cell borders and just outside the grid's box.
    q = np.concatenate([rng.uniform(-0.05, 1.05, (400, 3)), np.round(x[:100] / (H / 2)) * (H / 2)]).astype(np.float32)
    v = rng.normal(0, 1, (len(x), 3)).astype(np.float32)
    fv = ti.Vector.ndarray(3, ti.f32, len(x))
    fv.from_numpy(v)
    qs = ti.Vector.ndarray(3, ti.f32, len(q))
    qs.from_numpy(q)
    cnt, vsum, wsum = ti.ndarray(ti.i32, len(q)), ti.Vector.ndarray(3, ti.f32, len(q)), ti.ndarray(ti.f32, len(q))
    F3 = ti.types.ndarray(dtype=ti.math.vec3, ndim=1)
    I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
    F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)

    @ti.kernel
    def probe(m: ti.i32, qs: F3, lower: ti.math.vec3, inv_cell: ti.f32, dims: ti.math.ivec3, xs: F3, start: I1,
              reach: ti.template(), h: ti.f32, order: I1, fv: F3, cnt: I1, vsum: F3, wsum: F1):
        for p in range(m):
            c, vs, ws = fluid_neighbourhood(qs[p], lower, inv_cell, dims, xs, start, reach, h, order, fv)
            cnt[p], vsum[p], wsum[p] = c, vs, ws

    probe(len(q), qs, *g.query_args(), H, g.order, fv, cnt, vsum, wsum)
    near, edge = _within(q, x)
    sure = ~edge.any(1)
    assert sure.sum() > 400 and near.sum(1).max() > 50
    r = np.sqrt(((q[:, None, :].astype(np.float64) - x[None]) ** 2).sum(-1))
    w = np.where(near, 1.0 - r / H, 0.0)
    assert (cnt.to_numpy()[sure] == near.sum(1)[sure]).all()
    np.testing.assert_allclose(wsum.to_numpy()[sure], w.sum(1)[sure], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(vsum.to_numpy()[sure], (w @ v)[sure], rtol=1e-3, atol=1e-4)
