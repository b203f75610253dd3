"""Position Based Fluids (Macklin & Müller 2013, "Position Based Fluids").

One step, following Algorithm 1 of the paper:

    v  ← v + Δt f_ext                      apply_external_forces
    x* ← x + Δt v                          (same kernel)
    neighbours of x*                       grid.NeighborGrid.build (once per step)
    repeat `iterations` times:
        λ_i  = −C_i / (Σ_k |∇_k C_i|² + ε)  compute_lambda,  C_i = ρ_i/ρ0 − 1
        Δp_i = 1/ρ0 Σ_j (λ_i + λ_j + s_corr) ∇W(x*_i − x*_j)   correct_positions
        x*  ← x* + Δp, then collisions     (same kernel, with the next walls' ψ)
    v ← (x* − x)/Δt                        update_velocity
    XSPH viscosity and vorticity ω         compute_vorticity_and_xsph (one neighbour pass)
    vorticity confinement                  apply_vorticity_confinement
    x ← x*

The density constraint is unilateral, C_i = max(ρ_i/ρ0 − 1, 0) (as in
SPlisHSPlasH): a free surface is under-dense and must not be pulled together.

Boundaries (domain walls and obstacles) contribute to density through a
*density map* (Bender et al. 2019, "Volume maps"), in its planar form: a
particle at distance d from a wall gets ρ0·ψ(d), where ψ(d) is the kernel's
integral over the half space beyond the wall. This removes the density
deficit that would otherwise suck particles onto walls or leave a gap, at the
price of one table lookup per particle and iteration.

All particle state is plain Taichi ndarrays in :class:`FluidState`.
"""


import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, cast

import numpy as np
import taichi as ti

from ..config import Scene
from ..errors import SimulationError, WhitecapError
from ..io import ParticleFrame
from ..io.array_pool import ArrayPool
from ..io.ply import record_dtype
from ..resources import MEMORY_HEADROOM, available_memory
from ..timing import timer
from . import runtime
from .grid import F1, F3, I1, I2, U1, NeighborGrid, gather_i32, gather_vec3, grid_spec, vec3
from .launch import TEMPLATE, KernelGraph, permuted, run_direct
from .records import RecordReader
from .smoothing import SPHKernel, poly6, poly6_np, spiky_grad, spiky_grad_np

if TYPE_CHECKING:  # types only: the driver's build_solver sets them
    from .emitters import Sources
    from .obstacles import Obstacles

PSI_SAMPLES = 128  # samples of the wall density-map table ψ(d), d ∈ [0, h]

# Rows of the solver's ``box`` array, the scene's constant vectors. They reach the
# kernels as one ndarray set once, not as vec3 arguments: Taichi 1.7 marshals each
# vec3 argument in Python at every launch (~25-40 µs each, measured), and the
# step launched 23 of them.
CLAMP_LO, CLAMP_HI = 0, 1  # the walls shrunk by r: where particle centres may go [m]
DOMAIN_LO, DOMAIN_HI = 2, 3  # the walls themselves (density map) [m]
GRAVITY = 4  # g [m/s²]
BOX_ROWS = 5


# ============================================================================ kernels
@ti.kernel
def copy_out(n: ti.i32, x: F3, v: F3, rho: F1, ids: I1, with_rho: ti.i32, xo: F3, vo: F3, rho_o: F1, ids_o: U1):
    """The first n particles' x, v, ρ (with ``with_rho``) and ids into arrays of n rows (host arrays): one
    launch, and only the rows in use of the capacity's."""
    for i in range(n):
        xo[i] = x[i]
        vo[i] = v[i]
        ids_o[i] = ti.cast(ids[i], ti.u32)
        if with_rho:
            rho_o[i] = rho[i]


@ti.kernel
def apply_external_forces(n: ti.i32, x: F3, v: F3, p: F3, box: F3, dt: ti.f32):
    """v ← v + Δt g;  x* ← x + Δt v, kept inside the walls."""
    g = box[GRAVITY]
    for i in range(n):
        v[i] += dt * g
        p[i] = ti.math.clamp(x[i] + dt * v[i], box[CLAMP_LO], box[CLAMP_HI])


@ti.func
def lookup(table: TEMPLATE, d: ti.f32, h: ti.f32) -> ti.f32:
    """Linear interpolation of a table sampled on d ∈ [0, h]."""
    t = ti.math.clamp(d / h, 0.0, 1.0) * (PSI_SAMPLES - 1)
    k = ti.min(ti.cast(ti.floor(t), ti.i32), PSI_SAMPLES - 2)
    f = t - k
    return (1.0 - f) * table[k] + f * table[k + 1]


@ti.func
def wall_share(pi: vec3, lo: vec3, hi: vec3, h: ti.f32, psi_table: TEMPLATE, dpsi_table: TEMPLATE):
    """(ψ, ∇ψ) = (Σ_walls ψ(d), Σ_walls ψ'(d) n_wall) of a point, for the six domain walls."""
    s = 0.0
    g = vec3(0.0)
    for a in ti.static(range(3)):
        d_lo = pi[a] - lo[a]
        if d_lo < h:
            s += lookup(psi_table, d_lo, h)
            g[a] += lookup(dpsi_table, d_lo, h)  # dψ/dd · ∂d/∂x_a (= +1)
        d_hi = hi[a] - pi[a]
        if d_hi < h:
            s += lookup(psi_table, d_hi, h)
            g[a] -= lookup(dpsi_table, d_hi, h)
    return s, g


