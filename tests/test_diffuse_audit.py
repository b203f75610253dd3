"""Diffuse-particle checks that catch realistic one-line bugs the other tests let through
(scripts/mutation_audit.py): the budget's room and the particles alive, 'auto' and the values
a user set, the survival model and running peak against their definitions, and the type of a
particle with exactly the threshold number of fluid neighbours."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from whitecap.config import Foam
from whitecap.diffuse import budget as B
from whitecap.diffuse.params import resolve

DT = 1 / 30


def _auto(**kw):
    return resolve(Foam(preset="auto", **kw))


# ---------------------------------------------------------------- the budget
def test_births_never_take_the_live_count_past_the_budget():
    """within_budget: whatever the particles alive, a frame's births at the scale it returns leave
    at most budget × fluid particles alive (or the count as it was, when already past); the scale
    is never raised, and left alone where the births fit."""
    budget = 3.0
    for scale, births, alive, n_fluid in itertools.product((0.5, 1.0, 4.0), (0.0, 10.0, 500.0, 5000.0),
                                                           (0.0, 1000.0, 2900.0, 2990.0, 3500.0), (1000.0,)):
        s = B.within_budget(scale, births, alive, n_fluid, budget)
        assert 0.0 <= s <= scale
        assert alive + births * s <= max(budget * n_fluid, alive) + 1e-9, (scale, births, alive, s)
        if alive + births * scale <= budget * n_fluid:
            assert s == scale
    # 2990 alive of a budget of 3000: room for 10 of the 100 births
    assert B.within_budget(1.0, 100.0, 2990.0, 1000.0, budget) == pytest.approx(0.1)


def test_more_particles_alive_than_predicted_lower_the_scale():
    """rescale: when the live count is twice what the survival model predicted for the scales used
    (particles live longer here than the model thinks), the corrected peak is twice as high and the
    scale half; half as many alive, twice the scale."""
    p = _auto()
    times = np.arange(60) * DT
    surv = B.survival_matrix(times, p, DT)
    rate = np.full(60, 50.0)  # births per frame at scale 1
    n_fluid = np.full(60, 1000.0)
    s_past = np.ones(10)
    model = float(surv[9, :10] @ (s_past * rate[:10]))
    assert model >= B.MIN_PREDICTED
    nominal = B.rescale(surv, rate, n_fluid, s_past, model, p, 1.0)
    assert nominal == pytest.approx(p.budget / B.predicted_ratio(surv, rate, n_fluid).max())
    assert B.rescale(surv, rate, n_fluid, s_past, 2 * model, p, 1.0) == pytest.approx(nominal / 2)
    assert B.rescale(surv, rate, n_fluid, s_past, 0.5 * model, p, 1.0) == pytest.approx(nominal * 2)


def test_the_survival_model_is_the_lifetime_distribution():
    """S(a), the chance a new particle is alive at age a: lifetimes uniform in [min, max] and foam
    dissipation at rate k give S = 1·e^(−ka) up to the shortest life, then (max − a)/(max − min)·e^(−ka),
    0 from the longest; ∫S is the mean residence time."""
    p = _auto()
    lo, hi, k = p.lifetime_min, p.lifetime_max, p.foam_dissipation
    assert 0 < lo < hi and k > 0
    ages = np.array([0.0, 0.5 * lo, lo, 0.5 * (lo + hi), 0.9 * hi, hi, 2 * hi])
    want = np.array([1.0, np.exp(-k * 0.5 * lo), np.exp(-k * lo), 0.5 * np.exp(-k * 0.5 * (lo + hi)),
                     (hi - 0.9 * hi) / (hi - lo) * np.exp(-k * 0.9 * hi), 0.0, 0.0])
    assert B.survival(p, DT, ages) == pytest.approx(want, abs=1e-12)
    a = np.linspace(0.0, hi, 200001)
    exact = float(np.sum(B.survival(p, DT, a)) * (a[1] - a[0]))
    assert B.mean_residence(p, DT) == pytest.approx(exact, abs=DT)  # a sum over frame ages: within a frame


def test_one_violent_frame_counts_for_its_own_births():
    """running_peak: a single frame that makes R particles (all alive right after), a particle
    lifetime after motion began, peaks at R, within the rounding of the window to whole frames; a
    rate held over many frames peaks at rate × ∫S/Δt. (A burst in the first frames counts as a rate
    that has held since motion began: the simulation cannot tell the two apart.)"""
    p = _auto()
    span = B.mean_residence(p, DT) / DT
    w = round(span)
    for before in (w, w + 7, 3 * w):
        rates = np.zeros(before + 150)
        rates[before] = 1000.0
        assert B.running_peak(rates, p, DT) == pytest.approx(1000.0, rel=0.5 / w), before
    assert B.running_peak(np.full(400, 3.0), p, DT) == pytest.approx(3.0 * span, rel=1e-9)


def test_phi_clamps_below_the_lower_threshold_and_above_the_upper():
    """φ(I, τmin, τmax): 0 up to τmin, linear to 1 at τmax, 1 beyond (never negative)."""
    i = np.array([0.0, 1.0, 2.0, 3.5, 5.0, 9.0])
    assert B.phi(i, 2.0, 5.0) == pytest.approx([0.0, 0.0, 0.0, 0.5, 1.0, 1.0])


# ---------------------------------------------------------------- 'auto' and what the user set
def _violent_frames(n=3, r=0.01):
    """Blocks of water stirred violently (a swirl and noise), as ParticleFrames with times."""
    from whitecap.io import ParticleFrame

    ax = [np.arange(r, 0.3, 2 * r), np.arange(r, 0.2, 2 * r), np.arange(r, 0.24, 2 * r)]
    x = (np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3) + 0.2).astype(np.float32)
    rng = np.random.default_rng(0)
    d = x - x.mean(0)
    out = []
    for k in range(n):
        v = 6.0 * np.stack([d[:, 2], np.zeros(len(x)), -d[:, 0]], 1) + rng.normal(0, 0.5, x.shape)
        out.append(ParticleFrame(x, v.astype(np.float32), np.arange(len(x), dtype=np.uint32), time=k * DT))
    return out


def _calibrated(p):
    from whitecap.diffuse.generator import FoamGenerator

    gen = FoamGenerator(p, 0.01, ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]), (0.0, 0.0, -9.81), seed=1)
    frames = _violent_frames()
    gen.calibrate(frames, np.array([f.time for f in frames]), np.array([len(f) for f in frames], float), DT)
    return gen


def test_auto_keeps_the_multipliers_a_user_set_and_scales_the_others():
    """'auto' with k_ta and k_wc set in [foam]: those multipliers are used as given, whatever the
    budget; without them, the budget scales the preset's (control: it does, on the same frames)."""
    mine = [_calibrated(_auto(k_ta=400.0, k_wc=4000.0, budget=b)) for b in (1.0, 2.0)]
    for gen in mine:
        assert gen.multipliers() == pytest.approx((400.0, 4000.0, gen.p.k_vo))
        assert not np.allclose(gen.thresholds(), gen.base_thresholds())  # 'auto' chose the thresholds
    scaled = [_calibrated(_auto(budget=b)) for b in (1.0, 2.0)]
    k1, k2 = scaled[0].multipliers()[0], scaled[1].multipliers()[0]
    assert k2 == pytest.approx(2 * k1, rel=1e-6) and k1 != pytest.approx(scaled[0].p.k_ta)


