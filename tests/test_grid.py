"""The one neighbour query (sim/grid.py for_each_neighbor), checked against brute force.

The solver's neighbour lists and the diffuse stage's fluid neighbourhood both
come from it; each must find exactly the pairs closer than h that an all-pairs
search finds, wherever the point lies (cell borders, domain borders, outside),
with the dense cell table and with the hashed one (issue 31: memory set by the
particles, not by the domain).
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


@pytest.fixture(scope="module", params=["dense", "hashed"])
def grid_and_points(request):
    import taichi as ti

    from whitecap.sim import runtime
    from whitecap.sim.grid import NeighborGrid, grid_spec

    runtime.init("cpu")
    x = _points(3000, seed=5)
    g = NeighborGrid(grid_spec((0, 0, 0), (1, 1, 1), H / 2), len(x), 512, H, request.param)
    assert g.layout == request.param
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


@pytest.mark.parametrize("layout", ["dense", "hashed"])
def test_full_lists_count_the_overflow_and_keep_true_neighbours(layout):
    import taichi as ti

    from whitecap.sim import runtime
    from whitecap.sim.grid import NeighborGrid, grid_spec

    runtime.init("cpu")
    x = _points(1500, seed=9)
    cap = 8
    g = NeighborGrid(grid_spec((0, 0, 0), (1, 1, 1), H / 2), len(x), cap, H, layout)
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


def test_lists_are_cut_to_32_bit_indices_and_the_pairs_past_them_counted(monkeypatch, capsys):
    """Taichi indexes an array with 32-bit integers: lists of 64 for 50 M particles would pass it. The grid
    cuts its lists to what fits (42 at 50 M), says so, counts the pairs past them as overflow and keeps true
    neighbours; under MIN_LIST_SLOTS it refuses with one line."""
    import taichi as ti

    from whitecap.errors import WhitecapError
    from whitecap.sim import grid as G, runtime

    assert G.list_slots(50_000_000, 64) == 42 and G.list_slots(30_000_000, 64) == 64
    with pytest.raises(WhitecapError, match="neighbour lists would hold 15 entries"):
        G.list_slots(140_000_000, 64)
    runtime.init("cpu")
    x = _points(1500, seed=9)
    monkeypatch.setattr(G, "MAX_NDARRAY_ELEMENTS", len(x) * 40 + 7)  # room for 40 a particle, not 64
    monkeypatch.setattr(G, "MIN_LIST_SLOTS", 16)
    g = G.NeighborGrid(G.grid_spec((0, 0, 0), (1, 1, 1), H / 2), len(x), 64, H)
    assert g.max_neighbors == 40 and g.cut and g.nb.shape == (len(x), 40)
    said = " ".join(capsys.readouterr().err.split())
    assert "neighbour lists of 40 entries a particle at 1,500 particles, not 64" in said
    xs = ti.Vector.ndarray(3, ti.f32, len(x))
    xs.from_numpy(x)
    overflow = g.build(xs, len(x))
    near, edge = _within(x, x)
    np.fill_diagonal(near, False)
    true, sure = near.sum(1), ~edge.any(1)
    assert true.max() > 40  # some lists were cut
    assert (g.nb_count.to_numpy()[sure] == np.minimum(true[sure], 40)).all()
    assert overflow == np.maximum(true - 40, 0).sum() > 0


def test_fluid_neighbourhood_of_any_point_matches_brute_force(grid_and_points):
    import taichi as ti

    from whitecap.diffuse.kernels import fluid_neighbourhood
    from whitecap.sim.grid import GridQuery, gather_vec3

    g, _, x = grid_and_points
    rng = np.random.default_rng(2)
    # Points anywhere, also on cell borders and just outside the grid's box.
    q = np.concatenate([rng.uniform(-0.05, 1.05, (400, 3)), np.round(x[:100] / (H / 2)) * (H / 2)]).astype(np.float32)
    v = rng.normal(0, 1, (len(x), 3)).astype(np.float32)
    fv = ti.Vector.ndarray(3, ti.f32, len(x))
    fv.from_numpy(v)
    vs = ti.Vector.ndarray(3, ti.f32, len(x))  # the velocities in the grid's cell order, as the query reads them
    gather_vec3(len(x), g.order, fv, vs)
    qs = ti.Vector.ndarray(3, ti.f32, len(q))
    qs.from_numpy(q)
    cnt, vsum, wsum = ti.ndarray(ti.i32, len(q)), ti.Vector.ndarray(3, ti.f32, len(q)), ti.ndarray(ti.f32, len(q))
    F3 = ti.types.ndarray(dtype=ti.math.vec3, ndim=1)
    I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
    F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)

    @ti.kernel
    def probe(m: ti.i32, qs: F3, grid: GridQuery, scan: ti.template(), h: ti.f32, vs: F3, cnt: I1, vsum: F3,
              wsum: F1):
        for p in range(m):
            c, vv, ws = fluid_neighbourhood(qs[p], grid, scan, h, vs)
            cnt[p], vsum[p], wsum[p] = c, vv, ws

    probe(len(q), qs, *g.query_args(), H, vs, cnt, vsum, wsum)
    near, edge = _within(q, x)
    sure = ~edge.any(1)
    assert sure.sum() > 400 and near.sum(1).max() > 50
    r = np.sqrt(((q[:, None, :].astype(np.float64) - x[None]) ** 2).sum(-1))
    w = np.where(near, 1.0 - r / H, 0.0)
    assert (cnt.to_numpy()[sure] == near.sum(1)[sure]).all()
    np.testing.assert_allclose(wsum.to_numpy()[sure], w.sum(1)[sure], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(vsum.to_numpy()[sure], (w @ v)[sure], rtol=1e-3, atol=1e-4)


def test_a_count_that_stops_past_its_threshold_is_exact_below_it(grid_and_points):
    """fluid_count (for_each_neighbor with a stop, columns nearest first): the brute-force count of the
    fluid particles within h where that is at most the threshold, a number above it where the true count is;
    so a type decided by count > threshold is the full count's."""
    import taichi as ti

    from whitecap.diffuse.kernels import fluid_count
    from whitecap.sim.grid import GridQuery

    g, _, x = grid_and_points
    rng = np.random.default_rng(3)
    q = np.concatenate([rng.uniform(-0.05, 1.05, (400, 3)), x[:300] + rng.normal(0, H / 4, (300, 3)),
                        np.round(x[300:400] / (H / 2)) * (H / 2)]).astype(np.float32)
    qs = ti.Vector.ndarray(3, ti.f32, len(q))
    qs.from_numpy(q)
    F3 = ti.types.ndarray(dtype=ti.math.vec3, ndim=1)
    I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)

    @ti.kernel
    def probe(m: ti.i32, qs: F3, grid: GridQuery, scan: ti.template(), h: ti.f32, most: ti.i32, cnt: I1):
        for p in range(m):
            cnt[p] = fluid_count(qs[p], grid, scan, h, most)

    near, edge = _within(q, x)
    true = near.sum(1)
    sure = ~edge.any(1)
    for most in (2, 20, 60):
        cnt = ti.ndarray(ti.i32, len(q))
        probe(len(q), qs, *g.query_args(), H, most, cnt)
        c = cnt.to_numpy()
        below = sure & (true <= most)
        above = sure & (true > most)
        assert below.sum() > 20 and above.sum() > 20, (most, below.sum(), above.sum())
        assert (c[below] == true[below]).all()
        assert (c[above] > most).all() and (c[above] <= true[above]).all()
    assert (true[sure] > 60).sum() > 50  # points deep in the blobs, whose count stops early


