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
    g = NeighborGrid(grid_spec((0, 0, 0), (1, 1, 1), H / 2), len(x), 512, H)
    xs = ti.Vector.ndarray(3, ti.f32, len(x))
    xs.from_numpy(x)
    g.build(xs, len(x))
    return g, xs, x


def test_neighbor_lists_are_exactly_the_pairs_within_h(grid_and_points):
    g, _, x = grid_and_points
    near, edge = _within(x, x)
    np.fill_diagonal(near, False)
    counts, nb = g.nb_count.to_numpy(), g.nb.to_numpy()
    assert g.overflow == 0
    assert near.sum(1).max() > 50  # the blobs really fill many cells
    for i in range(len(x)):
        found = np.zeros(len(x), bool)
        found[nb[i, : counts[i]]] = True
        assert len(set(nb[i, : counts[i]])) == counts[i]  # no particle twice
        assert not ((found != near[i]) & ~edge[i]).any(), f"particle {i}"
        # The row is padded with the particle itself up to a multiple of g.pad (the solver's loops run over it).
        assert (nb[i, counts[i]:min(-(-counts[i] // g.pad) * g.pad, g.max_neighbors)] == i).all()


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
    counts, nb = g.nb_count.to_numpy(), g.nb.to_numpy()
    sure = ~edge.any(1)
    assert (counts[sure] == np.minimum(true[sure], cap)).all()
    assert overflow == (np.maximum(true - cap, 0)).sum() and overflow > 0
    for i in np.flatnonzero(sure)[:300]:
        assert near[i, nb[i, : counts[i]]].all()


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
