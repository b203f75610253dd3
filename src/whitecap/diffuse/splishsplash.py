"""SPlisHSPlasH FoamGenerator's default (automatic) mode, behind the ``splishsplash`` preset.

FoamGenerator (SPlisHSPlasH, Tools/FoamGenerator; Ihmsen et al. 2012 with the
automatic configuration of Bender et al. 2019) reads the sequence twice:

1. For every frame it takes the largest trapped-air potential, wave-crest
   potential and kinetic energy of any fluid particle. The mean of these
   per-frame maxima over all frames, Ī, sets the clamping limits
   τmin = 0.1 Ī, τmax = Ī (:func:`limits_from_maxima`).
2. It generates n_d = ⌊foamscale · I_k (k_ta I_ta + k_wc I_wc) Δt + ½⌋
   particles per fluid particle, with k_ta = k_wc = 1 and foamscale = 1000,
   only for fluid particles with at least 15 neighbours.

Its potentials use the cubic spline kernel of support 4r weighted by an SPH
volume m/ρ, with the particle mass m = 0.8 (2r)³ ρ0, ρ0 = 1000 kg/m³; normals
from the colour-field gradient exist only for particles with at most 20
neighbours; the kinetic energy is ½ m |v|² in joules; and a new particle
lives τ = l_min + (I_k / τmax_k) X (l_max − l_min) seconds, X uniform in [0, 1).

Two of its rules are reproduced as FoamGenerator has them, because they set its
counts (measured on ../shared/data/splishsplash_rigid, see benchmarks/RESULTS.md):

- *Row volumes.* The trapped-air and wave-crest sums weight their k-th
  neighbour term by m/ρ of row k of the frame (its loop reads ``densities[j]``
  with j counting the neighbours), not by the neighbour's own volume. The
  weights are thus the volumes of the frame's first N rows (N the particle's
  neighbour count), and the counts depend on the row order of the input; on the
  shared case this doubles them against the neighbours' own volumes. Which
  term gets which of those weights follows the order of its neighbour search's
  lists, which is arbitrary; we give every term their mean,
  V̄_N = (1/N) Σ_{k<N} m/ρ_k (its expected value over list orders), so the
  result does not depend on how our own grid orders a neighbour list.
- *Wall correction.* A diffuse particle classified as foam within the support
  radius h of a face of the bounding box has its fluid-neighbour count raised
  by ⌈N · V_cap(1 − d/h)⌉ per face, V_cap(a) = π a² (3 − a) / 3 (a unit-sphere
  cap of height a), and becomes a bubble once it exceeds 20. FoamGenerator
  applies it against ``--bbsize``; whitecap always has a domain, which plays
  ``--bbsize … --bbtype kill`` (what leaves it is removed).

The vorticity generator needs the fluid's angular velocity (micropolar
solvers); without it FoamGenerator leaves it off, and so does this preset.
"""


import math

import numpy as np
import taichi as ti

from ..sim.grid import F1, F3, I1, I2, vec3
from ..sim.smoothing import cubic_spline, cubic_spline_grad
from .params import FOAMSCALE  # noqa: F401  (re-exported: the mode's numbers in one place)

# The numbers FoamGenerator's automatic mode runs with (its main.cpp and --help);
# FOAMSCALE (--foamscale, 1000) lives with the presets in .params.
LIMIT_MIN_FRACTION = 0.1  # τmin = 0.1 × the mean per-frame maximum, τmax = that mean
MIN_NEIGHBOURS = 15  # fluid particles with fewer neighbours generate nothing
NORMAL_MAX_NEIGHBOURS = 20  # only particles with at most this many neighbours get a normal
MASS_FACTOR = 0.8  # m = 0.8 (2r)³ ρ0
REST_DENSITY = 1000.0  # ρ0 [kg/m³]
CREST_MOTION_COS = 0.6  # δ_vn: v̂·n̂ ≥ 0.6 (Ihmsen et al. 2012, Eq. 7)
# Still water: the kinetic-energy limit τmax_k never drops below ½ m u², u = ENTRAINMENT_SPEED,
# about the slowest plunging jet that entrains air (experiments put the onset near 0.8–1 m/s,
# e.g. Ervine, McKeogh & Elsawy 1980), so the jitter of a resting tank is not scaled up to foam.
# FoamGenerator itself has no such floor (on exactly still water it divides 0 by 0); only a
# sequence whose mean per-frame top speed stays below u is affected.
ENTRAINMENT_SPEED = 1.0  # [m/s]
TINY = 1e-20  # keeps τmax > τmin when a potential is zero in every frame (then I = 0)


