"""'auto': clamping thresholds from the flow itself, multipliers from a budget.

The thresholds τmin, τmax of each potential are percentiles of that potential
over the moving fluid particles (AUTO_PERCENTILES):

- in post-processing, pooled over frames sampled across the whole run, so a
  gentle start is not the scale for a violent middle;
- in the simulation, which cannot look ahead, from the frames so far (a
  bounded history, history_add), and never lower than before: it only rises.

The multipliers k_ta, k_wc, k_vo are the preset's times one scale s, chosen so
that the live diffuse particles peak at ``budget`` per fluid particle with the
per-type multipliers at 1 (a type's multiplier then scales that type alone).
With G_f the particles born in frame f at s = 1,

    G_f    = Σ_i I_k,i (k_ta I_ta,i + k_wc I_wc,i + k_vo I_vo,i) Δt
    N_d(f) = Σ_{f' ≤ f} G_f' S(t_f − t_f')      (S(a): the chance to be alive at age a)
    s      = budget / max_f N_d(f) / N_fluid(f)

Post-processing evaluates N_d on every frame from G interpolated between the
sampled frames; then, frame by frame, with that frame's real G and the survival
corrected by the live count over its prediction (rescale). Both modes lower the
scale of a frame whose births would take the live count past the budget
(within_budget). The simulation cannot: it takes the mean rate over the last
∫S seconds (over the frames since motion began, where fewer) as lasting, and
the highest such estimate so far as the peak (running_peak).
"""

from __future__ import annotations

import functools
import math

import numpy as np

# τmin, τmax of 'auto': these percentiles of each potential over the moving particles.
AUTO_PERCENTILES = (95.0, 99.9)
# A particle counts as moving above this fraction of √(g h), the speed of a gravity
# wave one kernel radius deep: a settled tank's solver jitter stays below it.
MOVING_FRACTION = 0.05
# 'auto' thresholds never fall below this fraction of the preset's, so that still
# water, whose potentials are all noise, still makes nothing.
THRESHOLD_FLOOR = 1.0 / 20.0
# Water entrains air only where it moves faster than about 1 m/s: the inception velocity of
# air entrainment by a plunging jet is 0.8-1.1 m/s (Ervine, McKeogh & Elsawy 1980; Chanson
# 1997). 'auto' never puts the kinetic-energy τmin below ½ of its square, so a settling tank
# (a few tenths of a m/s) stays clear whatever its percentiles.
AIR_ENTRAINMENT_SPEED = 1.0  # [m/s]
# Fewer moving particles with a nonzero potential than this give no percentile.
MIN_SAMPLES = 10
# The simulation's running estimate keeps the potentials of sampled fluid particles in at most
# HISTORY_ROWS rows of HISTORY_SAMPLE each (5 MB), whatever the run's length (history_add).
HISTORY_SAMPLE = 4096
HISTORY_ROWS = 64
# Frames post-processing reads ahead, spread evenly over the run, for the thresholds: at
# most SAMPLE_FRAMES and a quarter of the run (at least MIN_SAMPLE_FRAMES), so looking
# ahead costs at most a quarter more neighbour searches and potentials.
SAMPLE_FRAMES = 12
SAMPLE_SHARE = 0.25
MIN_SAMPLE_FRAMES = 3
# Of each frame it samples, the look-ahead takes the potentials of at most this many fluid particles
# (4 × the simulation's HISTORY_SAMPLE, since it samples 3-12 frames where the simulation samples every
# one), in runs of SAMPLE_RUN consecutive ones in the neighbour grid's cell order spread evenly over the
# frame: neighbours, which share the normals their wave crests read (evenly spread single particles each took
# their own neighbours' lists as well; when the lists were built in groups of four, a group too). The
# percentiles then rest on 49k-197k particles whatever the fluid's size. On bench_foam's 98k sequence
# (3 frames) they were within 0.2-1.9 % of all particles' (at most 3 %, runs placed five ways), as close
# as a random sample of as many, where the frames sampled move them by several per cent (a run of 4
# against one of 10 frames: 7 % on τ_ta,max).
LOOK_AHEAD_SAMPLE = 4 * HISTORY_SAMPLE
SAMPLE_RUN = 64


