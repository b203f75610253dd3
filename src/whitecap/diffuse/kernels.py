"""Taichi kernels of the diffuse-particle model (Ihmsen et al. 2012).

Symbols follow the paper: x_ij = x_i − x_j, v_ij = v_i − v_j, the radially
symmetric weight W̃(x_ij, h) = 1 − |x_ij|/h, the clamping function
φ(I, τmin, τmax) and the potentials I_ta (trapped air), I_wc (wave crest),
I_k (kinetic energy) and, optionally, I_vo (vorticity).

Random numbers are a counter-based hash of (seed, frame, particle id, slot,
draw), so generation is parallel per fluid particle and bit-reproducible
whatever the thread count.
"""

import math
from typing import Any

import taichi as ti

from ..io.diffuse_types import BUBBLE, FOAM, SPRAY
from ..sim.grid import F1, F3, I1, I2, U1, GridQuery, for_each_neighbor, vec3
from ..sim.launch import TEMPLATE
from ..sim.obstacles import FAR, IV, M3, sdf_sample
from ..sim.pbf import padded_count
from . import splishsplash as SP

# Kernel argument annotations (typed Any: Taichi's annotations are not Python types).
B1: Any = ti.types.ndarray(dtype=ti.i8, ndim=1)  # a diffuse type per particle (or NOT_KEPT)
F2: Any = ti.types.ndarray(dtype=ti.f32, ndim=2)
U8: Any = ti.types.ndarray(dtype=ti.u8, ndim=1)  # the output's diffuse types
N1: Any = ti.types.ndarray(ndim=1)  # of any dtype
COUNTS3: Any = ti.types.vector(3, ti.i32)  # a count per diffuse type (spray, foam, bubbles), returned

# δ_vn of the wave-crest potential: a surface particle counts as a crest only
# while it moves along its normal, v̂_i·n̂_i ≥ this cosine (Ihmsen et al. 2012, Sec. 4.2).
CREST_MOTION_COS = 0.6
# Sampling frame of the generation cylinder: e1 is built from the x axis, or from y
# when v̂ is within acos(0.9) ≈ 26° of x, so the cross product never degenerates.
NEAR_PARALLEL_COS = 0.9


@ti.func
def hash_u32(a: ti.u32) -> ti.u32:
    """An integer avalanche hash (Wellons' lowbias32): each output bit depends on every input bit."""
    a ^= a >> ti.u32(16)
    a *= ti.u32(0x7FEB352D)
    a ^= a >> ti.u32(15)
    a *= ti.u32(0x846CA68B)
    a ^= a >> ti.u32(16)
    return a


@ti.func
def rand01(seed: ti.u32, frame: ti.u32, pid: ti.u32, slot: ti.u32, draw: ti.u32) -> ti.f32:
    """Uniform [0, 1) from the counter (seed, frame, particle id, slot, draw)."""
    h = hash_u32(seed ^ hash_u32(frame ^ hash_u32(pid ^ hash_u32(slot * ti.u32(16) + draw))))
    return ti.cast(h >> ti.u32(8), ti.f32) * (1.0 / 16777216.0)


@ti.func
def clamp_phi(i: ti.f32, tmin: ti.f32, tmax: ti.f32) -> ti.f32:
    """φ(I, τmin, τmax) = (min(I, τmax) − min(I, τmin)) / (τmax − τmin)."""
    return (ti.min(i, tmax) - ti.min(i, tmin)) / (tmax - tmin)


@ti.kernel
def fluid_potentials(
    n: ti.i32,
    x: F3,
    v: F3,
    nb_count: I1,
    nb: I2,
    pad: TEMPLATE,
    cap: TEMPLATE,
    h: ti.f32,
    surface_fraction: ti.f32,
    normal: F3,
    surface: I1,
    v_diff: F1,
    e_k: F1,
    vort: F1,
    mark: I1,
    value: ti.i32,
):
    """Per fluid particle: surface normal n̂_i (from the colour-field gradient,
    −∇c ∝ Σ_j x̂_ij W̃), trapped-air v_i^diff = Σ_j |v_ij|(1 − v̂_ij·x̂_ij) W̃,
    kinetic energy per unit mass E_k = ½|v_i|², and |ω_i| ≈ |Σ_j v_ji × x̂_ij W̃|/Σ W̃.
    The neighbour loop runs over the padded list (sim.pbf.padded_count: ``pad``, ``cap`` are the grid's
    NeighborGrid.pad and max_neighbors) and masks, without a branch, the pairs outside 0 < r < h (the pads
    are i itself, r = 0): so LLVM vectorises it ``pad`` neighbours at a time, as the solver's loops.
    Only the particles with mark[i] == ``value`` (see mark_energetic; there every particle may be marked)."""
    for i in range(n):
        if mark[i] != value:
            continue
        xi = x[i]
        vi = v[i]
        grad = vec3(0.0)
        wsum = 0.0
        vd = 0.0
        w = vec3(0.0)
        for k in range(padded_count(nb_count, i, pad, cap)):
            j = nb[i, k]
            xij = xi - x[j]
            r = xij.norm()
            near = (r > 0.0) & (r < h)
            wt = ti.select(near, 1.0 - r / h, 0.0)
            xh = xij / ti.select(near, r, 1.0)
            grad += xh * wt
            wsum += wt
            vij = vi - v[j]
            vl = vij.norm()
            moving = vl > 1e-9
            vd += ti.select(moving, vl * (1.0 - (vij / ti.select(moving, vl, 1.0)).dot(xh)), 0.0) * wt
            w += (v[j] - vi).cross(xh) * wt
        gl = grad.norm()
        normal[i] = grad / gl if gl > 1e-9 else vec3(0.0)
        # A particle is on the surface when its neighbourhood is lopsided.
        surface[i] = 1 if gl > surface_fraction * wsum else 0
        v_diff[i] = vd
        e_k[i] = 0.5 * vi.norm_sqr()
        vort[i] = w.norm() / (wsum + 1e-9) / h


@ti.kernel
def wave_crest(
    n: ti.i32, x: F3, v: F3, nb_count: I1, nb: I2, pad: TEMPLATE, cap: TEMPLATE, normal: F3, surface: I1,
    h: ti.f32, crest: F1, mark: I1, value: ti.i32,
):
    """κ_i = Σ_j (1 − n̂_i·n̂_j) W̃ over convex neighbours (x̂_ji·n̂_i < 0), times
    δ_vn = [v̂_i·n̂_i ≥ CREST_MOTION_COS]; zero away from the surface. Its neighbour loop is masked and
    padded, as fluid_potentials'. Only where mark[i] == ``value``."""
    for i in range(n):
        if mark[i] != value:
            continue
        kappa = 0.0
        if surface[i] == 1:
            ni = normal[i]
            xi = x[i]
            for k in range(padded_count(nb_count, i, pad, cap)):
                j = nb[i, k]
                xji = x[j] - xi
                r = xji.norm()
                take = (r > 0.0) & (r < h) & (xji.dot(ni) < 0.0)
                kappa += ti.select(take, (1.0 - ni.dot(normal[j])) * (1.0 - r / h), 0.0)
            vl = v[i].norm()
            if vl < 1e-9 or (v[i] / vl).dot(ni) < CREST_MOTION_COS:
                kappa = 0.0
        crest[i] = kappa