@ti.func
def wall_corrected_count(p: vec3, cnt: ti.i32, lo: vec3, hi: vec3, h: ti.f32, bubble_above: ti.i32) -> ti.i32:
    """FoamGenerator's correction of a foam particle's fluid-neighbour count N near the
    bounding box: per face within h (distance d), N += ⌈N V_cap(1 − d/h)⌉ with
    V_cap(a) = π a² (3 − a) / 3, the faces taken x, y, z (lower, then upper), stopping
    once N > bubble_above. FoamGenerator adds the unit-sphere cap's volume, not its
    fraction of the sphere (4π/3), and so do we."""
    c = cnt
    done = 0
    for j in ti.static(range(3)):
        if not done:
            for side in ti.static(range(2)):
                d = ti.abs(p[j] - (lo[j] if side == 0 else hi[j]))
                if d < h:
                    a = 1.0 - d / h
                    c += ti.cast(ti.ceil(c * (a * a * (math.pi / 3.0) * (3.0 - a))), ti.i32)
            if c > bubble_above:
                done = 1
    return c


def particle_mass(radius: float) -> float:
    """FoamGenerator's particle mass m = 0.8 (2r)³ ρ0 [kg]."""
    return MASS_FACTOR * (2.0 * radius) ** 3 * REST_DENSITY


@ti.kernel
def sph_density(n: ti.i32, x: F3, nb_count: I1, nb: I2, h: ti.f32, m: ti.f32, rho: F1):
    """ρ_i = m W(0) + Σ_j m W(|x_ij|), cubic spline of support h."""
    for i in range(n):
        d = m * cubic_spline(0.0, h)
        for k in range(nb_count[i]):
            d += m * cubic_spline((x[i] - x[nb[i, k]]).norm(), h)
        rho[i] = d


@ti.kernel
def surface_normals(n: ti.i32, x: F3, nb_count: I1, nb: I2, h: ti.f32, m: ti.f32, rho: F1, normal: F3):
    """n̂_i = −Σ_j (m/ρ_j) ∇W(x_ij), normalised, for particles with at most
    NORMAL_MAX_NEIGHBOURS neighbours; zero for the others."""
    for i in range(n):
        g = vec3(0.0)
        if nb_count[i] <= NORMAL_MAX_NEIGHBOURS:
            for k in range(nb_count[i]):
                j = nb[i, k]
                g -= m / rho[j] * cubic_spline_grad(x[i] - x[j], h)
        gl = g.norm()
        normal[i] = g / gl if gl > 0.0 else vec3(0.0)


@ti.kernel
def potentials(
    n: ti.i32, x: F3, v: F3, nb_count: I1, nb: I2, h: ti.f32, m: ti.f32, row_volume: F1, normal: F3,
    v_diff: F1, crest: F1, energy: F1,
):
    """FoamGenerator's potentials: v_diff = Σ_k V_k |v_ij| (1 − v̂_ij·x̂_ij) W,
    κ = δ_vn Σ_k V_k (1 − n̂_i·n̂_j) W over neighbours behind the surface (x̂_ij·n̂_i > 0),
    E = ½ m |v_i|², every term weighted by FoamGenerator's row volume V̄_N = ``row_volume[N]``,
    the mean of m/ρ_k over the frame's first N rows, N = the neighbour count of i (see the
    module docstring: its loop indexes the densities by the neighbour counter)."""
    for i in range(n):
        vd = 0.0
        kappa = 0.0
        ni = normal[i]
        for k in range(nb_count[i]):
            j = nb[i, k]
            xij = x[i] - x[j]
            r = xij.norm()
            w = cubic_spline(r, h)
            vol = row_volume[nb_count[i]]  # FoamGenerator's rows, not the neighbour's own m/ρ_j
            xh = xij / r if r > 0.0 else vec3(0.0)
            vij = v[i] - v[j]
            vl = vij.norm()
            vh = vij / vl if vl > 1e-6 else vij
            vd += vol * vl * (1.0 - vh.dot(xh)) * w
            if xh.dot(ni) > 0.0:
                kappa += vol * (1.0 - ni.dot(normal[j])) * w
        vi = v[i]
        sl = vi.norm()
        if sl == 0.0 or (vi / sl).dot(ni) < CREST_MOTION_COS:
            kappa = 0.0
        v_diff[i] = vd
        crest[i] = kappa
        energy[i] = 0.5 * m * vi.norm_sqr()


