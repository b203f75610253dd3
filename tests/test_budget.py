"""'auto' in the simulation: the bounded history of sampled potentials (diffuse.budget), driven directly."""

from __future__ import annotations

import io as pyio

import numpy as np
import pytest

from whitecap.diffuse import budget as B
from whitecap.diffuse.params import resolve

FRAMES = 500


def _frames(frames: int = FRAMES, seed: int = 3):
    """Synthetic per-frame samples (ta, wc, ke, vo, moving), HISTORY_SAMPLE particles each, their
    scale growing over the run (a gentle start, a violent end) and 70 % of them moving."""
    rng = np.random.default_rng(seed)
    n = B.HISTORY_SAMPLE
    for f in range(frames):
        s = 1 + 4 * (f / frames) ** 2
        yield np.stack([rng.lognormal(0, 1, n) * s, rng.lognormal(0, 0.5, n), rng.lognormal(-1, 1, n) * s * s,
                        rng.lognormal(0, 1, n), rng.random(n) < 0.7], 1).astype(np.float32)


def _add(h, frame):
    return B.history_add(*h, lambda m: frame[np.linspace(0, len(frame) - 1, m).astype(np.int64)])


def _auto():
    from whitecap.config import Foam

    return resolve(Foam(preset="auto"))


def test_the_history_is_bounded_and_its_thresholds_are_the_pooled_percentiles():
    """500 frames: the history holds at most HISTORY_ROWS rows (5 MB) standing for all 500
    frames, and the thresholds from it rank within 0.1 percentage point (τmin, the 95th
    percentile) and 0.05 point (τmax, the 99.9th) of where they fall in the pool of every
    frame's samples, the unbounded history's."""
    h = B.history_empty()
    pool = []
    for frame in _frames():
        pool.append(frame)
        h = _add(h, frame)
        assert len(h[1]) <= B.HISTORY_ROWS and h[0].shape == (5, len(h[1]), B.HISTORY_SAMPLE)
    rows, frames, stride = h
    assert frames.sum() == FRAMES and stride > 1 and (frames[:-1] == stride).all()
    pool = np.concatenate(pool)
    kept = B.history_columns(*h)
    assert kept.shape[1] < len(pool) / 4
    base = np.full(8, 1e-6, np.float32)
    exact = B.percentile_thresholds({k: pool[:, c] for c, k in enumerate(("ta", "wc", "ke", "vo"))},
                                    pool[:, 4] > 0, base)
    got = B.percentile_thresholds({k: kept[c] for c, k in enumerate(("ta", "wc", "ke", "vo"))}, kept[4] > 0, base)
    for c, name in enumerate(("ta", "wc", "ke", "vo")):
        vals = pool[:, c][(pool[:, 4] > 0) & (pool[:, c] > 0)]
        for j, (q, tol) in enumerate(zip(B.AUTO_PERCENTILES, (0.1, 0.05))):
            rank = 100.0 * (vals < got[2 * c + j]).mean()
            assert abs(rank - q) <= tol, (name, q, rank, got[2 * c + j], exact[2 * c + j])


def test_a_row_rate_is_the_mean_of_its_frames_and_the_peak_is_the_frame_by_frame_one():
    """Each row's birth rate is the mean of its frames' own rates, the last, part-filled row's
    too, and the running peak over the rows equals the frame-by-frame running peak of those
    row rates repeated per frame. (Every particle of a frame has the same potentials here, so
    that sampling loses nothing and the bookkeeping is checked exactly.)"""
    p = _auto()
    tau = np.array([3, 20, 1.5, 4, 1, 6, 3, 20], np.float32)
    k, dt = (p.k_ta, p.k_wc, p.k_vo), 1 / 30
    h = B.history_empty()
    own = []
    for frame in _frames(300):
        frame = np.repeat(frame[:1] * [2, 3, 1.5, 3, 1], len(frame), axis=0).astype(np.float32)
        pots = {n: frame[:, c] for c, n in enumerate(("ta", "wc", "ke", "vo"))}
        own.append(B.birth_rate(pots, tau, k, dt) / len(frame))
        h = _add(h, frame)
    rows, frames, stride = h
    rates = B.history_rates(*h, tau, k, dt)
    bounds = np.concatenate([[0], np.cumsum(frames)])
    mean_own = np.array([np.mean(own[a:b]) for a, b in zip(bounds[:-1], bounds[1:])])
    assert stride > 1 and frames[-1] < stride
    assert np.allclose(rates, mean_own, rtol=1e-5), np.abs(rates / mean_own - 1).max()
    for frames_left in (None, 40, 1000):
        want = B.running_peak(np.repeat(rates, frames), p, dt, frames_left)
        assert B.running_peak(rates, p, dt, frames_left, frames) == pytest.approx(want, rel=1e-12)
    # a short burst among rows of many frames: its window is found wherever it falls
    burst = np.array([0.0, 0.0, 5.0, 0.0, 0.0, 0.0])
    counts = np.array([37, 3, 2, 50, 1, 64])
    assert B.running_peak(burst, p, dt, None, counts) == pytest.approx(
        B.running_peak(np.repeat(burst, counts), p, dt), rel=1e-12)