#: mark_energetic's marks: a particle whose kinetic energy may reach I_k > 0, one of their neighbours whose
#: normal the wave crest reads (mark_crest_neighbours), and the others.
ENERGETIC, CREST_NEIGHBOUR, IDLE = 1, 2, 0
#: mark_energetic's margin below τ_k,min: E_k at or above (1 − KE_MARGIN) τ_k,min is marked, a superset of
#: those with I_k > 0 however τ is rounded (f32 on the device, f64 in budget.births).
KE_MARGIN = 1e-5
#: mark_crest_neighbours' margin on δ_vn: crests whose motion test passes within it are taken.
CREST_COS_MARGIN = 1e-3


@ti.kernel
def mark_energetic(
    n: ti.i32, v: F3, ke_floor: ti.f32, e_k: F1, mark: I1, normal: F3, surface: I1, v_diff: F1, vort: F1, crest: F1,
):
    """E_k = ½|v_i|² of every fluid particle and its mark: ENERGETIC where E_k ≥ ``ke_floor`` (just below
    τ_k,min), IDLE elsewhere. Below τ_k,min, I_k = Φ(E_k, τ_k,min, τ_k,max) is exactly 0, and so is n_d
    (new_particles): such a particle makes nothing whatever its other potentials, which are set to 0 here
    (fluid_potentials and wave_crest then compute them for the marked only, the neighbour lists being built
    for those alone: in a splash a few per cent of the fluid is energetic)."""
    for i in range(n):
        ek = 0.5 * v[i].norm_sqr()
        e_k[i] = ek
        mark[i] = ENERGETIC if ek >= ke_floor else IDLE
        normal[i] = vec3(0.0)
        surface[i] = 0
        v_diff[i] = 0.0
        vort[i] = 0.0
        crest[i] = 0.0


@ti.kernel
def mark_rows(m: ti.i32, rows: I1, mark: I1, value: ti.i32):
    """mark[rows[k]] = ``value`` for k < m."""
    for k in range(m):
        mark[rows[k]] = value


@ti.kernel
def mark_crest_neighbours(n: ti.i32, v: F3, normal: F3, surface: I1, nb_count: I1, nb: I2, mark: I1) -> ti.i32:
    """Marks CREST_NEIGHBOUR the IDLE neighbours of every ENERGETIC particle whose wave crest counts (on the
    surface, moving along its normal: δ_vn, with CREST_COS_MARGIN to spare): wave_crest reads their normals.
    Every writer writes the same mark, so the result does not depend on the threads. Returns how many
    particles' lists are still to build (an upper bound: a particle met twice is counted twice)."""
    more = 0
    for i in range(n):
        if mark[i] == ENERGETIC and surface[i] == 1:
            vl = v[i].norm()
            if vl >= 1e-9 and (v[i] / vl).dot(normal[i]) >= CREST_MOTION_COS - CREST_COS_MARGIN:
                for k in range(nb_count[i]):
                    j = nb[i, k]
                    if mark[j] == IDLE:
                        mark[j] = CREST_NEIGHBOUR
                        more += 1
    return more


@ti.func
def new_particles(i, v_diff: F1, crest: F1, e_k: F1, vort: F1, tau: F1, k_ta, k_wc, k_vo, dt) -> ti.f32:
    """n_d = I_k (k_ta I_ta + k_wc I_wc + k_vo I_vo) Δt of fluid particle i, before rounding."""
    i_ta = clamp_phi(v_diff[i], tau[0], tau[1])
    i_wc = clamp_phi(crest[i], tau[2], tau[3])
    i_k = clamp_phi(e_k[i], tau[4], tau[5])
    i_vo = clamp_phi(vort[i], tau[6], tau[7])
    return i_k * (k_ta * i_ta + k_wc * i_wc + k_vo * i_vo) * dt


@ti.kernel
def birth_counts(
    n: ti.i32,
    ids: U1,
    v_diff: F1,
    crest: F1,
    e_k: F1,
    vort: F1,
    tau: F1,
    k_ta: ti.f32,
    k_wc: ti.f32,
    k_vo: ti.f32,
    dt: ti.f32,
    seed: ti.u32,
    frame: ti.u32,
    cap: ti.i32,
    count: I1,
    rate: F1,
    round_half_up: ti.i32,
) -> ti.i32:
    """How many particles each fluid particle generates: n_d (see new_particles) into
    ``rate``, rounded stochastically into ``count`` (or to the nearest integer with
    ``round_half_up``, as SPlisHSPlasH's FoamGenerator does), at most ``cap`` (0: no
    cap). Returns the number beyond the cap."""
    lost = 0
    for i in range(n):
        nd = new_particles(i, v_diff, crest, e_k, vort, tau, k_ta, k_wc, k_vo, dt)
        rate[i] = nd
        m = ti.cast(ti.floor(nd), ti.i32)
        if round_half_up:
            m = ti.cast(ti.floor(nd + 0.5), ti.i32)
        elif rand01(seed, frame, ids[i], ti.u32(0xFFFF), ti.u32(0)) < nd - m:
            m += 1
        if cap > 0 and m > cap:
            lost += m - cap
            m = cap
        count[i] = m
    return lost


@ti.func
def new_particle(
    x_f: vec3, v_f: vec3, pid: ti.u32, s: ti.i32, i_k: ti.f32, life_min: ti.f32, life_max: ti.f32, life_mult: ti.f32,
    r_v: ti.f32, dt: ti.f32, seed: ti.u32, frame: ti.u32,
):
    """(x_d, v_d, lifetime) of the new particle in slot s of the fluid particle (x_f, v_f, id pid),
    sampled uniformly in a cylinder of radius r_V and height |Δt v_f| along v̂_f:
        r = r_V √X_r, θ = 2π X_θ, h = X_h |Δt v_f|,
        x_d = x_f + r cosθ e1' + r sinθ e2' + h v̂_f,  v_d = r cosθ e1' + r sinθ e2' + v_f,
    its lifetime l_min + X_l (l_max − l_min), or life_mult·I_k·Δt where life_mult > 0; the X are
    draws 1-4 of (seed, frame, pid, s)."""
    vl = v_f.norm()
    vh = vec3(0.0, 0.0, 1.0)
    if vl > 1e-9:
        vh = v_f / vl
    a = vec3(1.0, 0.0, 0.0)
    if ti.abs(vh.x) > NEAR_PARALLEL_COS:
        a = vec3(0.0, 1.0, 0.0)
    e1 = a.cross(vh).normalized()
    e2 = vh.cross(e1)
    su = ti.cast(s, ti.u32)
    xr = rand01(seed, frame, pid, su, ti.u32(1))
    xt = rand01(seed, frame, pid, su, ti.u32(2))
    xh = rand01(seed, frame, pid, su, ti.u32(3))
    xl = rand01(seed, frame, pid, su, ti.u32(4))
    rr = r_v * ti.sqrt(xr)
    th = 2.0 * math.pi * xt
    off = rr * ti.cos(th) * e1 + rr * ti.sin(th) * e2
    life = life_min + (life_max - life_min) * xl
    if life_mult > 0.0:
        life = life_mult * i_k * dt
    return x_f + off + xh * dt * vl * vh, off + v_f, life