# ---------------------------------------------------------------- hashed cell table (issue 31 goal 3)
def _near_chunked(a: np.ndarray, b: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_within` for another h, a few rows at a time (no n × n × 3 intermediate)."""
    near, edge = np.zeros((len(a), len(b)), bool), np.zeros((len(a), len(b)), bool)
    b64 = b.astype(np.float64)
    for k in range(0, len(a), 256):
        d2 = ((a[k:k + 256, None, :].astype(np.float64) - b64[None]) ** 2).sum(-1)
        near[k:k + 256], edge[k:k + 256] = d2 < h * h, np.abs(d2 - h * h) < 1e-6 * h * h
    return near, edge


def _lists(spec, x: np.ndarray, h: float, layout: str, max_neighbors: int = 256):
    """A built grid of the given layout over ``x`` and its lists as one set per particle."""
    import taichi as ti

    from whitecap.sim.grid import NeighborGrid

    g = NeighborGrid(spec, len(x), max_neighbors, h, layout)
    xs = ti.Vector.ndarray(3, ti.f32, len(x))
    xs.from_numpy(x)
    assert g.build(xs, len(x)) == 0
    counts, nb = g.nb_count.to_numpy(), g.nb.to_numpy()
    for i in range(len(x)):
        assert len(set(nb[i, : counts[i]])) == counts[i]  # no particle twice
    return g, xs, counts, nb


def _assert_brute_force(x: np.ndarray, counts: np.ndarray, nb: np.ndarray, h: float) -> None:
    near, edge = _near_chunked(x, x, h)
    np.fill_diagonal(near, False)
    for i in range(len(x)):
        found = np.zeros(len(x), bool)
        found[nb[i, : counts[i]]] = True
        assert not ((found != near[i]) & ~edge[i]).any(), f"particle {i} at {x[i]}"


@pytest.mark.parametrize("buckets", [None, 16])
def test_hashed_lists_equal_dense_ones_on_faces_and_far_outside_the_domain(buckets, monkeypatch):
    """Particles exactly on the domain's faces, edges and corners, and clusters far outside it (they
    belong to the border cells, clamped): both tables give exactly the same neighbour sets, those of
    brute force. The hashed table's layout does not depend on thread timing: two builds, same lists.
    With a table of 16 buckets every bucket holds many cells and most columns' runs wrap round the
    table's end: still each neighbour exactly once."""
    from whitecap.sim import grid, runtime
    from whitecap.sim.grid import grid_spec

    runtime.init("cpu")
    if buckets:
        monkeypatch.setattr(grid, "BUCKETS_PER_PARTICLE", 0)
        monkeypatch.setattr(grid, "MIN_BUCKETS", buckets)
    rng = np.random.default_rng(11)
    inner = _points(1500, seed=3)
    faces = rng.uniform(0.0, 1.0, (400, 3))
    for k, row in enumerate(faces):  # one, two or three coordinates on a face: faces, edges, corners
        axes = rng.choice(3, 1 + k % 3, replace=False)
        row[axes] = rng.integers(0, 2, len(axes))
    far = np.concatenate([c + rng.normal(0, 0.03, (40, 3)) for c in ([-30.0, 0.5, 0.5], [5.0, 8.0, -20.0],
                                                                     [1.04, 0.5, 1.02], [0.5, -0.06, 0.5])])
    x = np.concatenate([inner, faces, far]).astype(np.float32)
    spec = grid_spec((0, 0, 0), (1, 1, 1), H / 2)
    gd, _, cd, nd = _lists(spec, x, H, "dense")
    gh, xs, ch, nh = _lists(spec, x, H, "hashed")
    assert (gd.layout, gh.layout) == ("dense", "hashed") and gh.table_size == (buckets or gh.table_size)
    assert (cd == ch).all()
    for i in range(len(x)):
        assert set(nd[i, : cd[i]]) == set(nh[i, : ch[i]]), f"particle {i}"
    _assert_brute_force(x, ch, nh, H)
    assert ch[-160:].min() > 5  # the far clusters really have neighbours
    order, nb = gh.order.to_numpy().copy(), nh.copy()
    gh.build(xs, len(x))
    assert (gh.order.to_numpy() == order).all() and (gh.nb.to_numpy() == nb).all()


def test_a_domain_1000_times_the_fluid_is_hashed_and_gives_brute_force_neighbours():
    """A small blob of water in a 100 m × 100 m × 20 m box, 1000× its volume: the grid chooses the
    hashed table, whose memory is set by the particles (the dense one would need 4.7 M cells, 300×
    the particles), and its lists are those of brute force."""
    from whitecap.sim import runtime
    from whitecap.sim.grid import BUCKETS_PER_PARTICLE, grid_spec

    runtime.init("cpu")
    n, h, maxnb = 4000, 0.7, 128
    rng = np.random.default_rng(4)
    x = (np.array([40.0, 60.0, 3.0]) + rng.uniform(0, 1, (n, 3)) * [10.0, 10.0, 2.0]).astype(np.float32)
    spec = grid_spec((0, 0, 0), (100, 100, 20), h / 2)
    assert spec.ncells > 1000 * n
    g, _, counts, nb = _lists(spec, x, h, "auto", maxnb)
    assert g.layout == "hashed"
    per_particle = g.nbytes() / n
    lists = 4 * (7 + maxnb)  # what every layout keeps per particle
    assert per_particle < lists + 4 * 2 * BUCKETS_PER_PARTICLE + 8, per_particle  # the table: T + 1 words, T < 2·8·n
    assert counts.mean() > 15
    _assert_brute_force(x, counts, nb, h)


def test_millimetre_cells_in_a_coastal_box_are_not_refused():
    """100 m × 100 m × 20 m at 1 mm cells: 2·10¹⁴ cells, whose keys need 64 bits. Refused before (more
    than 64 M cells); now a hashed table of a few thousand buckets, neighbours from brute force, also for
    particles on the box's far corner and beyond it."""
    from whitecap.errors import WhitecapError
    from whitecap.sim import runtime
    from whitecap.sim.grid import grid_spec

    runtime.init("cpu")
    h = 0.002
    rng = np.random.default_rng(8)
    blob = np.array([73.21, 41.77, 12.34]) + rng.uniform(0, 0.01, (1500, 3))
    corner = np.array([100.0, 100.0, 20.0]) - rng.uniform(-0.003, 0.003, (300, 3))
    x = np.concatenate([blob, corner]).astype(np.float32)
    spec = grid_spec((0, 0, 0), (100, 100, 20), h / 2)
    assert spec.dims == (100000, 100000, 20000)
    g, _, counts, nb = _lists(spec, x, h, "auto")
    assert g.layout == "hashed" and g.nbytes() < 4 * len(x) * (7 + 256) + 64 * len(x)
    assert counts[:1500].mean() > 15
    _assert_brute_force(x, counts, nb, h)
    with pytest.raises(WhitecapError, match="along an axis"):
        grid_spec((0, 0, 0), (1e4, 1, 1), 1e-3)


def test_the_diffuse_stage_classifies_alike_with_both_tables(monkeypatch):
    """The diffuse stage's queries (diffuse/kernels.py, through for_each_neighbor) in a hashed grid: a
    FoamGenerator in a 100 m × 100 m × 20 m domain runs 3 frames of a splash, and the types of points
    around it (its diffuse particles, points in and near the water, points anywhere) are those that the
    same generator in a small domain, with a dense grid, gives."""
    import taichi as ti

    from whitecap.diffuse import kernels as K
    from whitecap.diffuse.generator import FoamGenerator, _nd
    from whitecap.sim import grid

    from .test_diffuse_generate import DT, R, _generator, _splash

    frame = _splash()
    huge = _generator((1.0, 1.0, 1.0))
    huge = FoamGenerator(huge.p, R, ([-50, -50, -10], [50, 50, 10]), (0, 0, -9.81), seed=11)
    monkeypatch.setattr(grid, "DENSE_CELLS_PER_PARTICLE", 10**9)  # the small domain's grid dense
    small = _generator((1.0, 1.0, 1.0))
    rng = np.random.default_rng(1)
    q, kinds, made = None, {}, {}
    for name, gen in (("hashed", huge), ("dense", small)):
        for k in range(3):
            out = gen.step(frame, k, DT)
        assert gen.grid.layout == name
        assert np.isfinite(out.positions).all()
        made[name] = len(out)
        if q is None:
            q = np.concatenate([out.positions, frame.positions + rng.normal(0, gen.h / 3, frame.positions.shape),
                                rng.uniform(-0.5, 1.5, (500, 3))]).astype(np.float32)
        p = gen.p
        _, _, _, args = gen._prepare(frame, len(frame))
        kd = ti.ndarray(ti.i32, len(q))
        K.classify(len(q), _nd(q, ti.f32, True), *args, p.spray_below, p.bubble_above, ti.math.vec3(*gen.lo),
                   ti.math.vec3(*gen.hi), 0, kd)
        kinds[name] = kd.to_numpy()
    assert (kinds["hashed"] == kinds["dense"]).all()
    assert len(np.unique(kinds["dense"])) == 3  # spray, foam and bubbles all met
    # The frames' diffuse particles: the same but for float summation order in the potentials.
    assert made["hashed"] > 100 and abs(made["hashed"] - made["dense"]) <= 0.01 * made["dense"], made


def test_a_tiny_scene_in_a_huge_domain_steps_on_the_cpu():
    """simulate's solver on a small block of water in a 100 m × 100 m × 20 m domain: a hashed grid (a
    dense one would need 3·10⁹ cells), and the block falls and spreads as the same block does in a
    small domain whose table is dense (the walls it meets are the same: the floor and two sides)."""
    from whitecap.config import scene_from_dict
    from whitecap.sim.driver import build_solver

    from .conftest import tiny_scene_dict

    out = {}
    for name, upper in (("huge", [100.0, 100.0, 20.0]), ("small", [0.6, 0.4, 0.4])):
        sc = scene_from_dict(tiny_scene_dict(domain={"upper": upper}))
        s = build_solver(sc)
        assert s.grid.layout == ("hashed" if name == "huge" else "dense")
        a = s.arrays(with_density=False)
        x0 = a["positions"][np.argsort(a["ids"])]
        for _ in range(15):
            s.step(1.0 / 600.0)
        a = s.arrays(with_density=False)
        out[name] = a["positions"][np.argsort(a["ids"])]  # cell order differs between the tables
        if name == "huge":
            assert s.memory_bytes() / s.n < 1000
    x, ref = out["huge"], out["small"]
    assert np.isfinite(x).all()
    assert np.abs(x - x0).max() > 0.01  # the column has begun to fall and spread
    # Same start, same walls nearby: the same motion but for float summation order (other lists' order).
    np.testing.assert_allclose(x, ref, atol=1e-5)


@pytest.mark.parametrize("layout", ["dense", "hashed"])
def test_a_grid_built_without_lists_sorts_as_one_with_them(layout):
    """build(lists=False) (the foam stage, where no potentials are computed) gives the cell order, the table
    and the positions in cell order that the queries read, exactly as a full build does, and leaves the lists."""
    import taichi as ti

    from whitecap.sim import runtime
    from whitecap.sim.grid import NeighborGrid, grid_spec

    runtime.init("cpu")
    x = _points(2000, seed=9)
    xs = ti.Vector.ndarray(3, ti.f32, len(x))
    xs.from_numpy(x)
    full, bare = (NeighborGrid(grid_spec((0, 0, 0), (1, 1, 1), H / 2), len(x), 256, H, layout) for _ in range(2))
    full.build(xs, len(x))
    bare.nb_count.fill(-1)
    assert bare.build(xs, len(x), lists=False) == 0
    for name in ("order", "start", "x_sorted"):
        assert (getattr(full, name).to_numpy() == getattr(bare, name).to_numpy()).all(), name
    assert (full.x_sorted.to_numpy() == x[full.order.to_numpy()]).all()
    assert (bare.nb_count.to_numpy() == -1).all()  # no lists were built


@pytest.mark.parametrize("layout", ["dense", "hashed"])
def test_a_sorted_build_is_a_bare_build_and_a_gather_in_one_graph(layout):
    """build_sorted (the foam stage's frame: the sort and the velocities in cell order) gives the same cell order,
    table, positions and gathered array as build(lists=False) and gather_vec3, frame after frame with new
    arrays bound, and on the CPU runs as one compute graph (compiled once a process, for every grid)."""
    import taichi as ti

    from whitecap.sim import grid as grid_mod, runtime
    from whitecap.sim.grid import NeighborGrid, gather_vec3, grid_spec

    runtime.init("cpu")
    graphs = []
    for seed, n, top in ((21, 2000, 1.0), (22, 1500, 1.3)):  # the second frame: another grid, another domain
        ref, g = (NeighborGrid(grid_spec((0, 0, 0), (top, 1, top), H / 2), n, 256, H, layout) for _ in range(2))
        x, v = _points(n, seed), np.random.default_rng(seed).normal(0, 1, (n, 3)).astype(np.float32)
        xs, vs = ti.Vector.ndarray(3, ti.f32, n), ti.Vector.ndarray(3, ti.f32, n)
        xs.from_numpy(x)
        vs.from_numpy(v)
        want, got = ti.Vector.ndarray(3, ti.f32, n), ti.Vector.ndarray(3, ti.f32, n)
        ref.build(xs, n, lists=False)
        gather_vec3(n, ref.order, vs, want)
        g.build_sorted(xs, n, vs, got)
        for name in ("order", "start", "x_sorted"):
            assert (getattr(ref, name).to_numpy()[:n] == getattr(g, name).to_numpy()[:n]).all(), name
        assert (got.to_numpy() == want.to_numpy()).all()
        assert (got.to_numpy() == v[g.order.to_numpy()[:n]]).all()
        graphs.append(grid_mod._SORTED_GRAPHS.get((g.hashed, g.sum_group)))
    assert graphs[0] is not None and graphs[1] is graphs[0]


@pytest.mark.parametrize("layout", ["dense", "hashed"])
def test_marked_lists_are_the_rows_a_whole_build_makes(layout):
    """build_marked (the foam stage's lists, of the energetic particles alone) writes each marked particle's row as
    the whole build does, whether its group of the cell order is scanned at once (MARKED_GROUP marked or more) or
    it alone: marks in runs (whole groups), in pairs and single, and on particles outside the domain."""
    import taichi as ti

    from whitecap.sim import runtime
    from whitecap.sim.grid import GROUP, MARKED_GROUP, NeighborGrid, grid_spec

    runtime.init("cpu")
    x = _points(2000, seed=11)
    x[:40] += np.float32(0.3)  # some beyond the domain's upper faces (in its border cells)
    xs = ti.Vector.ndarray(3, ti.f32, len(x))
    xs.from_numpy(x)
    full, part = (NeighborGrid(grid_spec((0, 0, 0), (1, 1, 1), H / 2), len(x), 256, H, layout) for _ in range(2))
    full.build(xs, len(x))
    part.build(xs, len(x), lists=False)
    part.nb_count.fill(-1)
    order = part.order.to_numpy()
    rng = np.random.default_rng(3)
    mark = np.zeros(len(x), np.int32)
    mark[order[200:264]] = 1  # a run of slots: whole groups
    mark[order[rng.choice(np.arange(300, 2000, GROUP), 150, replace=False)]] = 1  # one of a group
    mark[order[np.arange(1000, 1400, 3 * GROUP)[:, None] + np.arange(MARKED_GROUP)].ravel()] = 1  # a few of a group
    mark[:40:3] = 1  # outside the domain
    mark[rng.choice(len(x), 100, replace=False)] = 2  # another value: not built
    marks = ti.ndarray(ti.i32, len(x))
    marks.from_numpy(mark)
    part.build_marked(len(x), marks, 1)
    want_n, want = full.nb_count.to_numpy(), full.nb.to_numpy()
    got_n, got = part.nb_count.to_numpy(), part.nb.to_numpy()
    rows = np.flatnonzero(mark == 1)
    assert (got_n[rows] == want_n[rows]).all()
    for i in rows:
        assert (got[i, : got_n[i]] == want[i, : want_n[i]]).all(), f"particle {i}"
    # the others are left as they were, unless their group was scanned at once: then their rows are right too
    other = np.flatnonzero(mark != 1)
    kept = got_n[other] == -1
    assert kept.mean() > 0.9
    for i in other[~kept]:
        assert (got[i, : got_n[i]] == want[i, : want_n[i]]).all(), f"particle {i}"


def test_an_unfilled_array_is_a_taichi_array_that_kernels_write_and_read():
    """runtime.empty_ndarray (the neighbour lists, the live diffuse particles): the same types and shapes as
    ti.ndarray's, and what a kernel writes is what is read back, for scalars, rows and vectors."""
    import taichi as ti

    from whitecap.sim import runtime

    runtime.init("cpu")
    rows = runtime.empty_ndarray(ti.i32, (7, 5))
    vecs = runtime.empty_ndarray(ti.f32, 9, 3)
    assert isinstance(rows, type(ti.ndarray(ti.i32, (1, 1)))) and rows.shape == (7, 5)
    assert isinstance(vecs, type(ti.Vector.ndarray(3, ti.f32, 1))) and vecs.shape == (9,) and vecs.n == 3

    @ti.kernel
    def write(a: ti.types.ndarray(dtype=ti.i32, ndim=2), v: ti.types.ndarray(dtype=ti.math.vec3, ndim=1)):
        for i, j in a:
            a[i, j] = 10 * i + j
        for p in v:
            v[p] = ti.math.vec3(p, -p, 0.5 * p)

    write(rows, vecs)
    assert (rows.to_numpy() == 10 * np.arange(7)[:, None] + np.arange(5)).all()
    p = np.arange(9, dtype=np.float32)
    assert np.array_equal(vecs.to_numpy(), np.stack([p, -p, 0.5 * p], 1))


@pytest.mark.parametrize("layout, group", [("dense", 3), ("hashed", 3), ("dense", 512)])
def test_the_gpus_grouped_scan_of_the_cell_counts_gives_the_same_table_and_lists(layout, group, monkeypatch):
    """The cell table's prefix sum as a GPU runs it (the block sums scanned in groups, sim.grid.SCAN_GROUP_GPU), here
    on the CPU: the same starts, cell order and lists as the CPU's one-thread scan, over many groups (3 blocks a
    group; a hashed table's size is set by the particles) and over the GPU's own group size in a dense table of
    2 M cells (4 groups of 512 blocks)."""
    import taichi as ti

    from whitecap.sim import grid as G, runtime

    runtime.init("cpu")
    x = _points(3000, seed=11)
    xs = ti.Vector.ndarray(3, ti.f32, len(x))
    xs.from_numpy(x)
    cell = H / 2 if group == 3 else 0.0079  # 127³ cells: 2,001 blocks of 1,024
    built = {}
    for grouped in (False, True):
        monkeypatch.setattr(G, "GROUPED_SCAN", grouped)
        monkeypatch.setattr(G, "SCAN_GROUP_GPU", group)
        g = G.NeighborGrid(G.grid_spec((0, 0, 0), (1, 1, 1), cell), len(x), 256, H, layout)
        assert g.sum_group == (group if grouped else 0)
        g.build(xs, len(x))
        built[grouped] = {k: getattr(g, k).to_numpy() for k in ("start", "order", "nb_count", "nb")}
    blocks = G.len_blocks(g.table_size)
    assert blocks > 2 * group if group == 3 else blocks > group  # several groups
    assert (built[False]["start"] > 0).any()
    for k in ("start", "order", "nb_count"):
        np.testing.assert_array_equal(built[True][k], built[False][k], err_msg=k)
    # the foam stage's sorted build, a compute graph kept by table layout and scan: the same order in both scans
    for grouped in (True, False):
        monkeypatch.setattr(G, "GROUPED_SCAN", grouped)
        g = G.NeighborGrid(G.grid_spec((0, 0, 0), (1, 1, 1), cell), len(x), 256, H, layout)
        vs = ti.Vector.ndarray(3, ti.f32, len(x))
        g.build_sorted(xs, len(x), xs, vs)
        np.testing.assert_array_equal(g.start.to_numpy(), built[False]["start"])
        np.testing.assert_array_equal(g.order.to_numpy(), built[False]["order"])
    counts = built[False]["nb_count"]
    for i in range(0, len(x), 97):
        assert (built[True]["nb"][i, :counts[i]] == built[False]["nb"][i, :counts[i]]).all()