def test_a_resumed_history_is_byte_identical():
    """Saved in the checkpoint half way (through npz) and resumed: the same history as uninterrupted."""
    from whitecap.diffuse.generator import DiffuseState

    frames = list(_frames(200))
    full = B.history_empty()
    for f in frames:
        full = _add(full, f)
    st = DiffuseState.empty()
    h = B.history_empty()
    for f in frames[:130]:
        h = _add(h, f)
    st.history, st.history_frames, st.history_stride = h
    buf = pyio.BytesIO()
    np.savez(buf, **st.to_arrays())
    buf.seek(0)
    z = np.load(buf)
    st = DiffuseState.from_arrays({k: z[k] for k in z.files})
    h = (st.history, st.history_frames, st.history_stride)
    for f in frames[130:]:
        h = _add(h, f)
    assert h[2] == full[2] and np.array_equal(h[1], full[1]) and h[0].tobytes() == full[0].tobytes()


def test_the_history_keeps_each_frames_samples_column_by_column_in_order():
    """The pooled columns are the frames' own samples, in order (the part-filled last row as far as it is filled),
    before the rows first merge; a checkpoint's rows in the layout written before 2026-11-28 (a row's samples side
    by side: (rows, HISTORY_SAMPLE, 5)) are read as the same history, and go on to the same bytes."""
    from whitecap.diffuse.generator import DiffuseState

    frames = list(_frames(B.HISTORY_ROWS + 7))  # (on past the rows' first merge)
    h = B.history_empty()
    for f in frames[:25]:
        h = _add(h, f)
    assert np.array_equal(B.history_columns(*h), np.concatenate(frames[:25]).T)
    d = DiffuseState.empty().to_arrays()
    d["history"], d["history_frames"], d["history_stride"] = h[0].transpose(1, 2, 0).copy(), h[1], h[2]
    st = DiffuseState.from_arrays(d)
    assert st.history.shape == h[0].shape and st.history.tobytes() == h[0].tobytes()
    a, b = h, (st.history, st.history_frames, st.history_stride)
    for f in frames[25:]:
        a, b = _add(a, f), _add(b, f)
    assert a[0].tobytes() == b[0].tobytes() and np.array_equal(a[1], b[1]) and a[2] == b[2]
    rows, counts, stride = a
    assert stride == 2 and counts[-1] == 1  # the last row half filled: its other half is left out
    cols = B.history_columns(*a)
    assert cols.shape == (5, (len(counts) - 0.5) * B.HISTORY_SAMPLE) and cols[4].max() == 1
    half = np.linspace(0, B.HISTORY_SAMPLE - 1, B.HISTORY_SAMPLE // 2).astype(np.int64)  # the frame's picks (_add)
    assert np.array_equal(cols[:, -B.HISTORY_SAMPLE // 2:], frames[-1][half].T)


def test_a_checkpoint_from_before_the_bound_is_bounded_on_resume():
    """An old checkpoint's history, a row per frame: replayed into the bounded history."""
    from whitecap.diffuse.generator import DiffuseState

    frames = list(_frames(100))
    d = DiffuseState.empty().to_arrays()
    del d["history_frames"], d["history_stride"]
    d["history"] = np.stack(frames)
    st = DiffuseState.from_arrays(d)
    want = B.history_empty()
    for f in frames:
        want = _add(want, f)
    assert st.history_stride == want[2] and np.array_equal(st.history_frames, want[1])
    assert np.array_equal(st.history, want[0])


def test_foam_aging_holds_foam_fed_at_a_steady_rate_at_its_share():
    """Foam alive = inflow × lifetime / λ: iterating budget.foam_aging on that population brings
    it to share × budget × fluid particles, and λ never leaves [1, FOAM_AGING_LIMIT]: foam short
    of its share lives its full lifetime, foam fed past any bound ages at most the limit faster."""
    share, budget, n = 1 / 3, 3.0, 1000.0
    target = share * budget * n
    for inflow_life in (2.6 * target, 0.4 * target):
        lam = 1.0
        for _ in range(40):
            lam = B.foam_aging(lam, inflow_life / lam, n, share, budget)
        assert lam >= 1.0
        assert abs(inflow_life / lam - min(inflow_life, target)) < 0.01 * target, (inflow_life, lam)
    lam = 1.0
    for _ in range(40):
        lam = B.foam_aging(lam, 1e3 * target / lam, n, share, budget)
    assert lam == pytest.approx(B.FOAM_AGING_LIMIT)


def test_the_births_kept_are_bounded_and_give_the_type_scales_and_boost_of_all_frames():
    """2000 frames of births at 60 fps (33 s, lifetimes up to a few seconds): budget.born_add keeps
    only the frames younger than the longest lifetime (and the last BOOST_FRAMES), and
    type_scales and birth_boost from them are those from every frame's births."""
    p, dt = _auto(), 1 / 60
    rng = np.random.default_rng(5)
    full, kept = np.zeros((0, 7)), np.zeros((0, 7))
    live, scales = np.array([900.0, 2500.0, 600.0]), np.ones(3)
    horizon = B.longest_life(p, dt)
    for f in range(2000):
        row = [f * dt, *rng.integers(0, 200, 3), *rng.uniform(0.5, 2.0, 3)]
        full = np.concatenate([full, [row]])
        kept = B.born_add(kept, row, p, dt)
        assert len(kept) <= horizon / dt + 2
        if f % 97 == 0 or f == 1999:
            args = (f * dt, live, scales, p.type_multipliers, p.shares, p, dt)
            np.testing.assert_allclose(B.type_scales(kept, *args), B.type_scales(full, *args), rtol=1e-12)
            assert B.birth_boost(kept, scales * [1, 2, 3], p.type_multipliers) == pytest.approx(
                B.birth_boost(full, scales * [1, 2, 3], p.type_multipliers), rel=1e-12)
    assert len(kept) < len(full) / 5


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_top_percentiles_are_np_percentile_bit_for_bit(dtype):
    """budget.top_percentiles (the running 'auto''s τ from up to 262k samples a frame) partitions only the values
    above a bound sampled from them, and interpolates as np.percentile does: the same bits as np.percentile of
    the kept values, for lognormal potentials (a long tail), values with many ties (a bound that falls on a run of
    equal values), a strided column of a history (as percentile_thresholds hands it), counts on both sides of
    TOP_MIN, and percentiles for which the bound is too high (where it partitions everything)."""
    rng = np.random.default_rng(7)
    cases = halves = 0
    for n in (B.TOP_MIN - 1, B.TOP_MIN, 40_000, 100_003, 262_144):
        for kind in ("lognormal", "wide", "ties", "column"):
            if kind == "lognormal":
                values = rng.lognormal(0, 1.5, n).astype(dtype)
            elif kind == "wide":  # neighbours in the tail far apart: the two ways of interpolating round apart
                values = rng.lognormal(0, 8, n).astype(dtype)
            elif kind == "ties":
                values = np.floor(rng.exponential(3.0, n)).astype(dtype)  # a few dozen distinct values
            else:
                values = rng.lognormal(0, 1, (n, 5)).astype(dtype)[:, 2]  # every fifth of an interleaved array
            keep = (rng.random(n) < 0.7) & (values > 0)
            drawn = tuple(rng.uniform(60, 100, 500))  # ranks with fractions over and under a half
            for q in (B.AUTO_PERCENTILES, (50.0, 99.0), (99.99, 100.0), (0.5, 99.0), drawn):
                got = B.top_percentiles(values, keep, q)
                want = np.percentile(values[keep], q)
                assert got.dtype == want.dtype and got.tobytes() == want.tobytes(), (n, kind, q, got, want)
                cases += 1
                halves += int(np.count_nonzero(np.modf((n - 1) * np.array(q) / 100)[0] >= 0.5))
    assert cases == 5 * 4 * 5 and halves > 4000  # numpy's two ways of interpolating, both checked


_PERCENTILE = np.percentile  # NumPy's own, for the expected values (the tests below spy on budget's calls of it)


def _spy_on_partitions(monkeypatch, values: np.ndarray) -> tuple[list, np.ndarray]:
    """(sizes, spied): ``spied`` is ``values`` as an array whose partitions append their sizes to ``sizes``, and
    budget's calls of np.percentile append ("all", size)."""
    sizes: list = []
    real = np.ndarray.partition

    class Spy(np.ndarray):
        def partition(self, kth, *a, **k):
            sizes.append(self.size)
            return real(self, kth, *a, **k)

    monkeypatch.setattr(B.np, "percentile", lambda a, q: (sizes.append(("all", np.size(a))), _PERCENTILE(a, q))[1])
    return sizes, values.view(Spy)


def test_the_top_percentiles_partition_only_the_values_above_their_bound(monkeypatch):
    """The bound is what makes them cheaper: at 262k values and (95, 99.9) about 6 % of them are partitioned, and a
    bound drawn too high falls back to all of them (still the same bits)."""
    rng = np.random.default_rng(3)
    values = rng.lognormal(0, 1, 262_144).astype(np.float32)
    keep = values > 0
    sizes, spied = _spy_on_partitions(monkeypatch, values)
    got = B.top_percentiles(spied, keep, B.AUTO_PERCENTILES)
    assert got.tobytes() == _PERCENTILE(values[keep], B.AUTO_PERCENTILES).tobytes()
    sample, parted = sizes  # the even sample for the bound, then the values above it; np.percentile not called
    assert sample <= 2 * B.TOP_SAMPLE and 0.05 * len(values) < parted < 0.08 * len(values), sizes
    sizes.clear()
    monkeypatch.setattr(B, "TOP_MARGIN", -0.02)  # a bound above the 95th percentile's rank
    got = B.top_percentiles(values, keep, B.AUTO_PERCENTILES)
    assert got.tobytes() == _PERCENTILE(values[keep], B.AUTO_PERCENTILES).tobytes()
    assert sizes == [("all", len(values))]


def test_the_top_percentiles_bound_holds_for_values_in_lattice_order(monkeypatch):
    """A frame's particles lie in lattice or cell order, so a potential can repeat with the lattice's period. A
    sample of every k-th value then reads one phase of it: here, where the period is a power of two, only the
    fastest row, whose bound lies above the 95th percentile, and all the values were partitioned. The sample at
    pseudo-random places bounds them as it does shuffled values: about 6 % partitioned, the same bits."""
    rng = np.random.default_rng(11)
    n, period = 1 << 20, 64  # every 256th value (n // TOP_SAMPLE) is in the same phase of the period
    row = np.linspace(0.0, 4.0, period) ** 2  # a shear flow: E_k rising across each row of the lattice
    values = (np.tile(row[::-1], n // period) * rng.uniform(0.99, 1.01, n)).astype(np.float32)
    keep = values > 0
    sizes, spied = _spy_on_partitions(monkeypatch, values)
    got = B.top_percentiles(spied, keep, B.AUTO_PERCENTILES)
    assert got.tobytes() == _PERCENTILE(values[keep], B.AUTO_PERCENTILES).tobytes()
    assert ("all", n) not in sizes, "the bound fell above a rank read: every value was partitioned"
    sample, parted = sizes
    assert sample <= B.TOP_SAMPLE and 0.05 * n < parted < 0.08 * n, sizes