@ti.kernel
def chunk_owners(n: ti.i32, base: ti.i32, m: ti.i32, count: I1, offset: I1, owner: I1):
    """owner[k − base] = i for the candidates k of the chunk [base, base + m) in the run [offset[i],
    offset[i] + count[i]) of fluid particle i: the frame's candidates are numbered by fluid particle, then
    by slot s < count[i] (offset: the exclusive prefix sum of count), so the order is fixed whatever the
    thread count."""
    for i in range(n):
        for k in range(ti.max(offset[i], base), ti.min(offset[i] + count[i], base + m)):
            owner[k - base] = i


@ti.kernel
def zero_below(n: ti.i32, nb_count: I1, min_count: ti.i32, a: F1):
    """a_i = 0 where particle i has fewer than ``min_count`` neighbours."""
    for i in range(n):
        if nb_count[i] < min_count:
            a[i] = 0.0


@ti.func
def _weigh_fluid(g: TEMPLATE, s, r2, h, h2, vs: F3, cnt: TEMPLATE, vsum: TEMPLATE, wsum: TEMPLATE):
    """Adds the fluid particle in slot s (velocity vs[s], in the grid's cell order) at distance r to the
    neighbourhood sums when r² < h², weighted by W̃ = 1 − r/h (``g``, the index of the query point, is always 0:
    one point a query). Every candidate of the scanned cells is handed in and masked, not branched on: the
    branch, taken for about a third of them in no order the processor can predict, cost more than the
    masked work (the velocities are read in the order of the positions, vs, so the extra loads stream).
    A masked candidate adds exact zeros: the sums are those of the neighbours alone, in the same order."""
    inside = r2 < h2
    wt = ti.select(inside, 1.0 - ti.sqrt(r2) / h, 0.0)
    cnt += ti.cast(inside, ti.i32)
    vsum += wt * vs[s]
    wsum += wt


@ti.func
def fluid_neighbourhood(p: vec3, grid: TEMPLATE, scan: TEMPLATE, h: ti.f32, vs: F3):
    """(fluid neighbour count, Σ W̃ v_f, Σ W̃) around a point, from the fluid's
    :class:`~whitecap.sim.grid.NeighborGrid` (its ``query_args()``: the query and the scan; then h and
    the fluid's velocities in the grid's cell order, ``vs[s] = v[order[s]]``: read in the order the scan
    meets them, not gathered through ``order``)."""
    cnt = 0
    vsum = vec3(0.0)
    wsum = 0.0
    for_each_neighbor([p], h, grid, scan, _weigh_fluid, (h, h * h, vs, cnt, vsum, wsum), True)
    return cnt, vsum, wsum


@ti.func
def diffuse_type(cnt: ti.i32, spray_below: ti.i32, bubble_above: ti.i32) -> ti.i32:
    """SPRAY (fewer than spray_below fluid neighbours), BUBBLE (more than bubble_above), else FOAM
    (the codes of :mod:`whitecap.io.diffuse_types`)."""
    t = FOAM
    if cnt < spray_below:
        t = SPRAY
    elif cnt > bubble_above:
        t = BUBBLE
    return t


@ti.func
def diffuse_type_in_box(
    p: vec3, cnt: ti.i32, spray_below: ti.i32, bubble_above: ti.i32, lo: vec3, hi: vec3, h: ti.f32,
    wall_correction: ti.i32,
) -> ti.i32:
    """:func:`diffuse_type`, with FoamGenerator's count correction near the box's faces for
    foam when ``wall_correction`` (the ``splishsplash-box`` preset; see .splishsplash)."""
    t = diffuse_type(cnt, spray_below, bubble_above)
    if wall_correction and t == FOAM:
        t = diffuse_type(SP.wall_corrected_count(p, cnt, lo, hi, h, bubble_above), spray_below, bubble_above)
    return t


@ti.kernel
def advect_diffuse(
    nd: ti.i32,
    xd: F3,
    vd: F3,
    life: F1,
    grid: GridQuery,
    scan: TEMPLATE,
    h: ti.f32,
    vs: F3,
    g: vec3,
    k_b: ti.f32,
    k_d: ti.f32,
    dt: ti.f32,
    spray_below: ti.i32,
    bubble_above: ti.i32,
    lo: vec3,
    hi: vec3,
    keep: I1,
    kind: I1,
    foam_keeps_velocity: ti.i32,
    wall_correction: ti.i32,
):
    """Classify by fluid-neighbour count and advect each type its own way:
    spray ballistic (v += Δt g); foam carried by the kernel-averaged fluid
    velocity ṽ_f (moving with it; its own v is set to ṽ_f, or kept as it was with
    ``foam_keeps_velocity``, as SPlisHSPlasH's FoamGenerator does, so foam that
    turns into spray leaves with its earlier velocity), its lifetime counting down; bubbles
    v += Δt(−k_b g + k_d (ṽ_f − v)/Δt). Removes expired foam and particles
    that leave the domain. ``kind`` is the type each particle moved as. ``wall_correction``:
    FoamGenerator's foam-count correction near the domain's faces (see diffuse_type_in_box)."""
    for p in range(nd):
        cnt, vsum, wsum = fluid_neighbourhood(xd[p], grid, scan, h, vs)
        vf = vec3(0.0)
        if wsum > 0.0:
            vf = vsum / wsum
        alive = 1
        t = diffuse_type_in_box(xd[p], cnt, spray_below, bubble_above, lo, hi, h, wall_correction)
        if t == SPRAY:
            vd[p] += dt * g
            xd[p] += dt * vd[p]
        elif t == BUBBLE:
            vd[p] += dt * (-k_b * g) + k_d * (vf - vd[p])
            xd[p] += dt * vd[p]
        else:
            if not foam_keeps_velocity:
                vd[p] = vf
            xd[p] += dt * vf
            life[p] -= dt
            if life[p] <= 0.0:
                alive = 0
        q = xd[p]
        if q.x < lo.x or q.y < lo.y or q.z < lo.z or q.x > hi.x or q.y > hi.y or q.z > hi.z:
            alive = 0
        keep[p] = alive
        kind[p] = t


@ti.kernel
def classify(
    nd: ti.i32,
    xd: F3,
    grid: GridQuery,
    scan: TEMPLATE,
    h: ti.f32,
    vs: F3,
    spray_below: ti.i32,
    bubble_above: ti.i32,
    lo: vec3,
    hi: vec3,
    wall_correction: ti.i32,
    kind: I1,
):
    """The type of each diffuse particle from its fluid-neighbour count (see diffuse_type_in_box)."""
    for p in range(nd):
        cnt, vsum, wsum = fluid_neighbourhood(xd[p], grid, scan, h, vs)
        kind[p] = diffuse_type_in_box(xd[p], cnt, spray_below, bubble_above, lo, hi, h, wall_correction)


# ---------------------------------------------------------------- classifying a frame's candidates
#: kind of a candidate that no type can keep (see classify_candidates)
NOT_KEPT = -1
#: The owner's neighbours are counted within h·(1 − OWNER_SLACK) of a candidate: a strict radius, so
#: that rounding can never count one that the grid's query (|x_j − x_d|² < h²) leaves out.
OWNER_SLACK = 1e-4


@ti.func
def _count_fluid(g, s, r2, h2, cnt: TEMPLATE, most):
    """Counts a fluid particle met by the scan where r² < h² (every candidate of the scanned cells is
    handed in: no branch on the distance)."""
    cnt += ti.cast(r2 < h2, ti.i32)