def test_auto_keeps_thresholds_set_in_an_ini_file(tmp_path):
    """Thresholds a DiffuseCalculator .ini sets are explicit: 'auto' picks the others from the flow
    and keeps these (control: without the file, 'auto' picks all of them)."""
    ini = tmp_path / "case.ini"
    ini.write_text("[DiffuseCalculator]\nTaMin = 3\nTaMax = 12\n")
    gen = _calibrated(resolve(Foam(preset="auto"), ini=ini))
    tau = gen.thresholds()
    assert tau[0] == pytest.approx(3.0) and tau[1] == pytest.approx(12.0)
    free = _calibrated(_auto()).thresholds()
    assert not np.allclose(free[:2], [3.0, 12.0]) and np.allclose(tau[2:], free[2:])


# ---------------------------------------------------------------- the type of a diffuse particle
def test_the_type_follows_the_fluid_neighbour_count_at_its_thresholds():
    """Spray: fewer than spray_below fluid neighbours; bubble: more than bubble_above; foam
    otherwise, the thresholds themselves included. Checked on points whose counts are exact (no
    fluid particle within 1e-4 h of the support's edge), among which every count from 0 to past
    bubble_above occurs, both thresholds too."""
    import taichi as ti

    from whitecap.diffuse import kernels as K
    from whitecap.diffuse.generator import FoamGenerator, _nd
    from whitecap.io import ParticleFrame

    r = 0.01
    n = 8
    g = np.arange(n) * 2 * r
    x = (np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + 0.1).astype(np.float32)
    x += np.random.default_rng(7).uniform(-0.05 * r, 0.05 * r, x.shape).astype(np.float32)
    fr = ParticleFrame(positions=x, velocities=np.zeros_like(x), ids=np.arange(len(x), dtype=np.uint32))
    p = resolve(preset="ihmsen2012")
    lo, hi = x.min(0) - 1.0, x.max(0) + 1.0
    gen = FoamGenerator(p, r, (lo, hi), (0, 0, -9.81), seed=3)
    *_, args = gen._prepare(fr, len(fr))
    rng = np.random.default_rng(11)
    pts = (x.min(0) - 3 * r + rng.random((6000, 3)) * (x.max(0) - x.min(0) + 6 * r)).astype(np.float32)
    h = gen.h
    dist = np.linalg.norm(pts[:, None, :].astype(np.float64) - x[None].astype(np.float64), axis=2)
    clear = (np.abs(dist - h) > 1e-4 * h).all(1)
    pts, count = pts[clear], (dist[clear] < h).sum(1)
    assert {p.spray_below - 1, p.spray_below, p.bubble_above, p.bubble_above + 1} <= set(count.tolist())
    kd = ti.ndarray(ti.i32, len(pts))
    K.classify(len(pts), _nd(pts, ti.f32, True), *args, p.spray_below, p.bubble_above, ti.math.vec3(*lo),
               ti.math.vec3(*hi), 0, kd)
    want = np.where(count < p.spray_below, 0, np.where(count > p.bubble_above, 2, 1))
    got = kd.to_numpy()[: len(pts)]
    bad = np.flatnonzero(got != want)
    assert not len(bad), [(int(count[b]), int(got[b])) for b in bad[:10]]