def sample_slots(n: int, m: int) -> np.ndarray:
    """m of the slots 0..n-1 (all where m ≥ n): runs of SAMPLE_RUN consecutive slots, spread evenly, apart."""
    if m >= n:
        return np.arange(n)
    run = min(SAMPLE_RUN, m)
    starts = np.linspace(0, n - run, max(m // run, 1)).astype(np.int64)
    return (starts[:, None] + np.arange(run)).ravel()


def sample_count(frames: int) -> int:
    return int(min(frames, SAMPLE_FRAMES, max(MIN_SAMPLE_FRAMES, math.ceil(SAMPLE_SHARE * frames))))
# Capacity when max_particles is unset and the multipliers are set by hand ('auto' thresholds only): this
# many times the budget's peak, so that an estimate off by the tests' ±50 % (and a wide margin more)
# never saturates.
CAPACITY_HEADROOM = 3.0
# Capacity when 'auto' also sets the multipliers: a frame's births are then cut to the room the budget
# leaves (FoamGenerator._generate), so the live count never passes budget × fluid particles; the margin
# covers the stochastic rounding of the cut limits. Its arrays (about 80 B a row) were 3× that before.
SCALED_HEADROOM = 1.05
def moving_speed(g: float, h: float) -> float:
    return MOVING_FRACTION * math.sqrt(g * h)


def phi(i: np.ndarray, tmin: float, tmax: float) -> np.ndarray:
    """φ(I, τmin, τmax), as kernels.clamp_phi."""
    return (np.minimum(i, tmax) - np.minimum(i, tmin)) / (tmax - tmin)


# top_percentiles: values are pre-selected above a bound read from a sample of TOP_SAMPLE of them at
# pseudo-random places (TOP_SAMPLE_SEED: the same places for the same count), TOP_MARGIN of the values below the
# lowest rank asked for: about 3 standard deviations of the sample's rank error at 4096 values, so the bound is
# almost never too high (then all the values are partitioned, as np.percentile does). Not every k-th value: a
# frame's particles lie in lattice or cell order, where every k-th one may fall in the same phase of the flow
# (the 1 M-particle sloshing block of bench_foam.py: its strided sample put the bound above the 95th percentile
# and its 3 M kinetic energies were partitioned whole, 41 ms). Below TOP_MIN values np.percentile is called as
# it is.
TOP_SAMPLE = 4096
TOP_SAMPLE_SEED = 0x5EED
TOP_MARGIN = 0.01
TOP_MIN = 32768


@functools.lru_cache(maxsize=8)
def _sample_places(n: int) -> np.ndarray:
    """TOP_SAMPLE places among n at random, the same for the same n (made once: a generator's seeding costs 65 µs,
    and the running 'auto' asks for the same history's size four times a frame)."""
    places = np.random.default_rng(TOP_SAMPLE_SEED).integers(0, n, TOP_SAMPLE)
    places.flags.writeable = False
    return places


def top_percentiles(values: np.ndarray, keep: np.ndarray, q: tuple[float, ...]) -> np.ndarray:
    """``np.percentile(values[keep], q)`` (its 'linear' method), the same bits, for percentiles near the top; the
    kept values are numbers (NaN fails every comparison with the bound: percentile_thresholds keeps only v > 0).

    np.percentile partitions all n values for the few order statistics it reads (those at ranks ⌊q (n − 1)⌋ and
    the next, and the largest). Here only the values at or above a bound L are gathered and partitioned, about
    (1 − q_min + TOP_MARGIN) n of them, when at least n − k_min are (k_min the lowest rank read): the values at
    those ranks are then the same. L is the (k_min/n − TOP_MARGIN) quantile of a sample at pseudo-random places;
    where it is too high, the values are partitioned whole. The interpolation is np.percentile's own (numpy's
    _lerp, and its indexes: the float32 difference b − a, then a + (b − a)γ, or b − (b − a)(1 − γ) where γ ≥ ½,
    in float64).
    The simulation's running 'auto' takes τ from up to 262k samples every frame: there the percentiles of the
    four potentials took 9-11 ms a frame of the loop's thread on 2 cores, as much again as the rest of it."""
    n = int(np.count_nonzero(keep))
    if n < TOP_MIN:
        return np.percentile(values[keep], q)
    virtual = (n - 1) * np.asanyarray(np.true_divide(q, 100))  # as numpy's _quantile, its 'linear' method
    prev = np.floor(virtual)
    nxt = prev + 1
    top = virtual >= n - 1  # the largest value (numpy's _get_indexes: index -1, which its γ is taken from)
    prev[top] = nxt[top] = -1
    gamma = virtual - prev
    ranks = np.concatenate([prev, nxt]).astype(np.intp) % n
    k_min = int(ranks.min())
    at_random = _sample_places(len(values))
    sample = values[at_random][keep[at_random]]
    cut = int((k_min / n - TOP_MARGIN) * len(sample))
    if cut > 0:
        sel = keep & (values >= np.partition(sample, cut)[cut])
        m = int(np.count_nonzero(sel))
    if cut <= 0 or m < n - k_min:  # the bound is above a rank read (or too few sampled): all of them
        return np.percentile(values[keep], q)
    sub = values[sel]  # the m largest of the n, ties at the bound included
    at = ranks - (n - m)
    sub.partition(np.unique(at))
    a, b = sub[at[: len(prev)]], sub[at[len(prev):]]
    diff = np.subtract(b, a)
    out = np.asanyarray(np.add(a, diff * gamma))
    np.subtract(b, diff * (1 - gamma), out=out, where=gamma >= 0.5, casting="unsafe", dtype=out.dtype)
    return out


def percentile_thresholds(pots: dict[str, np.ndarray], moving: np.ndarray, base: np.ndarray) -> np.ndarray:
    """τ (8 values: ta, wc, ke, vo min/max) from the moving particles' potentials; ``base`` where too few."""
    tau = base.copy()
    for k, name in enumerate(("ta", "wc", "ke", "vo")):
        pot = pots[name]
        keep = moving & (pot > 0)
        if np.count_nonzero(keep) < MIN_SAMPLES:
            continue
        lo, hi = top_percentiles(pot, keep, AUTO_PERCENTILES)
        tmin = max(float(lo), float(base[2 * k]) * THRESHOLD_FLOOR)
        if name == "ke":
            tmin = max(tmin, 0.5 * AIR_ENTRAINMENT_SPEED**2)
        tau[2 * k] = tmin
        tau[2 * k + 1] = max(float(hi), 2 * tmin)
    return tau


def births(pots: dict[str, np.ndarray], tau: np.ndarray, k: tuple, dt: float) -> np.ndarray:
    """Particles born per fluid particle in one frame with multipliers k (before rounding)."""
    i_k = phi(pots["ke"], tau[4], tau[5])
    return i_k * (k[0] * phi(pots["ta"], tau[0], tau[1]) + k[1] * phi(pots["wc"], tau[2], tau[3])
                  + k[2] * phi(pots["vo"], tau[6], tau[7])) * dt


def birth_rate(pots: dict[str, np.ndarray], tau: np.ndarray, k: tuple, dt: float) -> float:
    """G: particles born in one frame with multipliers k (before rounding)."""
    return float(births(pots, tau, k, dt).sum())


def survival(p, dt: float, ages: np.ndarray) -> np.ndarray:
    """S(a): the chance a new particle is still alive at age a, from the foam lifetime
    (uniform in [lifetime_min, lifetime_max], or up to lifetime_multiplier·Δt) and the
    foam dissipation rate (exponential)."""
    if p.lifetime_multiplier > 0:
        lo, hi = 0.0, p.lifetime_multiplier * dt
    else:
        lo, hi = p.lifetime_min, p.lifetime_max
    if hi <= lo:
        alive = (ages < hi).astype(np.float64)
    else:
        alive = np.clip((hi - ages) / (hi - lo), 0.0, 1.0)
    return alive * np.exp(-p.foam_dissipation * ages)


def longest_life(p, dt: float) -> float:
    """The age [s] from which S is 0: the longest foam lifetime."""
    return p.lifetime_multiplier * dt if p.lifetime_multiplier > 0 else p.lifetime_max


def mean_residence(p, dt: float) -> float:
    """∫S: how long a new particle lives on average [s]."""
    hi = longest_life(p, dt)
    ages = np.arange(0.0, hi + dt, dt)
    return float(survival(p, dt, ages).sum() * dt)


def survived(p, dt: float, ages: np.ndarray) -> np.ndarray:
    """S(a) for ages that may be negative (not yet born: 0)."""
    ages = np.asarray(ages, np.float64)
    return np.where(ages >= 0, survival(p, dt, np.maximum(ages, 0.0)), 0.0)


def survival_matrix(times: np.ndarray, p, dt: float) -> np.ndarray:
    """S(t_f − t_g) for every frame f (rows) and birth frame g (columns). It depends on the
    frame times alone, so a run computes it once, not at every frame."""
    times = np.asarray(times, np.float64)
    return survived(p, dt, times[:, None] - times[None, :])


def predicted_ratio(surv: np.ndarray, rate: np.ndarray, fluid: np.ndarray) -> np.ndarray:
    """N_d(f) / N_fluid(f) for every frame, from the births per frame (``surv``: survival_matrix)."""
    return per_fluid(surv @ rate, fluid)


def per_fluid(n_diffuse: np.ndarray, n_fluid: np.ndarray) -> np.ndarray:
    """N_d / N_fluid per frame; 0 for a frame without fluid (an empty frame of a sequence is no
    peak: dividing its survivors by zero fluid would scale every other frame down to nothing)."""
    n_fluid = np.asarray(n_fluid, np.float64)
    return np.where(n_fluid > 0, n_diffuse / np.maximum(n_fluid, 1), 0.0)


# The model's survival is corrected by the live count over its prediction once it predicts
# at least this many particles, and by no more than a factor CORRECTION_LIMIT either way.
MIN_PREDICTED = 100.0
CORRECTION_LIMIT = 4.0


def rescale(surv, rate, n_fluid, s_past, alive: float, p, s_now: float) -> float:
    """One scale for the whole run, set again before frame k = len(s_past): the births G
    (real up to k, interpolated after) convolved with the survival S, times c, the live count
    after frame k − 1 over what the model predicted for it with the scales used so far;
    s = budget / max_f c N_d(f) / N_fluid(f). The count keeps following the violence (one
    scale, not a controller holding it at the budget) while the model learns how long
    particles really live here. ``surv``: survival_matrix of the frame times."""
    k = len(s_past)
    c = 1.0
    if k > 0:
        model = float(surv[k - 1, :k] @ (s_past * rate[:k]))
        if model >= MIN_PREDICTED:
            c = float(np.clip(alive / model, 1 / CORRECTION_LIMIT, CORRECTION_LIMIT))
    peak = float(per_fluid(surv @ rate, n_fluid).max()) * c
    return p.budget / peak if peak > 0 else s_now


def within_budget(scale: float, births: float, alive: float, n_fluid: float, budget: float) -> float:
    """The scale, lowered where this frame's births (``births`` at scale 1) would take the
    live count past budget × fluid particles: a prediction that ran high is clipped at the
    budget instead of overshooting it. It never raises the scale."""
    room = budget * n_fluid - alive
    if births > 0 and births * scale > room:
        return max(room, 0.0) / births
    return scale


def running_peak(rates: np.ndarray, p, dt: float, frames: int | None = None, counts=None) -> float:
    """The simulation's peak estimate of N_d / N_fluid from the births per frame and fluid
    particle so far (``rates``, oldest first; ``counts``: how many consecutive frames each rate
    stands for, 1 each if not given): max over frames f of the mean rate over the last ∫S/Δt
    frames up to f, times ∫S/Δt. A single violent frame counts for what it is; a rate that
    has held since motion began is taken to hold on, but only until the run ends: with
    ``frames`` from the first of ``rates`` to the last of the run, ∫S is taken over the ages up
    to there (a run shorter than a particle's life never accumulates a full one).

    The births so far, C(x) over the first x frames, are piecewise linear between the bounds
    b_j of the rates' runs of frames, so the window mean (C(x) − C(x − w)) / w is too, with
    breaks where x or x − w is a bound, and C(x)/x (x < w) is monotone between bounds: the
    maximum is at x ∈ {b_j, b_j + w, w}, O(rows) work however many frames the rows stand for."""
    rates = np.asarray(rates, np.float64)
    if not len(rates):
        return 0.0
    counts = np.ones(len(rates)) if counts is None else np.asarray(counts, np.float64)
    span = mean_residence(p, dt) / dt
    if frames is not None:
        span = min(span, float(survival(p, dt, np.arange(0, max(frames, 0) + 1) * dt).sum()))
    w = max(int(round(span)), 1)
    b = np.concatenate([[0.0], np.cumsum(counts)])
    c = np.concatenate([[0.0], np.cumsum(rates * counts)])
    x = np.unique(np.clip(np.concatenate([b[1:], b[1:] + w, [w]]), 1, b[-1]))
    first = np.maximum(x - w, 0)
    mean = (np.interp(x, b, c) - np.interp(first, b, c)) / (x - first)
    return float(mean.max() * span)


# The simulation's history of sampled potentials: rows of HISTORY_SAMPLE samples, held as one (5, rows,
# HISTORY_SAMPLE) array: the samples' ta, wc, ke, vo and moving flag, each column's rows one after the other.
# Each row holds ``stride`` consecutive frames, HISTORY_SAMPLE / stride samples of each, so every sample stands
# for the same share of a frame's fluid and pooled percentiles need no weights; the last row fills up one frame
# at a time. When HISTORY_ROWS rows are full, neighbouring rows merge in pairs (every other sample of each: still
# an even spread over the fluid of each frame) and the stride doubles. Memory and the work per frame stay
# bounded; the time resolution of old frames coarsens to stride = 2^k ≤ 2 frames / HISTORY_ROWS.
# Column by column, because every frame pools each column over the whole history for its percentiles (a view:
# history_columns) and sums each row's births (history_rates): with the samples' five values side by side (rows of
# (HISTORY_SAMPLE, 5), before 2026-11-28) each of those passes read every fifth value, and the pool was a copy.
def history_empty() -> tuple[np.ndarray, np.ndarray, int]:
    """(rows, frames per row, stride): no frame yet."""
    return np.zeros((5, 0, HISTORY_SAMPLE), np.float32), np.zeros(0, np.int64), 1


def history_per_frame(stride: int) -> int:
    """Fluid particles sampled from a frame while the history keeps one row per ``stride`` frames."""
    return max(HISTORY_SAMPLE // stride, 1)


def history_add(rows: np.ndarray, frames: np.ndarray, stride: int, frame_sample) -> tuple[np.ndarray, np.ndarray, int]:
    """The history with one frame more (new arrays: a checkpoint may still hold the old ones);
    ``frame_sample(m)``: that frame's (m, 5) samples (ta, wc, ke, vo, moving), evenly spread."""
    per = history_per_frame(stride)
    if not len(frames) or frames[-1] >= stride:
        rows = np.concatenate([rows, np.zeros((5, 1, HISTORY_SAMPLE), np.float32)], axis=1)
        frames = np.concatenate([frames, [0]]).astype(np.int64)
    else:
        rows, frames = rows.copy(), frames.copy()
    k = int(frames[-1])
    rows[:, -1, k * per:(k + 1) * per] = np.asarray(frame_sample(per)).T
    frames[-1] += 1
    if len(frames) == HISTORY_ROWS and frames[-1] == stride:
        rows = np.concatenate([rows[:, 0::2, 0::2], rows[:, 1::2, 0::2]], axis=2)
        frames, stride = frames[0::2] + frames[1::2], 2 * stride
    return rows, frames, stride


def history_columns(rows: np.ndarray, frames: np.ndarray, stride: int) -> np.ndarray:
    """All samples kept, each standing for the same share of a frame, column by column: (5, samples) (ta, wc, ke,
    vo, moving), the rows' samples in order, the last row's as far as it is filled; a view of ``rows``."""
    if not len(frames):
        return np.zeros((5, 0), np.float32)
    filled = (len(frames) - 1) * HISTORY_SAMPLE + int(frames[-1]) * history_per_frame(stride)
    return np.ascontiguousarray(rows).reshape(5, -1)[:, :filled]


def history_rates(
    rows: np.ndarray, frames: np.ndarray, stride: int, tau: np.ndarray, k: tuple, dt: float,
) -> np.ndarray:
    """Each row's births per frame and fluid particle (its frames' mean) with thresholds τ now."""
    if not len(frames):
        return np.zeros(0)
    per = history_per_frame(stride)
    pots = {"ta": rows[0], "wc": rows[1], "ke": rows[2], "vo": rows[3]}  # (rows, samples)
    # the last row's unfilled tail holds zero potentials, which make no births (φ(0, τmin, τmax) = 0 for τ ≥ 0)
    return births(pots, tau, k, dt).sum(axis=1).astype(np.float64) / (frames * per)


def history_from_rows(rows: np.ndarray) -> np.ndarray:
    """A checkpoint's history rows in this layout, (5, rows, HISTORY_SAMPLE): those written before 2026-11-28 are
    (rows, HISTORY_SAMPLE, 5)."""
    rows = np.asarray(rows, np.float32)
    if rows.ndim == 3 and rows.shape[1:] == (HISTORY_SAMPLE, 5):
        return np.ascontiguousarray(rows.transpose(2, 0, 1))
    return rows


# Capacity of the explicit presets, whose count no budget bounds (as before budgets).
PRESET_CAPACITY = 400_000


def capacity_for(p, n_fluid: int) -> int:
    if p.max_particles is not None:
        return p.max_particles
    if not p.auto:
        return PRESET_CAPACITY
    scaled = not ({"k_ta", "k_wc", "k_vo"} & p.explicit)  # as FoamGenerator._scaled
    return int(math.ceil((SCALED_HEADROOM if scaled else CAPACITY_HEADROOM) * p.budget * max(n_fluid, 1))) + 1000


# Per-type shares of the budget. A type's particles are born where its new particles land
# (spray above the surface, bubbles inside), live as long as their own motion lets them and
# turn into another type where they go (spray that lands is foam), so how the live particles
# split is a property of the flow: 'auto' measures it and scales each type's generation so that
# type t makes up share_t of the live particles.
# A type's scale stays within [1/TYPE_SCALE_LIMIT, TYPE_SCALE_LIMIT] (the DualSPHysics dam
# break's spray needs ~15), is set once the survival model predicts MIN_PREDICTED particles,
# and moves halfway (geometrically) towards its target each frame, since a type's scale also
# changes what the others receive from it.
TYPE_SCALE_LIMIT = 100.0
TYPE_SCALE_STEP = 0.5


def type_scales(born, t_now: float, live, scales, mult, shares, p, dt: float) -> np.ndarray:
    """The scale c_t of each type's generation. ``born``: per frame so far, (time, new spray,
    foam, bubbles, and the c_t they were made with); ``live``: each type's particles alive at
    ``t_now``. With S the survival model, B_t = Σ_f S(t_now − t_f) born_t(f) is what type t
    would hold if its particles stayed what they were born as, U_t the same at c_t m_t = 1.
    Type t is φ_t = U_t / Σ U of the births at unit scales, and its particles outlive the
    average by ρ_t = (live_t / B_t) / (Σ live / Σ B), so c_t = share_t / (φ_t ρ_t) makes it
    share_t of the live particles, and Σ_t c_t φ_t ρ_t = 1: the total is what the common
    scale makes it."""
    born = np.asarray(born, np.float64).reshape(-1, 7)
    live, scales = np.asarray(live, np.float64), np.asarray(scales, np.float64)
    mult, shares = np.asarray(mult, np.float64), np.asarray(shares, np.float64)
    on = (mult > 0) & (shares > 0)
    age = t_now - born[:, 0]
    w = survived(p, dt, age)[:, None]
    made = (w * born[:, 1:4]).sum(0)
    if made[on].sum() < MIN_PREDICTED or live[on].sum() <= 0:
        return scales
    unit = (w * born[:, 1:4] / np.maximum(born[:, 4:7] * mult, 1e-30)).sum(0)
    phi_ = np.where(on, unit, 0.0) / max(unit[on].sum(), 1e-30)
    rho = np.where(made > 0, live / np.maximum(made, 1e-30), 0.0) / (live[on].sum() / made[on].sum())
    f = phi_ * rho
    target = np.where(f > 0, shares / np.maximum(f, 1e-30), TYPE_SCALE_LIMIT)
    target = np.clip(target, 1 / TYPE_SCALE_LIMIT, TYPE_SCALE_LIMIT)
    new = scales ** (1 - TYPE_SCALE_STEP) * target ** TYPE_SCALE_STEP
    return np.where(on, new, scales)


# Frames whose births give the split of the births now (birth_boost).
BOOST_FRAMES = 10


def born_add(born, row, p, dt: float) -> np.ndarray:
    """``born`` (as in type_scales) with this frame's ``row``, less the frames no longer needed:
    those at least the longest lifetime old, whose S is 0 now and stays 0 as ages only grow,
    beyond the last BOOST_FRAMES (birth_boost). Memory and the work per frame stay bounded."""
    born = np.concatenate([np.asarray(born, np.float64).reshape(-1, 7), [row]])
    keep = born[-1, 0] - born[:, 0] < longest_life(p, dt)
    keep[-BOOST_FRAMES:] = True
    return born[keep]


def birth_boost(born, scales, mult) -> float:
    """Σ_t c_t φ_t: the births with the type scales c_t over those at c = 1, φ_t being type t's
    part of the births at unit scales over the last BOOST_FRAMES frames (``born`` as in
    type_scales). within_budget takes the births times this, so a type scaled far up (spray
    that lands turns into foam) cannot take the live count past the budget."""
    b = np.asarray(born, np.float64).reshape(-1, 7)[-BOOST_FRAMES:]
    mult = np.asarray(mult, np.float64)
    on = mult > 0
    unit = np.where(on, (b[:, 1:4] / np.maximum(b[:, 4:7] * mult, 1e-30)).sum(0), 0.0)
    if unit.sum() <= 0:
        return 1.0
    return float((np.asarray(scales, np.float64) * unit).sum() / unit.sum())


# Foam is fed by the other types (spray that lands, bubbles that surface turn into foam and keep
# the lifetime they were born with), so where foam holds more than its share with its own births
# already scaled down, fewer births cannot bring it back: its particles' lifetimes count down
# faster instead, by a factor λ ≥ 1 (foam_aging). Foam's population is its inflow times how long
# it lives, so λ = live / target holds it at its share in steady flow; λ moves there halfway
# (geometrically) each frame, as the type scales do, never below 1 (the preset's lifetimes are
# the longest foam lives) nor above FOAM_AGING_LIMIT (lifetimes of 2-5 s no shorter than 0.2-0.5 s).
FOAM_AGING_LIMIT = 10.0


def foam_aging(aging: float, live_foam: float, n_fluid: float, share: float, budget: float) -> float:
    """λ, how many times faster foam's lifetime counts down than the clock, so that the live foam
    heads for ``share`` × ``budget`` × ``n_fluid`` (its part of the budget)."""
    target = share * budget * n_fluid
    if target <= 0 or live_foam <= 0:
        return max(1.0, aging ** (1 - TYPE_SCALE_STEP))
    new = aging ** (1 - TYPE_SCALE_STEP) * (live_foam / target * aging) ** TYPE_SCALE_STEP
    return float(np.clip(new, 1.0, FOAM_AGING_LIMIT))