@ti.func
def _counted_past(h2, cnt: TEMPLATE, most) -> ti.i32:
    """Whether the count is past ``most``: the stop of :func:`fluid_count`'s query."""
    return cnt > most


@ti.func
def fluid_count(p: vec3, grid: TEMPLATE, scan: TEMPLATE, h: ti.f32, most: ti.i32) -> ti.i32:
    """The number of fluid particles within h of a point (as :func:`fluid_neighbourhood` counts them, without
    its velocity sums), exact up to ``most``; above it, some number above ``most``: the query scans the
    nearest columns of cells first and stops once the count passes it (for_each_neighbor's ``stop``).
    Given bubble_above, a candidate's type (:func:`diffuse_type_in_box`) is the same as with the full count:
    any count above bubble_above makes a bubble, and the wall correction only looks at foam. Most
    candidates (80 % on bench_foam's 100k) are bubbles, born inside the water, whose count passes
    bubble_above before the outer columns: the foam stage's CPU time there went 190 → 180 ms a frame."""
    cnt = 0
    for_each_neighbor([p], h, grid, scan, _count_fluid, (h * h, cnt, most), True, _counted_past)
    return cnt


@ti.func
def owner_neighbours_near(i, p: vec3, x: F3, nb_count: I1, nb: I2, r2: ti.f32) -> ti.i32:
    """How many of fluid particle i's neighbours (its list nb[i, :nb_count[i]]) lie within r of the point p.
    They are distinct fluid particles, so for r ≤ h this never exceeds p's own count of fluid neighbours
    within h. The whole list is counted, without a branch: stopping at a count would branch on every
    neighbour, unpredictably (at 800k candidates, 29 ms against 18). (Over the padded row with the pads
    masked, as fluid_potentials' loop, not faster: 71 against 53 ms a frame on the r = 4 mm dam break at load 8.)"""
    c = 0
    for k in range(nb_count[i]):
        c += ti.cast((x[nb[i, k]] - p).norm_sqr() < r2, ti.i32)
    return c


#: The most fluid particles that owner_reach ranks about a point (spray_below at most, as a sorting network
#: in registers); a larger spray_below leaves classify_candidates to the owner's list alone.
REACH_RANK = 8
#: Points along a fluid particle's generation cylinder (its axis, from x_i to x_i + Δt v_i) at which
#: owner_reach measures how far the fluid reaches.
REACH_PROBES = 9
#: owner_reach's value for a fluid particle none of whose spray-only candidates can be spray (they are
#: neither generated nor searched).
REACH_ALL = 1e30
#: Rounding allowed for in a candidate's distance from its owner's axis, relative to the largest coordinate:
#: its position is x_f + off + X_h Δt v_f in f32 (three roundings of half an ulp, 2^-24, each).
REACH_ROUNDING = 8.0 * 2.0**-23
#: generate_candidates' lifetime for a spray-only candidate it found within reach without placing it (a
#: lifetime is never negative): classify_candidates keeps none of these.
SETTLED = -1.0


@ti.kernel
def owner_reach(
    n: ti.i32, limit: I2, x: F3, v: F3, nb_count: I1, nb: I2, h: ti.f32, spray_below: ti.i32, r_v: ti.f32,
    dt: ti.f32, probe: F3, reach: F1,
):
    """For each fluid particle i with spray-only slots (at or past the foam and bubble limits but below spray's,
    which classify_candidates settles with this), REACH_PROBES points c_k = x_i + k/(REACH_PROBES − 1) Δt v_i
    along its generation cylinder's axis (probe[i·REACH_PROBES + k]) and a distance from each (reach[…])
    within which any point surely has spray_below fluid particles within h, so a candidate born there is not
    spray: i and its listed neighbours are fluid particles; the spray_below nearest of them to c_k, at most
    d_(spray_below) from it, lie within d + d_(spray_below) of a point at d from c_k (triangle inequality):
    reach = h·(1 − OWNER_SLACK) − d_(spray_below). They are some of the fluid particles within h of such a
    point, so the test never calls spray what the grid's count would not. Where every candidate lies within
    the reach of its nearest probe (no candidate is further than r_V + half the probes' spacing from it, see
    new_particle, give or take REACH_ROUNDING), every reach is REACH_ALL: none of i's spray-only candidates
    can be kept. Negative (no test) where spray_below > REACH_RANK. Nothing is written for the other particles:
    only a spray-only slot's candidate reads its owner's probes (generate_candidates, classify_candidates), and
    nine probes written for every fluid particle (18 MB a frame at 125k) cost more than the probes' work."""
    h_in = h * (1.0 - OWNER_SLACK)
    for i in range(n):
        if limit[i, SPRAY] <= limit[i, FOAM] or limit[i, SPRAY] <= limit[i, BUBBLE]:
            continue  # no spray-only slot
        xi, vi = x[i], v[i]
        all_in = spray_below <= REACH_RANK
        far = r_v + dt * vi.norm() / (2.0 * (REACH_PROBES - 1))
        far += REACH_ROUNDING * (ti.max(ti.abs(xi).max(), 1.0) + far)
        for k in range(REACH_PROBES):  # (a loop, not unrolled: a ninth of the kernel to compile)
            c = xi + (k / (REACH_PROBES - 1) * dt) * vi
            r = -1.0
            if spray_below <= 0:  # nothing is spray
                r = REACH_ALL
            elif spray_below <= REACH_RANK:
                best = ti.Vector([REACH_ALL] * REACH_RANK, ti.f32)  # the smallest distances, ascending
                best[0] = (xi - c).norm()
                for m in range(nb_count[i]):
                    d = (x[nb[i, m]] - c).norm()
                    for t in ti.static(range(REACH_RANK)):  # insertion without branches
                        lo = ti.min(best[t], d)
                        d = ti.max(best[t], d)
                        best[t] = lo
                dk = REACH_ALL
                for t in ti.static(range(REACH_RANK)):
                    dk = ti.select(t == spray_below - 1, best[t], dk)
                r = h_in - dk
                all_in = all_in and far < r
            probe[i * REACH_PROBES + k] = c
            reach[i * REACH_PROBES + k] = r
        if all_in:
            for k in range(REACH_PROBES):
                reach[i * REACH_PROBES + k] = REACH_ALL


@ti.func
def within_reach(i, p: vec3, probe: F3, reach: F1) -> ti.i32:
    """Whether the point p lies within the reach of the probe of fluid particle i nearest it along the axis
    (owner_reach): then it has spray_below fluid particles within h. Any probe would be a sound test; the
    nearest along the axis is the one most likely to settle it."""
    b = i * REACH_PROBES
    c0 = probe[b]
    axis = probe[b + REACH_PROBES - 1] - c0
    a = (p - c0).dot(axis) / ti.max(axis.norm_sqr(), 1e-30) * (REACH_PROBES - 1)
    k = ti.min(ti.max(ti.cast(ti.round(a), ti.i32), 0), REACH_PROBES - 1)
    return ti.cast((p - probe[b + k]).norm() < reach[b + k], ti.i32)