def row_volumes(rho: np.ndarray, m: float) -> ti.ndarray:
    """V̄_N = (1/N) Σ_{k<N} m/ρ_k for N = 0 … n (0 for N = 0): the mean volume of the frame's
    first N rows, FoamGenerator's weight for a particle with N neighbours."""
    cum = np.concatenate([[0.0], np.cumsum(m / rho.astype(np.float64))])
    vbar = cum / np.maximum(np.arange(len(cum)), 1)
    out = ti.ndarray(ti.f32, len(vbar))
    out.from_numpy(vbar.astype(np.float32))
    return out


def frame_potentials(gen, fx, fv, n: int):
    """(v_diff, κ, E) ndarrays of a prepared frame (``gen._prepare`` built the neighbour lists)."""
    g = gen.grid
    mm = max(n, 1)
    m = particle_mass(gen.r)
    rho, v_diff, crest, energy = (ti.ndarray(ti.f32, mm) for _ in range(4))
    normal = ti.Vector.ndarray(3, ti.f32, mm)
    sph_density(n, fx, g.nb_count, g.nb, gen.h, m, rho)
    surface_normals(n, fx, g.nb_count, g.nb, gen.h, m, rho, normal)
    potentials(n, fx, fv, g.nb_count, g.nb, gen.h, m, row_volumes(rho.to_numpy()[:n], m), normal, v_diff, crest, energy)
    return v_diff, crest, energy


def frame_maxima(gen, frame) -> np.ndarray:
    """Pass 1 for one frame: the largest (v_diff, κ, E) of any fluid particle."""
    n = len(frame)
    if n == 0:
        return np.zeros(3)
    fx, fv, _, _ = gen._prepare(frame, n)
    return np.array([a.to_numpy()[:n].max() for a in frame_potentials(gen, fx, fv, n)], np.float64)


def limits_from_maxima(maxima: np.ndarray, radius: float) -> np.ndarray:
    """τ (8 values: ta, wc, ke, vo as min/max pairs) from the per-frame maxima (frames × 3 of
    v_diff, κ, E): τmax = the mean over frames, τmin = LIMIT_MIN_FRACTION τmax; vorticity off."""
    mean = np.asarray(maxima, np.float64).reshape(-1, 3).mean(axis=0)
    mean[2] = max(mean[2], 0.5 * particle_mass(radius) * ENTRAINMENT_SPEED**2)
    mean = np.maximum(mean, 2 * TINY)
    tau = np.empty(8, np.float64)
    tau[0:6:2] = LIMIT_MIN_FRACTION * mean
    tau[1:6:2] = mean
    tau[6:8] = (1.0, 2.0)  # vorticity: unused (k_vo = 0)
    return tau.astype(np.float32)


def lifetimes(life01: np.ndarray, i_k: np.ndarray, ke_max: float, lo: float, hi: float) -> np.ndarray:
    """τ = l_min + (I_k / τmax_k) X (l_max − l_min) from X = ``life01`` (FoamGenerator's rule:
    I_k ∈ [0, 1] divided by the energy limit in joules)."""
    return (lo + i_k / ke_max * life01 * (hi - lo)).astype(np.float32)