@ti.kernel
def wall_density_map(n: ti.i32, p: F3, box: F3, h: ti.f32, psi_table: F1, dpsi_table: F1, psi: F1, grad_psi: F3):
    """ψ_i = Σ_walls ψ(d), ∇ψ_i = Σ_walls ψ'(d) n_wall, for the six domain walls.

    ψ is the boundary's share of ρ_i/ρ0; its gradient enters ∇_i C_i.
    """
    for i in range(n):
        s, g = wall_share(p[i], box[DOMAIN_LO], box[DOMAIN_HI], h, psi_table, dpsi_table)
        psi[i] = s
        grad_psi[i] = g


@ti.func
def padded_count(nb_count: TEMPLATE, i, pad: TEMPLATE, list_capacity: TEMPLATE):
    """How far the neighbour loops of particle i run: its count rounded up to the
    grid's padding ``pad`` (the row is padded with i itself, see
    :func:`~whitecap.sim.grid._store_list`), at most ``list_capacity``. Both are
    compile-time constants.

    The rounding spares the scalar remainder loop that LLVM adds after a loop
    vectorised ``pad`` pairs at a time. The min with the capacity changes nothing
    but what LLVM knows: a loop with a known maximum trip count under 128 is
    vectorised without interleaving (8 neighbours a step instead of 8 × 4 = 32),
    and then runs vectorised for the usual 20–40 neighbours instead of falling
    back to its scalar remainder loop. Measured on the position correction at
    115k particles (Taichi 1.7.4 / LLVM 15, x86-64): 8.0 → 4.4 ms a call."""
    return ti.min((nb_count[i] + pad - 1) // pad * pad, list_capacity)


@ti.kernel
def compute_lambda(
    n: ti.i32,
    p: F3,
    nb_count: I1,
    nb: I2,
    psi: F1,
    grad_psi: F3,
    mass: ti.f32,
    rho0: ti.f32,
    h: ti.f32,
    w_poly6: ti.f32,
    w_spiky: ti.f32,
    eps: ti.f32,
    rho: F1,
    lam: F1,
    pad: TEMPLATE,
    list_capacity: TEMPLATE,
):
    """ρ_i = Σ_j m W(x_ij) + ρ0 ψ_i;  C_i = max(ρ_i/ρ0 − 1, 0);
    λ_i = −C_i / (|∇_i C_i|² + Σ_j |∇_j C_i|² + ε),  ∇_j C_i = −m/ρ0 ∇W(x_ij).

    The loop runs over the padded list (:func:`padded_count`); the pads, i
    itself, are left out of the density sum (∇W(0) = 0 leaves the others)."""
    for i in range(n):
        pi = p[i]
        h2 = h * h
        w_sum = poly6(0.0, h2, w_poly6)
        grad_i = vec3(0.0)
        sum_grad2 = 0.0
        for k in range(padded_count(nb_count, i, pad, list_capacity)):  # sums of ∇W; m/ρ0 is applied after the loop
            j = nb[i, k]
            r = pi - p[j]
            w_sum += ti.select(j != i, poly6(r.norm_sqr(), h2, w_poly6), 0.0)
            g = spiky_grad(r, h, w_spiky)
            grad_i += g
            sum_grad2 += g.norm_sqr()
        rho_i = mass * w_sum + rho0 * psi[i]
        vr = mass / rho0
        grad_i = vr * grad_i + grad_psi[i]
        sum_grad2 *= vr * vr
        c = ti.max(rho_i / rho0 - 1.0, 0.0)
        rho[i] = rho_i
        lam[i] = -c / (grad_i.norm_sqr() + sum_grad2 + eps)


@ti.kernel
def correct_positions(
    n: ti.i32,
    p: F3,
    nb_count: I1,
    nb: I2,
    lam: F1,
    mass: ti.f32,
    rho0: ti.f32,
    h: ti.f32,
    w_poly6: ti.f32,
    w_spiky: ti.f32,
    scorr_k: ti.f32,
    scorr_inv_w_dq: ti.f32,
    scorr_n: TEMPLATE,
    box: F3,
    next_walls: ti.i32,
    psi_table: F1,
    dpsi_table: F1,
    psi: F1,
    grad_psi: F3,
    p_out: F3,
    pad: TEMPLATE,
    list_capacity: TEMPLATE,
):
    """Δp_i = m/ρ0 Σ_j (λ_i + λ_j + s_corr) ∇W(x_ij) + λ_i ∇ψ_i,
    s_corr = −k (W(x_ij)/W(Δq))ⁿ (tensile-instability correction);
    x*_i ← x*_i + Δp_i kept inside the walls (``box`` rows CLAMP_LO/HI: the walls shrunk by r),
    written to ``p_out`` (Jacobi: every Δp reads the old x*).

    The neighbour loop runs over the padded list (:func:`padded_count`): a pad
    (i itself) adds nothing, since ∇W(0) = 0.

    With ``next_walls`` set, the same pass also evaluates the walls' density
    map ψ_i, ∇ψ_i at the new x*_i for the next iteration (:func:`wall_share`),
    which saves two passes over the particles per iteration."""
    for i in range(n):
        pi = p[i]
        li = lam[i]
        h2 = h * h
        acc = vec3(0.0)  # Σ_j (λ_i + λ_j − k (W(x_ij)/W(Δq))ⁿ) ∇W(x_ij)
        for k in range(padded_count(nb_count, i, pad, list_capacity)):
            j = nb[i, k]
            r = pi - p[j]
            q = poly6(r.norm_sqr(), h2, w_poly6) * scorr_inv_w_dq  # W(x_ij)/W(Δq)
            qn = 1.0
            for _ in ti.static(range(scorr_n)):
                qn *= q
            acc += (li + lam[j] - scorr_k * qn) * spiky_grad(r, h, w_spiky)
        dp = (mass / rho0) * acc + li * grad_psi[i]
        pn = ti.math.clamp(pi + dp, box[CLAMP_LO], box[CLAMP_HI])
        p_out[i] = pn
        if next_walls:
            s, g = wall_share(pn, box[DOMAIN_LO], box[DOMAIN_HI], h, psi_table, dpsi_table)
            psi[i] = s
            grad_psi[i] = g


@ti.kernel
def confine_to_domain(n: ti.i32, p: F3, box: F3):
    """p ← p kept inside the walls (the starting positions; the step clamps x* as it predicts it)."""
    for i in range(n):
        p[i] = ti.math.clamp(p[i], box[CLAMP_LO], box[CLAMP_HI])


@ti.kernel
def update_velocity(n: ti.i32, x: F3, p: F3, v: F3, inv_dt: ti.f32, box: F3, wall_friction: ti.f32):
    """v ← (x* − x)/Δt; tangential damping for particles touching a wall."""
    lo, hi = box[CLAMP_LO], box[CLAMP_HI]
    for i in range(n):
        vi = (p[i] - x[i]) * inv_dt
        touching = 0
        for a in ti.static(range(3)):
            if p[i][a] <= lo[a] + 1e-7 or p[i][a] >= hi[a] - 1e-7:
                touching = 1
        if touching == 1:
            vi *= 1.0 - wall_friction
        v[i] = vi


@ti.kernel
def compute_vorticity_and_xsph(
    n: ti.i32,
    p: F3,
    v: F3,
    nb_count: I1,
    nb: I2,
    rho: F1,
    mass: ti.f32,
    h: ti.f32,
    w_poly6: ti.f32,
    w_spiky: ti.f32,
    c: ti.f32,
    omega: F3,
    v_out: F3,
    pad: TEMPLATE,
    list_capacity: TEMPLATE,
):
    """One pass over the neighbours of the updated velocities:
    ω_i = ∇×v = Σ_j (m/ρ_j) ∇W(x_ij) × (v_j − v_i)            (vorticity)
    v_i ← v_i + c Σ_j (m/ρ_j) (v_j − v_i) W(x_ij)              (XSPH viscosity)
    over the padded list (:func:`padded_count`; a pad has v_j − v_i = 0)."""
    for i in range(n):
        h2 = h * h
        w = vec3(0.0)
        acc = vec3(0.0)
        for k in range(padded_count(nb_count, i, pad, list_capacity)):
            j = nb[i, k]
            r = p[i] - p[j]
            vj_i = (mass / rho[j]) * (v[j] - v[i])
            w += spiky_grad(r, h, w_spiky).cross(vj_i)
            acc += vj_i * poly6(r.norm_sqr(), h2, w_poly6)
        omega[i] = w
        v_out[i] = v[i] + c * acc


@ti.kernel
def apply_vorticity_confinement(
    n: ti.i32,
    p: F3,
    nb_count: I1,
    nb: I2,
    rho: F1,
    omega: F3,
    mass: ti.f32,
    h: ti.f32,
    w_spiky: ti.f32,
    eps: ti.f32,
    dt: ti.f32,
    v: F3,
    pad: TEMPLATE,
    list_capacity: TEMPLATE,
):
    """η = ∇|ω| = Σ_j (m/ρ_j)(|ω_j| − |ω_i|) ∇W(x_ij),  N = η/|η|,
    f_vorticity = ε (N × ω_i);  v ← v + Δt f,
    over the padded list (:func:`padded_count`; a pad has ∇W(0) = 0)."""
    for i in range(n):
        wi = omega[i].norm()
        eta = vec3(0.0)
        for k in range(padded_count(nb_count, i, pad, list_capacity)):
            j = nb[i, k]
            eta += (mass / rho[j]) * (omega[j].norm() - wi) * spiky_grad(p[i] - p[j], h, w_spiky)
        ln = eta.norm()
        if ln > 1e-9:
            v[i] += dt * eps * (eta / ln).cross(omega[i])


@ti.kernel
def max_speed_and_nans(n: ti.i32, x: F3, v: F3) -> ti.math.vec2:
    """(max |v|, number of non-finite particles)."""
    vmax = 0.0
    bad = 0.0
    for i in range(n):
        s = v[i].norm()
        q = x[i].sum()
        if not (s == s and q == q) or ti.abs(s) > 1e30 or ti.abs(q) > 1e30:
            bad += 1.0
        else:
            ti.atomic_max(vmax, s)
    return ti.math.vec2(vmax, bad)


# ============================================================================ setup
def block_lattice(scene: Scene, b) -> np.ndarray:
    """Lattice sites (spacing 2r, one radius in from the faces) of one fluid block, float64."""
    r = scene.solver.particle_radius
    lo, hi = b.bounds()
    axes = [np.arange(lo[a] + r, hi[a] - r + 1e-6 * r, 2.0 * r, dtype=np.float64) for a in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    if b.shape == "sphere":
        g = g[np.linalg.norm(g - np.asarray(b.center), axis=1) <= b.radius]
    return g


def lattice_points(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities of the initial fluid: a cubic lattice of spacing 2r."""
    pos, vel = [], []
    for b in scene.fluid:
        g = block_lattice(scene, b)
        pos.append(g)
        vel.append(np.broadcast_to(np.asarray(b.velocity, np.float64), g.shape))
    if not pos:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    return np.concatenate(pos).astype(np.float32), np.concatenate(vel).astype(np.float32)


def estimate_particle_count(scene: Scene) -> int:
    """Particle count from the fluid blocks, without allocating them."""
    r = scene.solver.particle_radius
    d = 2.0 * r
    total = 0.0
    for b in scene.fluid:
        lo, hi = b.bounds()
        cnt = 1.0
        for a in range(3):
            cnt *= max(0.0, math.floor((hi[a] - lo[a] - 2 * r) / d + 1e-6) + 1)
        if b.shape == "sphere":
            cnt *= math.pi / 6.0  # sphere / bounding cube
        total += cnt
    return int(total)


def bytes_per_particle(max_neighbors: int) -> int:
    """Device memory per particle: state (x, x*, v, v_tmp, ∇ψ or ω: 5 vec3; ρ, λ, ψ, id: 4
    scalars) plus grid (cell, rank, order, sorted copy of x*, count, neighbours)."""
    return 4 * (STATE_WORDS + 7 + max_neighbors)


STATE_WORDS = 5 * 3 + 4  # 4-byte words of FluidState per particle
#: A fluid file's vertex record (io.ply.record_dtype of a frame of fluid particles: x y z vx vy vz density id,
#: 32 bytes), made on the device from the solver's state by sim.records (PBFSolver.arrays' ``records``): a, b the
#: positions and velocities, c the density, d the ids (int32, their bits written as uint32).
FLUID_RECORD = record_dtype(ParticleFrame(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                                          np.zeros(0, np.uint32), np.zeros(0, np.float32)))
FLUID_RECORD_SOURCES = {"x": ("a", 0), "y": ("a", 1), "z": ("a", 2), "vx": ("b", 0), "vy": ("b", 1), "vz": ("b", 2),
                        "density": ("c", 0), "id": ("d", 0)}


def fits_in_memory(n: int, max_neighbors: int) -> tuple[bool, int]:
    """(whether ``n`` particles fit in MEMORY_HEADROOM of the free memory, the bytes they need). The rest
    stays for the interpreter, NumPy copies of frames being written, Taichi's runtime, the foam stage
    and the operating system, so a run that passes the check does not push the machine into swap."""
    need = n * bytes_per_particle(max_neighbors)
    return need <= MEMORY_HEADROOM * available_memory(), need


def half_space_tables(h: float) -> tuple[np.ndarray, np.ndarray]:
    """ψ(d) = ∫_{z > d} W dV, the share of ρ/ρ0 that a solid half space at
    distance d contributes (W integrates to 1), and its derivative ψ'(d), sampled
    on d ∈ [0, h]. Integrated numerically once at set-up, plane by plane; the
    half space stands in for the lattice layers missing beyond a wall."""
    ds = np.linspace(0.0, h, PSI_SAMPLES)
    zs = np.linspace(0.0, h, 2001)
    # ∫∫ W over a plane at height z below the particle: 2π ∫ W(√(z²+ρ²)) ρ dρ
    rho_ = np.linspace(0.0, h, 2001)
    trapz = getattr(np, "trapezoid", None) or np.trapz  # numpy 2 renamed it
    plane = np.array([trapz(2 * np.pi * rho_ * poly6_np(z * z + rho_ * rho_, h), rho_) for z in zs])
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (plane[1:] + plane[:-1]) * np.diff(zs))])  # ∫_0^z plane
    total = cum[-1]
    psi = np.interp(ds, zs, total - cum)  # ∫_{d}^{h} plane(z) dz
    dpsi = -np.interp(ds, zs, plane)  # dψ/dd
    return psi.astype(np.float32), dpsi.astype(np.float32)


def lattice_calibration(h: float, spacing: float) -> tuple[float, float]:
    """Σ_j W and Σ_j |∇W|² over a full cubic lattice of this spacing.

    The particle mass is set so that the lattice is exactly at rest density
    (m = ρ0 / ΣW), and the second sum sets the scale of λ for s_corr and ε."""
    k = int(math.ceil(h / spacing)) + 1
    ax = np.arange(-k, k + 1) * spacing
    g = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    r2 = (g * g).sum(1)
    sum_w = float(poly6_np(r2, h).sum())
    grads = spiky_grad_np(g, h)
    sum_g2 = float((grads * grads).sum())
    return sum_w, sum_g2


# ============================================================================ state
@dataclass
class FluidState:
    """Particle state: plain ndarrays of capacity ``n`` (Taichi's, typed Any)."""

    n: int
    x: Any  # positions                         vec3 [m]
    p: Any  # predicted positions x*            vec3 [m]
    v: Any  # velocities                        vec3 [m/s]
    v_tmp: Any  # scratch (XSPH output, corrected x*, reorder) vec3
    grad_psi: Any  # ∇ of boundary density share vec3 [1/m]; after the constraints: vorticity ω [1/s]
    rho: Any  # density ρ                        f32 [kg/m³]
    lam: Any  # Lagrange multipliers λ           f32 [m²]
    psi: Any  # boundary density share ψ         f32 [-]
    ids: Any  # persistent particle ids          i32

    @classmethod
    def allocate(cls, n: int) -> "FluidState":
        v3 = lambda: ti.Vector.ndarray(3, ti.f32, n)  # noqa: E731
        f1 = lambda: ti.ndarray(ti.f32, n)  # noqa: E731
        i1 = lambda: ti.ndarray(ti.i32, n)  # noqa: E731
        return cls(n, v3(), v3(), v3(), v3(), v3(), f1(), f1(), f1(), i1())


@dataclass
class StepStats:
    max_speed: float = 0.0
    neighbor_overflow: int = 0
    steps: int = 0


class PBFSolver:
    """Owns the fluid state, the neighbour grid and the step.

    ``colliders`` are objects with ``apply_forces(solver, dt)`` (before
    prediction), ``add_density_map(solver)`` (start of each iteration: project
    particles out, then add to ψ/∇ψ), ``project(solver)`` (after the last
    iteration) and ``respond(solver)`` (velocity response): the obstacle
    module plugs in there.
    """

    def __init__(self, scene: Scene, positions: np.ndarray, velocities: np.ndarray, ids: np.ndarray | None = None,
                 capacity: int | None = None):
        s = scene.solver
        self.scene = scene
        n = len(positions)
        if n == 0 and not scene.emitter:
            raise WhitecapError("the scene has no fluid: add a [[fluid]] block or an [[emitter]]")
        # The arrays hold ``capacity`` particles, of which the first ``n`` live: emitters add at the
        # end, sinks remove by compaction (sim/emitters.py).
        self.capacity = max(n, 1, int(capacity or 0))
        fits, need = fits_in_memory(self.capacity, s.max_neighbors)
        if not fits:
            raise WhitecapError(
                f"{n} particles need about {need / 2**30:.1f} GiB, more than this machine has free; "
                "increase solver.particle_radius or shrink the fluid blocks"
            )
        self.n = n
        self.r = s.particle_radius
        self.h = s.kernel_support * s.particle_radius
        self.rho0 = s.rest_density
        sum_w, sum_g2 = lattice_calibration(self.h, 2.0 * self.r)
        self.mass = self.rho0 / sum_w
        # λ scale of a full lattice neighbourhood: λ_ref = 1 / Σ_j |∇_j C|².
        self.lambda_ref = 1.0 / ((self.mass / self.rho0) ** 2 * sum_g2)
        self.eps = s.relaxation / self.lambda_ref
        self.scorr_k = s.scorr_k * self.lambda_ref
        self.scorr_inv_w_dq = 1.0 / float(poly6_np((s.scorr_dq * self.h) ** 2, self.h))
        self.kernel = SPHKernel(self.h)
        lo, hi = np.asarray(scene.domain.lower), np.asarray(scene.domain.upper)
        self.box = ti.Vector.ndarray(3, ti.f32, BOX_ROWS)
        box = np.zeros((BOX_ROWS, 3), np.float32)
        box[CLAMP_LO], box[CLAMP_HI] = lo + self.r, hi - self.r
        box[DOMAIN_LO], box[DOMAIN_HI], box[GRAVITY] = lo, hi, scene.domain.gravity
        self.box.from_numpy(box)
        psi, dpsi = half_space_tables(self.h)
        self.psi_table = ti.ndarray(ti.f32, PSI_SAMPLES)
        self.dpsi_table = ti.ndarray(ti.f32, PSI_SAMPLES)
        self.psi_table.from_numpy(psi)
        self.dpsi_table.from_numpy(dpsi)

        self.state = FluidState.allocate(self.capacity)
        # the host arrays frames are read back into (arrays), used again once no frame handed out holds them
        pin, unpin = runtime.host_pinning()  # page-locked for the GPU's copies, where that is on
        self._frames = ArrayPool({"x": (np.float32, (3,)), "v": (np.float32, (3,)), "rho": (np.float32, ()),
                                  "ids": (np.uint32, ())}, pin=pin, unpin=unpin)
        # a frame's fluid file's records, made on the device (arrays(records=True))
        self._records = RecordReader(FLUID_RECORD, FLUID_RECORD_SOURCES, pin=pin, unpin=unpin)
        st = self.state
        ids = np.arange(n, dtype=np.int32) if ids is None else np.asarray(ids, np.int32)
        self._upload(positions, velocities, ids)
        self.next_id = int(ids.max()) + 1 if n else 0  # the id the next emitted particle takes
        self.sources: Sources | None = None  # emitters and sinks (sim/emitters.py), set by build_solver
        confine_to_domain(n, st.x, self.box)
        self.grid = NeighborGrid(grid_spec(lo, hi, self.h / 2), self.capacity, s.max_neighbors, self.h)
        self.colliders: list = []
        self.obstacles: Obstacles | None = None  # the scene's (set by build_solver), for the frame hooks
        # The step's phases run as Taichi compute graphs (sim/launch.py), one per phase and
        # structure; off, they launch kernel by kernel (the same launches, for comparison).
        self.use_graph = True
        self._graphs: dict = {}
        self.step_count = 0
        self.time = 0.0
        self.stats = StepStats()

    # ---------------------------------------------------------------- parameters
    @property
    def params(self):
        return self.scene.solver

    def memory_bytes(self) -> int:
        return self.capacity * 4 * STATE_WORDS + self.grid.nbytes() + self._records.nbytes

    def _upload(self, x, v, ids) -> None:
        """The live particles' state, padded with zeros up to the capacity."""
        st, n = self.state, len(x)
        for arr, a, dt in ((st.x, x, np.float32), (st.v, v, np.float32), (st.ids, ids, np.int32)):
            a = np.asarray(a, dt)
            if self.capacity > n:
                a = np.concatenate([a.reshape((n,) + a.shape[1:]), np.zeros((self.capacity - n,) + a.shape[1:], dt)])
            arr.from_numpy(np.ascontiguousarray(a))

    # ---------------------------------------------------------------- one step
    def reorder(self) -> None:
        """Permute particle data into cell order, for memory locality."""
        st, n = self.state, self.n
        self.grid.sort(st.x, n)
        order = self.grid.order
        gather_vec3(n, order, st.x, st.v_tmp)
        st.x, st.v_tmp = st.v_tmp, st.x
        gather_vec3(n, order, st.v, st.v_tmp)
        st.v, st.v_tmp = st.v_tmp, st.v
        # The grid's rank array (scratch of the sort, free until the next one) takes the gathered ids.
        gather_i32(n, order, st.ids, self.grid.rank)
        st.ids, self.grid.rank = self.grid.rank, st.ids

    def bindings(self, dt: float) -> dict:
        """Everything the step's recorded launches read, by name (see sim/launch.py): the state's
        arrays (``x``, ``p``, ``v``, ``t`` the scratch, ``omega``: ∇ψ's array, which holds ω after
        the constraints), the grid's (``g.*``), the colliders' (``c0.*``, …) and the scalars."""
        s, st = self.params, self.state
        b = {
            "n": self.n, "x": st.x, "p": st.p, "v": st.v, "t": st.v_tmp, "omega": st.grad_psi,
            "rho": st.rho, "lam": st.lam, "psi": st.psi, "grad_psi": st.grad_psi,
            "box": self.box, "psi_table": self.psi_table, "dpsi_table": self.dpsi_table,
            "dt": float(dt), "inv_dt": 1.0 / dt if dt > 0 else 0.0, "r": self.r, "h": self.h, "mass": self.mass,
            "rho0": self.rho0, "w_poly6": self.kernel.poly6, "w_spiky": self.kernel.spiky, "eps": self.eps,
            "scorr_k": self.scorr_k, "scorr_inv_w_dq": self.scorr_inv_w_dq, "walls_next": 1, "walls_last": 0,
            "wall_friction": float(s.wall_friction), "xsph_c": float(s.xsph_c),
            "vorticity_epsilon": float(s.vorticity_epsilon),
            **self.grid.bindings(),
        }
        for k, c in enumerate(self.colliders):
            b.update(c.bindings(f"c{k}."))
        return b

    def record_colliders(self, rec, what: str) -> None:
        """Each collider's recorded launches ``what`` (record_forces, …), its bindings named ``c<k>.``."""
        for k, c in enumerate(self.colliders):
            getattr(c, what)(rec, f"c{k}.")

    # Recorded launches (sim/launch.py): each phase of the step is written once, as calls
    # rec(kernel, *args), and runs as a compute graph or kernel by kernel.
    def record_boundary_density(self, rec) -> None:
        """ψ, ∇ψ of the walls at x*, then each collider's projection and density map."""
        r = rec
        rec(wall_density_map, r["n"], r["p"], r["box"], r["h"], r["psi_table"], r["dpsi_table"], r["psi"],
            r["grad_psi"])
        self.record_colliders(rec, "record_density_map")

    def record_lambda(self, rec) -> None:
        r = rec
        rec(compute_lambda, r["n"], r["p"], r["g.nb_count"], r["g.nb"], r["psi"], r["grad_psi"], r["mass"],
            r["rho0"], r["h"], r["w_poly6"], r["w_spiky"], r["eps"], r["rho"], r["lam"], self.grid.pad,
            self.grid.max_neighbors)

    def record_predict(self, rec) -> None:
        r = rec
        self.record_colliders(rec, "record_forces")
        rec(apply_external_forces, r["n"], r["x"], r["v"], r["p"], r["box"], r["dt"])

    def record_neighbours(self, rec) -> None:
        self.grid.record_build(rec, rec["p"], rec["n"])

    def record_constraints(self, rec, iterations: int) -> None:
        r, s = rec, self.params
        self.record_boundary_density(rec)
        for it in range(iterations):
            if it > 0:  # the walls' share came with the previous correction
                self.record_colliders(rec, "record_density_map")
            self.record_lambda(rec)
            rec(
                correct_positions, r["n"], r["p"], r["g.nb_count"], r["g.nb"], r["lam"], r["mass"], r["rho0"], r["h"],
                r["w_poly6"], r["w_spiky"], r["scorr_k"], r["scorr_inv_w_dq"], s.scorr_n, r["box"],
                r["walls_next" if it + 1 < iterations else "walls_last"], r["psi_table"], r["dpsi_table"],
                r["psi"], r["grad_psi"], r["t"], self.grid.pad, self.grid.max_neighbors,
            )
            rec.swap("p", "t")
        # Colliders project at the start of each iteration (fused with their
        # density map, see record_boundary_density) and once more here: the last
        # Δp pushes particles back inside the contact distance r, and
        # x ← x* must keep it (test_no_particle_ends_a_step_closer_than_its_radius).
        self.record_colliders(rec, "record_project")

    def record_velocity(self, rec) -> None:
        r = rec
        rec(update_velocity, r["n"], r["x"], r["p"], r["v"], r["inv_dt"], r["box"], r["wall_friction"])
        self.record_colliders(rec, "record_respond")

    def record_vorticity_xsph(self, rec, confinement: bool) -> None:
        """ω and XSPH share one neighbour pass (both read the velocities after the
        position update); confinement then uses ω of the neighbours and is added on
        top of the XSPH-smoothed velocity. ω is kept in ∇ψ's array: ∇ψ is dead once
        the constraints are done (recomputed before the next step's first λ), which
        saves 12 B a particle."""
        r = rec
        rec(compute_vorticity_and_xsph, r["n"], r["p"], r["v"], r["g.nb_count"], r["g.nb"], r["rho"], r["mass"],
            r["h"], r["w_poly6"], r["w_spiky"], r["xsph_c"], r["omega"], r["t"], self.grid.pad,
            self.grid.max_neighbors)
        rec.swap("v", "t")
        if confinement:
            rec(apply_vorticity_confinement, r["n"], r["p"], r["g.nb_count"], r["g.nb"], r["rho"], r["omega"],
                r["mass"], r["h"], r["w_spiky"], r["vorticity_epsilon"], r["dt"], r["v"], self.grid.pad,
                self.grid.max_neighbors)

    def _phases(self) -> list[tuple[str, tuple, Callable[[Any], None]]]:
        """(timer name, structure key, record function) of each phase of a step, for the
        current parameters: a phase's graph is compiled once per structure key."""
        s = self.params
        phases: list[tuple[str, tuple, Callable[[Any], None]]] = [
            ("pbf.predict", (), self.record_predict),
            ("pbf.neighbours", (), self.record_neighbours),
            ("pbf.constraints", (s.iterations,), lambda rec: self.record_constraints(rec, s.iterations)),
            ("pbf.velocity", (), self.record_velocity),
        ]
        if s.vorticity_epsilon > 0 or s.xsph_c > 0:
            conf = s.vorticity_epsilon > 0
            phases.append(("pbf.vorticity_xsph", (conf,), lambda rec: self.record_vorticity_xsph(rec, conf)))
        return phases

    def _run_phase(self, name: str, key: tuple, record, bindings: dict) -> dict:
        """Launch one phase (as a compute graph unless ``use_graph`` is off); returns the
        bindings with the roles the phase swapped (ping-pong buffers) permuted."""
        graph = self._graphs.get((name, key)) if self.use_graph else None
        if self.use_graph and graph is None:
            try:
                graph = self._graphs[(name, key)] = KernelGraph(record)
            except Exception as e:  # a backend without compute graphs: the same launches one by one
                from ..progress import console

                why = str(e).splitlines()[0] if str(e) else ""
                console.print(f"[yellow]warning:[/] no Taichi compute graph on this backend ({type(e).__name__}: "
                              f"{why}); launching kernel by kernel", soft_wrap=True)
                self.use_graph = False
        if graph is not None:
            roles = graph.run(bindings)
        else:
            roles = run_direct(record, bindings)
        return permuted(bindings, roles) if roles else bindings

    def boundary_density(self) -> None:
        run_direct(self.record_boundary_density, self.bindings(0.0))

    def compute_lambda(self) -> None:
        run_direct(self.record_lambda, self.bindings(0.0))

    def step(self, dt: float) -> None:
        s, st = self.params, self.state
        if self.sources:
            with timer("pbf.emit"):
                self.sources.emit(self)  # the particles due by now enter at the emitters' faces
        if s.reorder_interval and self.step_count % s.reorder_interval == 0:
            with timer("pbf.reorder"):
                self.reorder()
        for c in self.colliders:
            c.prepare(self, dt)  # host work: poses of moving bodies, their momentum sums cleared
        b = self.bindings(dt)
        for name, key, record in self._phases():
            with timer(name):
                b = self._run_phase(name, key, record, b)
        st.x, st.p, st.v, st.v_tmp = b["p"], b["x"], b["v"], b["t"]  # x ← x* (and the ping-pong's end)
        for c in self.colliders:
            c.finish_step(self)  # host work: the bodies' reactions
        if self.sources:
            with timer("pbf.sink"):
                self.sources.drain(self)  # no particle ends a step inside a sink
        self.step_count += 1
        self.time += dt

    def take_overflow(self) -> int:
        """Neighbour pairs that did not fit the lists since the last call."""
        k = self.grid.take_overflow()
        self.stats.neighbor_overflow += k
        return k

    # ---------------------------------------------------------------- frames
    def max_speed(self) -> tuple[float, int]:
        r = max_speed_and_nans(self.n, self.state.x, self.state.v)
        return float(r[0]), int(r[1])

    def substeps_for_frame(self) -> int:
        """Fixed substeps, or Δt ≤ min(cfl·2r / v_max, √(gravity_dt_limit·2r/|g|))."""
        s = self.params
        if s.substeps is not None:
            return s.substeps
        frame_dt = 1.0 / s.frame_rate
        vmax, _ = self.max_speed()
        # Speed expected by the end of the frame under gravity alone.
        v_est = vmax + float(np.linalg.norm(self.scene.domain.gravity)) * frame_dt
        dt_cfl = s.cfl * 2.0 * self.r / max(v_est, 1e-6)
        g = float(np.linalg.norm(self.scene.domain.gravity))
        dt_g = math.sqrt(s.gravity_dt_limit * 2.0 * self.r / g) if g > 0 else frame_dt
        return int(min(max(math.ceil(frame_dt / min(dt_cfl, dt_g)), s.min_substeps), s.max_substeps))

    def advance_frame(self, frame_index: int) -> int:
        """Advance one output frame; raise SimulationError on blow-up."""
        s = self.params
        nsub = self.substeps_for_frame()
        dt = 1.0 / s.frame_rate / nsub
        for _ in range(nsub):
            self.step(dt)
        runtime.device_idle()  # the frame's steps run on a GPU while the writer's thread writes (the GIL let go)
        self.take_overflow()
        vmax, bad = self.max_speed()
        self.stats.max_speed = vmax
        if bad or vmax > s.max_speed:
            what = f"{bad} particles became NaN" if bad else f"max speed {vmax:.3g} m/s exceeds solver.max_speed"
            raise SimulationError(
                f"simulation blew up at frame {frame_index} (t={self.time:.4f} s): {what}; "
                "try more substeps, more iterations or a smaller cfl"
            )
        return nsub

    def update_density(self) -> None:
        """Density at the current positions (for output and statistics)."""
        st, g = self.state, self.grid
        st.p.copy_from(st.x)
        g.build(st.p, self.n)
        self.boundary_density()
        self.compute_lambda()

    # ---------------------------------------------------------------- io
    def arrays(self, with_density: bool = True, records: bool = False) -> dict[str, np.ndarray | None]:
        """The particles in use as host arrays that no frame handed out before and still held anywhere shares
        (positions, velocities, density or None, uint32 ids; io.array_pool: blocks used again once the writer is
        done with them, not new pages every frame): read back in one launch, n rows (not the capacity's, which an
        emitter's scene keeps for the particles to come). :meth:`checkpoint` can be handed them (``host``) rather
        than read the device anew. With ``records`` (and the density), they are made on the device as the fluid
        file's records (FLUID_RECORD, sim.records) and read back in one copy, the arrays views of them, which are
        under ``records`` too: the PLY writer writes them as they are (ParticleFrame.from_records)."""
        st, n = self.state, self.n
        if with_density:
            self.update_density()
        if records and with_density and self._records.fits(n):
            frame, _ = self._records.read(n, (st.x, st.v, st.rho, st.ids, st.ids, 0), self.capacity)
            return {"positions": frame.positions, "velocities": frame.velocities, "density": frame.density,
                    "ids": frame.ids, "records": frame.records}
        h = self._frames.take(n)
        x, v, ids = h["x"], h["v"], h["ids"]
        rho = h["rho"] if with_density else np.empty(0, np.float32)
        # on CUDA straight from the device, one copy each (the solver's int32 ids keep their bits as uint32)
        rows = [(x, st.x), (v, st.v), (ids, st.ids)] + ([(rho, st.rho)] if with_density else [])
        if n and not runtime.rows_to_host(*rows):
            # (never an empty array handed to a kernel: a row stands in for the unread density)
            copy_out(n, st.x, st.v, st.rho, st.ids, int(with_density), x, v,
                     rho if with_density else np.empty(1, np.float32), ids)
        return {"positions": x, "velocities": v, "density": rho if with_density else None, "ids": ids}

    def checkpoint(self, host: dict[str, np.ndarray | None] | None = None) -> dict[str, np.ndarray | np.generic]:
        """The state to resume from. ``host``: what :meth:`arrays` returned for the state as it stands (the
        frame just written), taken instead of reading the particles back again."""
        a = host if host is not None else self.arrays(with_density=False)
        x, v, ids = (cast(np.ndarray, a[k]) for k in ("positions", "velocities", "ids"))
        return {
            "x": x,
            "v": v,
            "ids": ids.view(np.int32),  # the solver's own type (restore reads them as such)
            "next_id": np.int64(self.next_id),
            "step_count": np.int64(self.step_count),
            "time": np.float64(self.time),
            **({f"sources_{k}": a for k, a in self.sources.checkpoint().items()} if self.sources else {}),
            **{f"collider{k}_{name}": a for k, c in enumerate(self.colliders) if hasattr(c, "checkpoint")
               for name, a in c.checkpoint().items()},
        }

    def restore(self, ck: dict) -> None:
        ids = np.asarray(ck["ids"], np.int32)
        if len(ids) > self.capacity:
            raise WhitecapError(f"the checkpoint holds {len(ids):,} particles, more than the capacity "
                                f"{self.capacity:,}; raise solver.max_particles")
        self.n = len(ids)
        self._upload(ck["x"], ck["v"], ids)
        self.next_id = int(ck["next_id"]) if "next_id" in ck else (int(ids.max()) + 1 if len(ids) else 0)
        if self.sources:
            self.sources.restore({k[len("sources_"):]: a for k, a in ck.items() if k.startswith("sources_")})
        self.step_count = int(ck["step_count"])
        self.time = float(ck["time"])
        for k, c in enumerate(self.colliders):  # moving bodies: their state, then their pose at that time
            if hasattr(c, "restore"):
                c.restore({key[len(f"collider{k}_"):]: a for key, a in ck.items() if key.startswith(f"collider{k}_")})
            if hasattr(c, "poses_at"):
                c.poses_at(self.time)