@ti.kernel
def generate_candidates(
    m: ti.i32, base: ti.i32, owner: I1, offset: I1, limit: I2, x: F3, v: F3, ids: U1, e_k: F1, tau: F1,
    life_min: ti.f32, life_max: ti.f32, life_mult: ti.f32, r_v: ti.f32, dt: ti.f32, seed: ti.u32, frame: ti.u32,
    reach: F1, out_x: F3, out_v: F3, out_life: F1,
):
    """The new particles (:func:`new_particle`) for the chunk of candidates base + j (j < m; candidate k is slot
    k − offset[i] of fluid particle i = owner[j], see chunk_owners), in parallel over them (a splash crowds
    its candidates into a few fluid particles, 800k from 3.6k in the r = 4 mm dam break, which one thread
    each would share badly); only those a type may keep (the others are never looked at), and of the
    spray-only slots (at or past the foam and bubble limits) none whose owner's reach is REACH_ALL (owner_reach:
    none can be spray), and none within the reach of its probe, told from its axial draw alone (its lifetime is
    set to SETTLED instead: classify_candidates keeps none of these). All three are written: a kernel that kept
    only the positions would compile them with other roundings (fast math contracts the shared offset into the
    position), and the classification would not see the positions the particles are born at."""
    for j in range(m):
        k = base + j
        i = owner[j]
        s = k - offset[i]
        foam_or_bubble = s < limit[i, FOAM] or s < limit[i, BUBBLE]
        if foam_or_bubble or (s < limit[i, SPRAY] and reach[i * REACH_PROBES] < REACH_ALL):
            settled = 0
            if not foam_or_bubble:  # spray-only: within the reach of the probe nearest along the axis?
                xh = rand01(seed, frame, ids[i], ti.cast(s, ti.u32), ti.u32(3))  # new_particle's X_h
                at = ti.min(ti.cast(ti.round(xh * (REACH_PROBES - 1)), ti.i32), REACH_PROBES - 1)
                # |x_d − c_at| ≤ r√X_r + |X_h − at/(P − 1)| Δt|v_f| (the offset off is at most r_V)
                far = r_v + ti.abs(xh - at / (REACH_PROBES - 1)) * dt * v[i].norm()
                far += REACH_ROUNDING * (ti.max(ti.abs(x[i]).max(), 1.0) + far)
                if far < reach[i * REACH_PROBES + at]:
                    settled = 1
                    out_life[j] = SETTLED
            if not settled:
                i_k = clamp_phi(e_k[i], tau[4], tau[5])
                out_x[j], out_v[j], out_life[j] = new_particle(x[i], v[i], ids[i], s, i_k, life_min, life_max,
                                                               life_mult, r_v, dt, seed, frame)


@ti.kernel
def classify_candidates(
    m: ti.i32,
    base: ti.i32,
    owner: I1,
    offset: I1,
    limit: I2,
    xd: F3,
    life: F1,
    x: F3,
    nb_count: I1,
    nb: I2,
    lists: ti.i32,
    probe: F3,
    reach: F1,
    grid: GridQuery,
    scan: TEMPLATE,
    h: ti.f32,
    spray_below: ti.i32,
    bubble_above: ti.i32,
    lo: vec3,
    hi: vec3,
    wall_correction: ti.i32,
    kind: B1,
):
    """Which of the candidates k = base + j (j < m, a chunk of the frame's) are kept: candidate k, at slot s of
    fluid particle i = owner[j] at xd[j] (generate_candidates), is kept when its type t
    (:func:`diffuse_type_in_box`) has s < limit[i, t], the particle's n_d·m_t rounded (see kept_limit).
    The type is found with the least work that decides this:
    - s at or above every type's limit: never kept, no count;
    - s below the foam or the bubble limit: the full type, from the fluid count within h;
    - otherwise only spray (fewer than spray_below fluid neighbours) can keep it. Where the frame's
      neighbour lists were built (``lists``; x, nb_count, nb: the fluid's positions and the grid's
      lists), a candidate within the reach of its owner's nearest probe (owner_reach, within_reach) is not
      spray, without a loop; else the owner's own neighbours within h of the candidate are some of its fluid
      neighbours: when spray_below of them are, it is not spray (these settle, without the grid's search,
      most candidates: they are born inside the water, near their fluid particle: on the r = 4 mm dam
      break, classify_candidates took 73 ms a frame without the list test against 54 with it). Else the count
      need only be known up to spray_below (a query that stops there): any count at or above it makes foam
      or a bubble (the wall correction only raises foam's count), which this slot cannot keep.
    kind[j] is the type of a kept candidate and NOT_KEPT for the others."""
    r2_owner = (h * (1.0 - OWNER_SLACK)) ** 2
    for j in range(m):
        i = owner[j]
        s = base + j - offset[i]
        t = NOT_KEPT
        if s < limit[i, SPRAY] or s < limit[i, FOAM] or s < limit[i, BUBBLE]:
            most = spray_below - 1
            search = 1
            if s < limit[i, FOAM] or s < limit[i, BUBBLE]:
                most = bubble_above
            elif lists:
                if reach[i * REACH_PROBES] >= REACH_ALL:  # not generated (generate_candidates): none can be spray
                    search = 0
                elif life[j] == SETTLED:  # not placed: generate_candidates found it within reach
                    search = 0
                elif within_reach(i, xd[j], probe, reach):  # settled by the owner's neighbours (owner_reach)
                    search = 0
                else:
                    search = ti.cast(owner_neighbours_near(i, xd[j], x, nb_count, nb, r2_owner) < spray_below, ti.i32)
            if search:
                p = xd[j]
                cnt = fluid_count(p, grid, scan, h, most)  # one search in the kernel's code (inlined where called)
                t = diffuse_type_in_box(p, cnt, spray_below, bubble_above, lo, hi, h, wall_correction)
                if s >= limit[i, t]:
                    t = NOT_KEPT
        kind[j] = ti.cast(t, ti.i8)


# Stream compaction on the device: the exclusive prefix sum is sim/scan.py's (shared with the sinks).


# ---------------------------------------------------------------- the live diffuse particles
#: Draw numbers of the (seed, frame, id, slot) counter outside the birth (birth_counts uses 0, new_particle 1-4).
DRAW_LIFE, DRAW_DISSIPATE = 6, 7
#: Slot of birth_counts' stochastic-rounding draw (the keep rule rounds with the same number).
ROUNDING_SLOT = 0xFFFF
#: kernels read a type's lifetime range only where it has one (``has_range``)


@ti.kernel
def expire_diffuse(
    nd: ti.i32, life: F1, ids: U1, kind: I1, keep: I1, dt: ti.f32, spray_range: ti.i32, bubble_range: ti.i32,
    foam_extra: ti.f32, dissipate: ti.i32, survive: ti.f32, seed: ti.u32, frame: ti.u32,
):
    """After advect_diffuse: spray and bubbles count their lifetime down where their type has a range
    (``spray_range``, ``bubble_range``); foam ages faster by ``foam_extra`` = (aging − 1)·Δt under 'auto'
    (budget.foam_aging); each foam particle survives the frame with probability ``survive`` = exp(−λΔt)
    when ``dissipate`` (draw DRAW_DISSIPATE of slot 0). A particle whose lifetime ran out goes."""
    for p in range(nd):
        t = kind[p]
        k = keep[p]
        if (t == SPRAY and spray_range) or (t == BUBBLE and bubble_range):
            life[p] -= dt
            if life[p] <= 0.0:
                k = 0
        if t == FOAM:
            if foam_extra > 0.0:
                life[p] -= foam_extra
                if life[p] <= 0.0:
                    k = 0
            if dissipate and rand01(seed, frame, ids[p], ti.u32(0), ti.u32(DRAW_DISSIPATE)) >= survive:
                k = 0
        keep[p] = k


@ti.func
def inside_box(q: vec3, lo: vec3, hi: vec3) -> ti.i32:
    return q.x >= lo.x and q.y >= lo.y and q.z >= lo.z and q.x <= hi.x and q.y <= hi.y and q.z <= hi.z


@ti.kernel
def copy_vec3(n: ti.i32, src: F3, dst: F3):
    for i in range(n):
        dst[i] = src[i]


@ti.kernel
def scatter_survivors(
    nd: ti.i32, keep: I1, pos: I1, x: F3, v: F3, life: F1, ids: U1, kind: I1,
    ox: F3, ov: F3, olife: F1, oids: U1, okind: I1,
):
    """Compaction of the live particles: those kept to their place pos[p] (the exclusive prefix sum of
    ``keep``), in their order."""
    for p in range(nd):
        if keep[p]:
            q = pos[p]
            ox[q], ov[q], olife[q], oids[q], okind[q] = x[p], v[p], life[p], ids[p], kind[p]


# ---------------------------------------------------------------- the keep rule of the new particles
@ti.func
def rounded(want: ti.f32, u0: ti.f32, round_half_up: ti.i32) -> ti.f32:
    """A fluid particle's n_d·m_t rounded with its own draw u0 (or half up, FoamGenerator's)."""
    f = ti.floor(want)
    lim = f + ti.cast(u0 < want - f, ti.f32)
    if round_half_up:
        lim = ti.floor(want + 0.5)
    return lim


@ti.kernel
def candidate_limits(
    n: ti.i32, count: I1, rate: F1, ids: U1, most: ti.f32, mult: F1, seed: ti.u32, frame: ti.u32,
    round_half_up: ti.i32, want: F2, limit: I2,
):
    """want[i, t] = n_d·m_t of fluid particle i for type t (n_d = rate/most: the rate of the most generous
    type), and limit[i, t], the slots that type t may keep: want rounded (see rounded); zero without
    candidates."""
    for i in range(n):
        u0 = rand01(seed, frame, ids[i], ti.u32(ROUNDING_SLOT), ti.u32(0))
        nd = rate[i] / most
        for t in ti.static(range(3)):
            w = nd * mult[t]
            want[i, t] = w
            lim = 0.0
            if count[i] > 0:
                lim = ti.min(rounded(w, u0, round_half_up), 2.0**30)
            limit[i, t] = ti.cast(lim, ti.i32)


@ti.kernel
def scale_want(n: ti.i32, want: F2, factor: F1):
    """want[i, t] ×= factor[t]: the budget's cut of each type, or its common cut (one rounding each, in this
    order: a product of several factors in one expression may be reordered by the compiler's fast math)."""
    for i in range(n):
        for t in ti.static(range(3)):
            want[i, t] = want[i, t] * factor[t]


@ti.kernel
def kept_flags(total: ti.i32, kind: B1, flag: I1):
    for k in range(total):
        flag[k] = ti.cast(kind[k] >= 0, ti.i32)


@ti.kernel
def thin_kept(
    m: ti.i32, base: ti.i32, kind: B1, owner: I1, offset: I1, want: F2, ids: U1, seed: ti.u32, frame: ti.u32,
    round_half_up: ti.i32,
):
    """The keep rule again with lower limits (``want`` after scale_want's cuts for the budget) on the chunk of
    candidates base + j (j < m; their types in kind[j]): a kept candidate whose slot reaches its type's new
    limit is no longer kept (tally_kinds counts those still kept)."""
    for j in range(m):
        t = ti.cast(kind[j], ti.i32)
        if t >= 0:
            k = base + j
            i = owner[j]
            u0 = rand01(seed, frame, ids[i], ti.u32(ROUNDING_SLOT), ti.u32(0))
            if k - offset[i] >= rounded(want[i, t], u0, round_half_up):
                kind[j] = ti.cast(NOT_KEPT, ti.i8)


@ti.kernel
def tally_kinds(n: ti.i32, kind: N1) -> COUNTS3:
    """The number of entries of ``kind[0..n)`` equal to t, for t = 0, 1, 2 (others not counted). Three sums,
    each a reduction Taichi keeps per thread (an atomic add at an index read from the data made the two
    threads contend for the three counters: 1.1 ms a frame at bench_foam's 300k candidates); returned, not
    left in an array: clearing and reading one back were two more launches."""
    c0, c1, c2 = 0, 0, 0
    for k in range(n):
        t = ti.cast(kind[k], ti.i32)
        c0 += ti.cast(t == 0, ti.i32)
        c1 += ti.cast(t == 1, ti.i32)
        c2 += ti.cast(t == 2, ti.i32)
    return ti.Vector([c0, c1, c2])


@ti.kernel
def place_new(m: ti.i32, kind: B1, rank: I1, rank_base: ti.i32, room: ti.i32, cx: F3, lo: vec3, hi: vec3, flag: I1):
    """The kept candidates j of a chunk (j < m; positions cx[j]) that fit (their rank among the
    frame's kept, rank_base + rank[j], in candidate order, below ``room``) and lie in the domain get flag 1."""
    for j in range(m):
        f = 0
        if kind[j] >= 0 and rank_base + rank[j] < room:
            f = inside_box(cx[j], lo, hi)
        flag[j] = f


@ti.kernel
def outside_box(n: ti.i32, x: F3, flag: I1, lo: vec3, hi: vec3):
    """flag[p] = 0 where particle p has left the domain [lo, hi]."""
    for p in range(n):
        if not inside_box(x[p], lo, hi):
            flag[p] = 0


@ti.kernel
def scatter_new(
    m: ti.i32, base: ti.i32, flag: I1, pos: I1, rank: I1, rank_base: ti.i32, out_base: ti.i32, next_id: ti.u32,
    kind: B1, owner: I1, offset: I1, ids: U1, e_k: F1, tau: F1, cx: F3, cv: F3, clife: F1, life_min: ti.f32,
    spray_range: vec3, bubble_range: vec3, foamgenerator: ti.i32, span: ti.f32, life_min64: ti.f64, span64: ti.f64,
    seed: ti.u32, frame: ti.u32, ox: F3, ov: F3, olife: F1, oids: U1, okind: I1,
):
    """The placed new particles of the chunk (flag[j]) to out_base + pos[j], after the survivors, in candidate
    order; ids next_id + their rank among the frame's kept (so one born outside the domain still takes its id,
    as before). Their lifetimes: FoamGenerator's where ``foamgenerator``, l_min + (I_k/τmax_k) X (l_max − l_min)
    with X = (l − l_min)/``span`` (f32) and the rest in f64, as SP.lifetimes; a draw (DRAW_LIFE) in the type's
    own range for spray and bubbles that have one (range = (min, max − min, 1); z = 0: none)."""
    for j in range(m):
        if flag[j]:
            i = owner[j]
            s = ti.cast(base + j - offset[i], ti.u32)
            t = ti.cast(kind[j], ti.i32)
            life = clife[j]
            if foamgenerator:
                x01 = (life - life_min) / span
                e = ti.cast(e_k[i], ti.f64)
                t4, t5 = ti.cast(tau[4], ti.f64), ti.cast(tau[5], ti.f64)
                i_k = (ti.min(e, t5) - ti.min(e, t4)) / ti.cast(tau[5] - tau[4], ti.f64)
                life = ti.cast(life_min64 + i_k / t5 * ti.cast(x01, ti.f64) * span64, ti.f32)
            if t == SPRAY and spray_range.z > 0.0:
                life = spray_range.x + spray_range.y * rand01(seed, frame, ids[i], s, ti.u32(DRAW_LIFE))
            if t == BUBBLE and bubble_range.z > 0.0:
                life = bubble_range.x + bubble_range.y * rand01(seed, frame, ids[i], s, ti.u32(DRAW_LIFE))
            q = out_base + pos[j]
            ox[q], ov[q], olife[q] = cx[j], cv[j], life
            oids[q] = next_id + ti.cast(rank_base + rank[j], ti.u32)
            okind[q] = t


@ti.kernel
def download_state(
    n: ti.i32, x: F3, v: F3, life: F1, ids: U1, kind: I1, ox: F3, ov: F3, olife: F1, oids: U1, okind: U8,
):
    """The first n live particles into host arrays (one copy a frame, for its output)."""
    for p in range(n):
        ox[p], ov[p], olife[p], oids[p], okind[p] = x[p], v[p], life[p], ids[p], ti.cast(kind[p], ti.u8)


@ti.kernel
def upload_state(
    n: ti.i32, hx: F3, hv: F3, hlife: F1, hids: U1, x: F3, v: F3, life: F1, ids: U1,
):
    """Host state (a resumed checkpoint, a state set by hand) into the live particles' arrays."""
    for p in range(n):
        x[p], v[p], life[p], ids[p] = hx[p], hv[p], hlife[p], hids[p]


@ti.kernel
def copy_fluid(n: ti.i32, sx: F3, sv: F3, sids: N1, x: F3, v: F3, ids: U1):
    """A fluid frame's first n particles into the kept arrays x, v, ids (ids of any integer type), their rows past
    n zero: one launch for the three. From host arrays (post-processing; on the CPU read in place), or, inside
    `simulate`, from the solver's own arrays, which hold the frame just written in the same order, so that it
    never goes up again (1 M particles: 28 MB over the bus each way, Taichi copying a host array back after each
    launch)."""
    for p in range(x.shape[0]):
        if p < n:
            x[p], v[p], ids[p] = sx[p], sv[p], ti.cast(sids[p], ti.u32)
        else:
            x[p], v[p], ids[p] = vec3(0.0), vec3(0.0), ti.u32(0)


@ti.kernel
def clear_fluid_rows(n: ti.i32, x: F3, v: F3, ids: U1):
    """Rows n.. of the kept fluid arrays zero, as copy_fluid leaves them (the first n copied up without a kernel)."""
    for p in range(n, x.shape[0]):
        x[p], v[p], ids[p] = vec3(0.0), vec3(0.0), ti.u32(0)


@ti.kernel
def pack_potentials(m: ti.i32, picked: ti.i32, rows: I1, v_diff: F1, crest: F1, e_k: F1, vort: F1, out: F2):
    """The potentials I_ta (v_diff), I_wc (crest), E_k and I_vo (vort) of the fluid particles i = rows[j] (j < m)
    where ``picked``, else of i = j, into one host array, out[0..3, j]: one launch, where reading each back took
    four, and only the rows the host needs (a frame's history sample under the running 'auto')."""
    for j in range(m):
        i = rows[j] if picked else j
        out[0, j], out[1, j], out[2, j], out[3, j] = v_diff[i], crest[i], e_k[i], vort[i]


#: Fluid particles each thread of birth_sums adds up (the last thread's may be fewer): a few thousand threads at 1 M.
BIRTH_RUN = 256
#: birth_sums counts in units of 2^-s, s set by the caller (birth_unit) so that the most the sums can reach, n·Δt
#: (each term is at most Δt), stays below 2^BIRTH_BITS: one bit short of the 64-bit integers they are kept in.
BIRTH_BITS = 62
I64: Any = ti.types.ndarray(dtype=ti.i64, ndim=1)
SUMS3: Any = ti.types.vector(3, ti.i64)


def birth_unit(n: int, dt: float) -> float:
    """birth_sums' unit for n fluid particles and a frame of dt: the largest power of two u with n·Δt·u < 2^BIRTH_BITS.
    A term of births is an f32, so it is a whole number of units, exactly, down to 2^24 units (at 1 M particles and
    Δt = 1/120 s, terms above 1e-8 of a particle: the rest are rounded to the unit)."""
    return math.ldexp(1.0, BIRTH_BITS - math.frexp(max(n * dt, 1e-30))[1])


@ti.func
def _birth_units(i, v_diff: F1, crest: F1, e_k: F1, vort: F1, tau: F1, dt: ti.f32, unit: ti.f64):
    """Fluid particle i's three terms of birth_sums (f32, as the births are drawn), each to its nearest unit."""
    w = clamp_phi(e_k[i], tau[4], tau[5]) * dt
    term = ti.max(ti.Vector([w * clamp_phi(v_diff[i], tau[0], tau[1]), w * clamp_phi(crest[i], tau[2], tau[3]),
                             w * clamp_phi(vort[i], tau[6], tau[7])]), 0.0)  # (≥ 0; NaN, never cast: 0)
    return ti.cast(ti.cast(term, ti.f64) * unit + 0.5, ti.i64)


@ti.kernel
def birth_sums(n: ti.i32, v_diff: F1, crest: F1, e_k: F1, vort: F1, tau: F1, dt: ti.f32, unit: ti.f64,
               interleaved: TEMPLATE, total: I64) -> SUMS3:
    """The frame's births per unit multiplier (Ihmsen et al. 2012, eq. 8 summed over the fluid): Σ_i I_k·φ_ta·Δt,
    Σ_i I_k·φ_wc·Δt and Σ_i I_k·φ_vo·Δt, so that G = k_ta·S_ta + k_wc·S_wc + k_vo·S_vo for any multipliers (the
    'auto' budget's birth rate, budget.birth_rate), in units of 1/``unit`` (birth_unit): each term in f32, as the
    births are drawn, then counted as a 64-bit integer. Integers add up to the same bits in any order, so the sum is
    the same for any thread count and layout (on any arch whose f32 terms are the same), and no thread has to walk
    the others' sums: each adds BIRTH_RUN particles, in the layout its arch reads fastest (``interleaved``, a GPU's:
    thread t takes particles t + j·threads, so that neighbouring threads read neighbouring particles; else the
    CPU's, runs of consecutive ones), and adds its sums into ``total`` atomically. (Summed in f64 by blocks and then
    the blocks' sums in order by one thread, that last pass was a loop over n/256 values on one GPU thread.) Nothing
    of the frame's potentials is read back to the host."""
    for c in range(3):
        total[c] = ti.i64(0)
    runs = (n + BIRTH_RUN - 1) // BIRTH_RUN
    for t in range(runs):
        s = ti.Vector([0, 0, 0], ti.i64)
        if ti.static(interleaved):
            for j in range(BIRTH_RUN):
                i = t + j * runs
                if i < n:
                    s += _birth_units(i, v_diff, crest, e_k, vort, tau, dt, unit)
        else:
            for i in range(t * BIRTH_RUN, ti.min(n, (t + 1) * BIRTH_RUN)):
                s += _birth_units(i, v_diff, crest, e_k, vort, tau, dt, unit)
        for c in ti.static(range(3)):
            ti.atomic_add(total[c], s[c])
    return ti.Vector([total[0], total[1], total[2]])


# ---------------------------------------------------------------- obstacles (sim.obstacles' SDFs)
# Diffuse particles and obstacles, static or moving (FoamGenerator._obstacles says what and why):
# - a foam particle within BODY_CONTACT·r of a moving body at the start of a frame rides on it:
#   one fluid-particle diameter, the fluid's own contact with a body (its centres keep r from it);
# - a particle pushed out of an obstacle is put SURFACE_OFFSET·r outside it, where the fluid's
#   centres rest (sim/obstacles.py projects them to sdf = r);
# - spray bouncing off keeps SPRAY_RESTITUTION of its normal speed relative to the body: our
#   choice for the look of droplets glancing off a wet hull, not a measured value (0 makes them
#   slide along it).
BODY_CONTACT = 2.0
SURFACE_OFFSET = 1.0
SPRAY_RESTITUTION = 0.5
# - a particle that moved farther than half an obstacle's SDF cell over the frame is also tested
#   along its path, at most PATH_SAMPLES points (half a cell apart up to 32 cells): a spray drop
#   must not pass through a wall thinner than its flight (an imported tank's walls are one
#   particle spacing thick, a frame's flight is often ten).
PATH_SAMPLES = 64
#: Bisection steps of the crossing of a particle's path with an obstacle's surface (2⁻¹⁶ of the path).
ENTRY_STEPS = 16


@ti.func
def obstacle_sdf(values: F1, off: I1, origin: F3, inv_dx: F1, dims: IV, beyond: F1, rot: M3, trans: F3, o, x: vec3):
    """Signed distance of obstacle o at world point x, the body at the pose (rot[o], trans[o]), and the
    world gradient: sim.obstacles.sdf_sample at x_rest = Rᵀ(x − T), ``beyond[o]`` outside its grid
    (FAR; −FAR for a wall around the fluid, whose SDF is inverted)."""
    xl = rot[o].transpose() @ (x - trans[o])
    d, g = sdf_sample(values, off[o], origin[o], inv_dx[o], dims[o], xl)
    if d >= FAR:
        d = beyond[o]
    return d, rot[o] @ g


@ti.kernel
def obstacles_diffuse(
    nd: ti.i32, x0: F3, x: F3, v: F3, kind: I1, keep: I1,
    values: F1, off: I1, origin: F3, inv_dx: F1, dims: IV, beyond: F1,
    rot0: M3, trans0: F3, rot1: M3, trans1: F3, carry_a: M3, carry_b: F3, vel_a: M3, vel_b: F3, moved: I1,
    r: ti.f32,
):
    """The live particles (keep[p] = 1) against every obstacle in turn, after advection from x0 to x
    (see FoamGenerator._obstacles): riders carried x ← C x0 + c with the body's velocity u = A x + b;
    a path that ends outside but crossed the obstacle ends at its first sample inside (PATH_SAMPLES, at
    most half a cell apart); a bubble inside goes; spray and foam inside are put SURFACE_OFFSET·r out
    from where they crossed the surface (bisection, ENTRY_STEPS) or, if the body came over them, from
    the nearest surface point, spray bouncing (SPRAY_RESTITUTION), foam moving with the body; one that
    is still inside (a crease) goes."""
    for p in range(nd):
        if keep[p]:
            alive = 1
            xp, vp, xs = x[p], v[p], x0[p]
            t = kind[p]
            for o in range(off.shape[0]):
                if alive:
                    ride = 0
                    if moved[o] and t == FOAM:
                        d0, _ = obstacle_sdf(values, off, origin, inv_dx, dims, beyond, rot0, trans0, o, xs)
                        if d0 < BODY_CONTACT * r:
                            ride = 1
                            xp = carry_a[o] @ xs + carry_b[o]
                            vp = vel_a[o] @ xp + vel_b[o]
                    d, _ = obstacle_sdf(values, off, origin, inv_dx, dims, beyond, rot1, trans1, o, xp)
                    seg = xp - xs
                    step = 0.5 / inv_dx[o]
                    length = seg.norm()
                    if not ride and d > 0.0 and length > step:  # the path, first point inside
                        m = ti.min(PATH_SAMPLES, ti.cast(ti.ceil(length / step), ti.i32))
                        for j in range(1, m):
                            q = xs + (j / m) * seg
                            dq, _ = obstacle_sdf(values, off, origin, inv_dx, dims, beyond, rot1, trans1, o, q)
                            if dq <= 0.0:
                                xp, d = q, dq
                                break
                    if d <= 0.0:
                        if t == BUBBLE:
                            alive = 0
                        else:
                            d_start, _ = obstacle_sdf(values, off, origin, inv_dx, dims, beyond, rot1, trans1, o, xs)
                            xh = xp
                            if d_start > 0.0:  # came through the surface: where, by bisection
                                lo, hi = 0.0, 1.0
                                for _step in range(ENTRY_STEPS):
                                    mid = 0.5 * (lo + hi)
                                    dm, _ = obstacle_sdf(values, off, origin, inv_dx, dims, beyond, rot1, trans1, o,
                                                         xs + mid * (xp - xs))
                                    if dm > 0.0:
                                        lo = mid
                                    else:
                                        hi = mid
                                xh = xs + lo * (xp - xs)
                            _, g = obstacle_sdf(values, off, origin, inv_dx, dims, beyond, rot1, trans1, o, xh)
                            nrm = vec3(0.0, 0.0, 1.0)
                            if g.norm() > 1e-12:
                                nrm = g.normalized()
                            if d_start <= 0.0:  # the body came over it: the nearest surface point
                                xh = xp - d * nrm
                            xh += SURFACE_OFFSET * r * nrm
                            u = vel_a[o] @ xh + vel_b[o]
                            vr = vp - u
                            vn = ti.min(vr.dot(nrm), 0.0)
                            vp = u
                            if t == SPRAY:
                                vp = u + vr - (1.0 + SPRAY_RESTITUTION) * vn * nrm
                            xp = xh
                            d_out, _ = obstacle_sdf(values, off, origin, inv_dx, dims, beyond, rot1, trans1, o, xp)
                            if d_out <= 0.0:
                                alive = 0
            x[p], v[p] = xp, vp
            keep[p] = alive


@ti.kernel
def outside_obstacles(
    n: ti.i32, x: F3, flag: I1, values: F1, off: I1, origin: F3, inv_dx: F1, dims: IV, beyond: F1, rot: M3,
    trans: F3,
):
    """flag[p] = 0 where particle p is inside (sdf ≤ 0) an obstacle at this frame's pose."""
    for p in range(n):
        if flag[p]:
            for o in range(off.shape[0]):
                d, _ = obstacle_sdf(values, off, origin, inv_dx, dims, beyond, rot, trans, o, x[p])
                if d <= 0.0:
                    flag[p] = 0
