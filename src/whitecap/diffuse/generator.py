"""The diffuse-particle state and one frame of its evolution.

    state = DiffuseState.empty()
    gen = FoamGenerator(params, radius=r, domain=(lo, hi), gravity=g, seed=s)
    diffuse_frame = gen.step(fluid_frame, index, dt)

``step`` is the same code inside ``simulate`` and in post-processing, so the
same fluid frames and seed give byte-identical diffuse particles.
Per frame: (1) existing diffuse particles are classified by their fluid
neighbours and advected by type; expired particles, dissipated foam and
escapees are removed; (2) each fluid particle generates into its own run of the new particles
(offsets from a prefix sum of the counts), the new particles are classified
and thinned by their type's multiplier; (3) survivors and the new particles
are compacted in a fixed order (survivors first, then the new ones in fluid
order), so no global counter is needed. 'auto' thresholds and multipliers: :mod:`.budget`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import taichi as ti
from taichi.lang.util import to_numpy_type

from ..io import ParticleFrame
from ..io.diffuse_types import BUBBLE, FOAM, SPRAY
from ..progress import console
from ..sim import runtime
from ..sim.grid import NeighborGrid, grid_spec
from ..timing import timer
from . import budget as B
from . import kernels as K
from . import splishsplash as SP
from .params import FoamParams

SURFACE_FRACTION = 0.25  # |Σ x̂ W̃| / Σ W̃ above which a particle counts as on the surface
# Neighbour-list length per fluid particle: a lattice of spacing 2r has 4/3·π·(h/2r)³ ≈ 34
# neighbours within h = 4r; 96 leaves ~3× room for water compressed in a splash.
MAX_FLUID_NEIGHBOURS = 96
# Draw numbers of the per-particle random streams used outside the kernels
# (the kernels use draws 0-4 of the (seed, frame, id, slot) counter).
DRAW_LIFE, DRAW_DISSIPATE = 6, 7
ROUNDING_SLOT = 0xFFFF  # the slot number of kernels.generate's stochastic-rounding draw
# Diffuse particles and obstacles (static or moving), see FoamGenerator._obstacles:
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
# The fluid neighbour grid, when the fluid outgrows it (inflow), is rebuilt this many times larger
# (not at the new count exactly, which would allocate a grid every frame of a steady inflow).
GRID_GROWTH = 1.25


@dataclass
class DiffuseState:
    positions: np.ndarray
    velocities: np.ndarray
    lifetime: np.ndarray
    ids: np.ndarray
    next_id: int = 0
    counts: list = field(default_factory=list)  # rows (frame, time, spray, foam, bubbles)
    tau: np.ndarray | None = None  # thresholds set by 'auto' mode
    scale: float = 1.0  # 'auto': the preset's multipliers are scaled by this for the budget
    # 'auto' in the simulation: the potentials (ta, wc, ke, vo) and whether it moves of sampled fluid
    # particles of the frames so far, for thresholds pooled over them and so the rates of past
    # frames can be recomputed whenever the thresholds rise: at most budget.HISTORY_ROWS rows,
    # each holding history_frames[j] frames, history_stride per full row (budget.history_add)
    history: np.ndarray = field(default_factory=lambda: B.history_empty()[0])
    history_frames: np.ndarray = field(default_factory=lambda: B.history_empty()[1])
    history_stride: int = 1
    # peak diffuse-to-fluid ratios so far: all types (its frame), then spray, foam, bubbles at their own peaks
    peaks: np.ndarray = field(default_factory=lambda: np.array([0.0, -1.0, 0.0, 0.0, 0.0]))
    # 'auto': spray, foam, bubbles' generation scaled by these on top of ``scale``, so each type
    # takes its share of the budget (budget.type_scales)
    type_scale: np.ndarray = field(default_factory=lambda: np.ones(3))
    # 'auto': per frame, its time, the new spray, foam, bubbles and the type scales they were made with
    # (the frames that still count: budget.born_add)
    born: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    # 'auto': how many times faster foam's lifetime counts down, so that foam fed by landing spray
    # and surfacing bubbles keeps to its share (budget.foam_aging)
    foam_aging: float = 1.0

    @classmethod
    def empty(cls) -> "DiffuseState":
        z = np.zeros((0, 3), np.float32)
        return cls(z, z.copy(), np.zeros(0, np.float32), np.zeros(0, np.uint32))

    def to_arrays(self) -> dict[str, np.ndarray]:
        d = {
            "positions": self.positions, "velocities": self.velocities, "lifetime": self.lifetime, "ids": self.ids,
            "next_id": np.int64(self.next_id), "counts": np.asarray(self.counts, np.float64).reshape(-1, 5),
        }
        if self.tau is not None:
            d["tau"] = self.tau
        d["scale"], d["history"], d["peaks"] = np.float64(self.scale), self.history, self.peaks
        d["history_frames"], d["history_stride"] = self.history_frames, np.int64(self.history_stride)
        d["type_scale"] = np.asarray(self.type_scale, np.float64)
        d["born"] = np.asarray(self.born, np.float64)
        d["foam_aging"] = np.float64(self.foam_aging)
        return d

    @classmethod
    def from_arrays(cls, d: dict) -> "DiffuseState":
        return cls(
            np.asarray(d["positions"], np.float32), np.asarray(d["velocities"], np.float32),
            np.asarray(d["lifetime"], np.float32), np.asarray(d["ids"], np.uint32), int(d["next_id"]),
            [tuple(r) for r in np.asarray(d["counts"]).tolist()], np.asarray(d["tau"], np.float32) if "tau" in d else None,
            float(d.get("scale", 1.0)),
            *_history(d),
            np.asarray(d.get("peaks", [0.0, -1.0, 0.0, 0.0, 0.0]), np.float64),
            np.asarray(d.get("type_scale", np.ones(3)), np.float64),
            np.asarray(d.get("born", np.zeros((0, 7))), np.float64).reshape(-1, 7),
            float(d.get("foam_aging", 1.0)),
        )


def _history(d: dict) -> tuple:
    """The history from a checkpoint; one from before it was bounded has a row per frame (stride 1)
    and is bounded from here on."""
    if "history_frames" in d:
        return np.asarray(d["history"], np.float32), np.asarray(d["history_frames"], np.int64), int(d["history_stride"])
    h = B.history_empty()
    for row in np.asarray(d.get("history", h[0]), np.float32):  # replayed a frame at a time
        h = B.history_add(*h, lambda m, row=row: row[np.linspace(0, len(row) - 1, m).astype(np.int64)])
    return h


def _nd(a: np.ndarray, dtype, vec: bool = False):
    """A new Taichi array holding ``a`` (tests; the generator keeps its arrays, see FoamGenerator._upload)."""
    n = max(len(a), 1)
    arr = ti.Vector.ndarray(3, ti.f32, n) if vec else ti.ndarray(dtype, n)
    if len(a):
        if vec:
            full = np.zeros((n, 3), np.float32)
            full[: len(a)] = a
        else:
            full = np.zeros(n, np.dtype(a.dtype))
            full[: len(a)] = a
        arr.from_numpy(full)
    return arr


def _hash_u32(a: np.ndarray) -> np.ndarray:
    """kernels.hash_u32 (lowbias32) on numpy arrays."""
    a = np.asarray(a, np.uint32).copy()
    with np.errstate(over="ignore"):
        a ^= a >> np.uint32(16)
        a *= np.uint32(0x7FEB352D)
        a ^= a >> np.uint32(15)
        a *= np.uint32(0x846CA68B)
        a ^= a >> np.uint32(16)
    return a


def uniform(seed: int, frame: int, pid: np.ndarray, slot, draw: int) -> np.ndarray:
    """kernels.rand01 on numpy arrays: uniform [0, 1) from (seed, frame, id, slot, draw)."""
    slot = np.asarray(slot, np.uint32)
    with np.errstate(over="ignore"):
        inner = _hash_u32(slot * np.uint32(16) + np.uint32(draw))
    h = _hash_u32(np.uint32(seed) ^ _hash_u32(np.uint32(frame & 0xFFFFFFFF) ^ _hash_u32(np.asarray(pid, np.uint32) ^ inner)))
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / 16777216.0)


class FoamGenerator:
    def __init__(self, params: FoamParams, radius: float, domain: tuple, gravity, seed: int, arch: str = "cpu",
                 obstacles: list | None = None):
        runtime.init(runtime.current() or arch)
        self.p = params
        self.r = float(radius)
        self.h = params.support * self.r
        self.lo = np.asarray(domain[0], np.float64)
        self.hi = np.asarray(domain[1], np.float64)
        self.g = ti.math.vec3(*gravity)
        self.g_norm = float(np.linalg.norm(np.asarray(gravity, np.float64)))
        self.seed = int(seed) & 0xFFFFFFFF
        self.state = DiffuseState.empty()
        self.grid: NeighborGrid | None = None
        self._warned_capacity = False
        self._warned_budget = False
        self._bufs: dict = {}  # Taichi arrays reused from frame to frame (see _buffer): the fluid's, the candidates'
        # the live diffuse particles' Taichi arrays (_advect): made at the budget's count, grown only past it
        self._resident: dict = {}
        self._host: dict = {}  # numpy copies of some of them, reused to upload into them (see _upload)
        self._candidates = None
        self._S = 0
        self.capacity: int | None = None
        self._sized_for = 0  # fluid particle count the capacity was sized for
        self.last_frame: int | None = None  # the run's last frame index, where known: no peak after it
        self.looked_ahead = False  # post-processing has set 'auto' from the whole run (calibrate)
        self.obstacles = obstacles or []  # sim.obstacles.PosedSDF: see _obstacles, and nothing is born inside

    # ------------------------------------------------------------------ thresholds and multipliers
    def base_thresholds(self) -> np.ndarray:
        p = self.p
        return np.array([p.ta_min, p.ta_max, p.wc_min, p.wc_max, p.ke_min, p.ke_max, p.vo_min, p.vo_max], np.float32)

    def thresholds(self) -> np.ndarray:
        return self.state.tau if self.state.tau is not None else self.base_thresholds()

    def multipliers(self) -> tuple[float, float, float]:
        """(k_ta, k_wc, k_vo) in use: the preset's, times the budget's scale under 'auto'."""
        s = self.state.scale if self._scaled() else 1.0
        return (self.p.k_ta * s, self.p.k_wc * s, self.p.k_vo * s)

    def type_multipliers(self) -> np.ndarray:
        """Each type's generation relative to k: the user's multiplier, times, under 'auto' with
        the budget, the type's scale for its share (a share of 0 makes none of that type)."""
        m = np.asarray(self.p.type_multipliers, np.float64)
        if self._scaled():
            m = m * self.state.type_scale * (np.asarray(self.p.shares, np.float64) > 0)
        return m

    def _split(self) -> None:
        """'auto': each type's scale, from the split of the particles alive after the last frame."""
        st = self.state
        if self._scaled() and st.counts and len(st.born):
            st.type_scale = B.type_scales(st.born, st.counts[-1][1], st.counts[-1][2:], st.type_scale,
                                          self.p.type_multipliers, self.p.shares, self.p, self._dt)

    def _age(self, n: int) -> None:
        """'auto': foam's aging rate, from the foam alive after the last frame over its share (budget.foam_aging)."""
        st = self.state
        if self._scaled() and st.counts:
            share = self.p.shares[1] * self.p.type_multipliers[1]
            st.foam_aging = B.foam_aging(st.foam_aging, st.counts[-1][3], n, share, self.p.budget)

    def _boost(self) -> float:
        """How many more particles the type scales make than the common scale alone (budget.birth_boost)."""
        return B.birth_boost(self.state.born, self.state.type_scale, self.p.type_multipliers)

    def _scaled(self) -> bool:
        return self.p.auto and not ({"k_ta", "k_wc", "k_vo"} & self.p.explicit)

    def _auto_tau(self, pots: dict, moving: np.ndarray) -> np.ndarray:
        """Percentile thresholds, keeping any threshold set explicitly."""
        base = self.base_thresholds()
        tau = B.percentile_thresholds(pots, moving, base)
        for k, name in enumerate(("ta_min", "ta_max", "wc_min", "wc_max", "ke_min", "ke_max", "vo_min", "vo_max")):
            if name in self.p.explicit:
                tau[k] = base[k]
        return tau

    def potentials(self, fluid: ParticleFrame) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """The four potentials per fluid particle and whether it moves: what 'auto' reads from a frame."""
        self._potential_arrays(fluid, len(fluid))
        return self._pots, self._moving(fluid)

    def _moving(self, fluid: ParticleFrame) -> np.ndarray:
        return np.linalg.norm(fluid.velocities, axis=1) > B.moving_speed(self.g_norm, self.h)

    def calibrate(self, samples: list[ParticleFrame], times: np.ndarray, n_fluid: np.ndarray, dt: float,
                  indices: list[int] | None = None) -> None:
        """Post-processing 'auto': thresholds from the potentials pooled over frames sampled
        across the run (``samples``), then the scale that puts the predicted peak on the
        budget, predicted at every frame time in ``times`` (fluid counts ``n_fluid``; frame
        numbers ``indices``). As frames are processed their real birth rates replace the
        interpolated ones and the scale is set again (see _replan)."""
        got = [self.potentials(f) for f in samples]
        pooled = {k: np.concatenate([g[0][k] for g in got]) for k in ("ta", "wc", "ke", "vo")}
        tau = self._auto_tau(pooled, np.concatenate([g[1] for g in got]))
        self.state.tau = tau
        if self._scaled():
            k0 = (self.p.k_ta, self.p.k_wc, self.p.k_vo)
            t_s = np.array([f.time for f in samples], np.float64)
            rate_s = np.array([B.birth_rate(g[0], tau, k0, dt) for g in got])
            rate = np.interp(times, t_s, rate_s)
            self._plan = (B.survival_matrix(times, self.p, dt), rate, np.asarray(n_fluid, np.float64),
                          {int(i): k for k, i in enumerate(indices if indices is not None else range(len(times)))})
            self._set_scale()
        self.looked_ahead = True
        self._say_auto(f"whole run, {len(samples)} frames sampled")

    def _set_scale(self) -> None:
        surv, rate, n_fluid, _ = self._plan
        ratio = B.predicted_ratio(surv, rate, n_fluid)
        peak = float(ratio.max()) if len(ratio) else 0.0
        self.state.scale = self.p.budget / peak if peak > 0 else 1.0
        self._scales = np.full(len(rate), np.nan)

    def _replan(self, index: int, dt: float) -> None:
        """Post-processing 'auto': this frame's real birth rate and fluid count replace the interpolated ones,
        the frames done so far correct the model's survival (live count / predicted), and the
        scale for the rest of the run is set so the corrected prediction peaks on the budget."""
        plan = getattr(self, "_plan", None)
        if plan is None or index not in plan[3]:
            return
        surv, rate, n_fluid, pos = plan
        k = pos[index]
        k0 = (self.p.k_ta, self.p.k_wc, self.p.k_vo)
        rate[k] = B.birth_rate(self._pots, self.state.tau, k0, dt)
        n_fluid[k] = len(self._pots["ta"])  # the real count replaces the one interpolated between samples
        s_past = np.nan_to_num(self._scales[:k])
        counts = self.state.counts
        alive = float(sum(counts[-1][2:])) if counts and k > 0 else 0.0
        self.state.scale = B.rescale(surv, rate, n_fluid, s_past, alive, self.p, self.state.scale)
        self.state.scale = B.within_budget(self.state.scale, rate[k] * self._boost(), alive, n_fluid[k], self.p.budget)
        self._scales[k] = self.state.scale

    def _running_auto(self, n: int, index: int, dt: float, fluid: ParticleFrame) -> None:
        """Simulation 'auto': the thresholds and the expected peak only rise with what the flow
        has shown so far, and the scale follows them (see budget.running_peak); the birth rates
        of past frames are recomputed with today's thresholds from their sampled potentials."""
        st = self.state
        pots = self._pots
        moving = self._moving(fluid)
        if moving.sum() < B.MIN_SAMPLES:
            return  # nothing moves yet: nothing would be generated

        def sample(m: int) -> np.ndarray:  # m fluid particles spread evenly over the frame
            pick = np.linspace(0, n - 1, m).astype(np.int64)
            return np.stack([pots[k][pick] for k in ("ta", "wc", "ke", "vo")] + [moving[pick]], 1).astype(np.float32)

        st.history, st.history_frames, st.history_stride = B.history_add(
            st.history, st.history_frames, st.history_stride, sample)
        # τ from the moving particles of the frames so far, pooled, as post-processing does with its samples.
        h = B.history_samples(st.history, st.history_frames, st.history_stride)
        tau = self._auto_tau({k: h[:, c] for c, k in enumerate(("ta", "wc", "ke", "vo"))}, h[:, 4] > 0)
        first = st.tau is None
        st.tau = tau if first else np.maximum(st.tau, tau)
        if self._scaled():
            k0 = (self.p.k_ta, self.p.k_wc, self.p.k_vo)
            rates = B.history_rates(st.history, st.history_frames, st.history_stride, st.tau, k0, dt)
            alive = float(sum(st.counts[-1][2:])) if st.counts else 0.0
            # frames from the first moving one to the end of the run, where known
            seen = int(st.history_frames.sum())
            left = None if self.last_frame is None else self.last_frame - (index - seen + 1)
            peak = B.running_peak(rates, self.p, dt, left, st.history_frames)
            if peak > 0:
                st.scale = self.p.budget / peak
                st.scale = B.within_budget(st.scale, B.birth_rate(pots, st.tau, k0, dt) * self._boost(), alive, n,
                                           self.p.budget)
        if first:
            self._say_auto(f"running estimate from frame {index}; it only rises")

    def _say_auto(self, how: str) -> None:
        tau, k = self.thresholds(), self.multipliers()
        budget = (f"k_ta {k[0]:.3g}, k_wc {k[1]:.3g}, k_vo {k[2]:.3g} 1/s ({self.state.scale:.3g} × the preset's) "
                  f"for a budget of {self.p.budget:g} diffuse per fluid particle at the peak"
                  if self._scaled() else "multipliers as set")
        console.print(
            f"foam auto ({how}): trapped air {tau[0]:.3g}–{tau[1]:.3g} m/s, wave crest "
            f"{tau[2]:.3g}–{tau[3]:.3g}, kinetic energy {tau[4]:.3g}–{tau[5]:.3g} J/kg, vorticity {tau[6]:.3g}–{tau[7]:.3g} 1/s; "
            + budget
        )

    def peak_report(self) -> str:
        pk = self.state.peaks
        k = self.multipliers()
        return (f"peak diffuse per fluid particle: {pk[0]:.2f} at frame {int(pk[1])} (spray {pk[2]:.2f}, foam {pk[3]:.2f}, "
                f"bubbles {pk[4]:.2f} at their own peaks)"
                + (f"; budget {self.p.budget:g} (spray, foam, bubbles {', '.join(f'{x:.2g}' for x in self.p.shares)} of it), "
                   f"last multipliers k_ta {k[0]:.3g}, k_wc {k[1]:.3g}, k_vo {k[2]:.3g} 1/s, by type "
                   f"{', '.join(f'{x:.3g}' for x in self.state.type_scale)}"
                   if self._scaled() else ""))

    # ------------------------------------------------------------------ one frame
    def _fluid_grid(self, n: int) -> NeighborGrid:
        if self.grid is None or self.grid.capacity < n:
            rows = max(n, 1, int(GRID_GROWTH * self.grid.capacity) if self.grid is not None else 0)
            self.grid = None  # the old grid's arrays go before the new ones are made
            self.grid = NeighborGrid(grid_spec(self.lo, self.hi, self.h / 2), rows, MAX_FLUID_NEIGHBOURS, self.h)
        return self.grid

    def _prepare(self, fluid: ParticleFrame, n: int):
        """The fluid frame in the kept Taichi arrays, and its neighbour lists."""
        fx = self._upload("fluid_x", fluid.positions, vec=True)
        fv = self._upload("fluid_v", fluid.velocities, vec=True)
        fid = self._upload("fluid_id", fluid.ids.astype(np.uint32, copy=False), ti.u32)
        g = self._fluid_grid(n)
        g.build(fx, n)
        return fx, fv, fid, (*g.query_args(), self.h, g.order, fv)

    def _potential_arrays(self, fluid: ParticleFrame, n: int):
        """Neighbours and the potentials (Taichi arrays; numpy copies in self._pots)."""
        fx, fv, fid, args = self._prepare(fluid, n)
        g = self.grid
        normal, surface = self._buffer("normal", n, vec=True), self._buffer("surface", n)
        v_diff, e_k, vort, crest = (self._buffer(k, n, ti.f32) for k in ("v_diff", "e_k", "vort", "crest"))
        if self.p.model == "foamgenerator":  # SPlisHSPlasH FoamGenerator's potentials (see .splishsplash)
            self._foamgenerator_potentials(fx, fv, n, normal, v_diff, crest, e_k)
            vort.fill(0.0)
            K.zero_below(n, g.nb_count, SP.MIN_NEIGHBOURS, e_k)  # too few neighbours: I_k = 0, no generation
        else:
            K.fluid_potentials(n, fx, fv, g.nb_count, g.nb, self.h, SURFACE_FRACTION, normal, surface, v_diff, e_k, vort)
            K.wave_crest(n, fx, fv, g.nb_count, g.nb, normal, surface, self.h, crest)
        self._pots = {"ta": v_diff.to_numpy()[:n], "wc": crest.to_numpy()[:n], "ke": e_k.to_numpy()[:n], "vo": vort.to_numpy()[:n]}
        return args, fx, fv, fid, (v_diff, crest, e_k, vort)

    def _foamgenerator_potentials(self, fx, fv, n: int, normal, v_diff, crest, e_k) -> None:
        """SP.frame_potentials into this generator's kept arrays (v_diff, κ, E; ``normal`` as scratch)."""
        g = self.grid
        m = SP.particle_mass(self.r)
        rho = self._buffer("sp_rho", n, ti.f32)
        SP.sph_density(n, fx, g.nb_count, g.nb, self.h, m, rho)
        SP.surface_normals(n, fx, g.nb_count, g.nb, self.h, m, rho, normal)
        # SP.row_volumes, into a kept array: V̄_N = (1/N) Σ_{k<N} m/ρ_k for N = 0 … n
        cum = np.concatenate([[0.0], np.cumsum(m / rho.to_numpy()[:n].astype(np.float64))])
        vbar = cum / np.maximum(np.arange(len(cum)), 1)
        vol = self._upload("sp_row_volume", vbar.astype(np.float32), ti.f32)
        SP.potentials(n, fx, fv, g.nb_count, g.nb, self.h, m, vol, normal, v_diff, crest, e_k)

    def nbytes(self) -> int:
        """Bytes of the Taichi arrays this generator keeps (its buffers and the fluid neighbour grid)."""
        total = self.grid.nbytes() if self.grid is not None else 0
        for a in (*self._bufs.values(), *self._resident.values()):
            vec = 3 if isinstance(a, ti.lang.matrix.VectorNdarray) else 1
            total += int(np.prod(a.shape)) * vec * np.dtype(to_numpy_type(a.dtype)).itemsize
        return total

    def step(self, fluid: ParticleFrame, index: int, dt: float) -> ParticleFrame:
        st = self.state
        if fluid.velocities is None:
            raise ValueError(f"{fluid.source}: fluid frame has no velocities")
        n = len(fluid)
        if self.capacity is None or n > self._sized_for:
            self._size(n)  # from the first frame, again when the fluid grows (empty first frames, inflow)
        with timer("foam.potentials"):
            args, fx, fv, fid, pots = self._potential_arrays(fluid, n)
        with timer("foam.advect"):
            self._age(n)
            old = self._advect(fx, fv, args, dt, index)
        with timer("foam.generate"):
            new = self._generate(fluid, fx, fv, fid, args, pots, n, index, dt)
        with timer("foam.compact"):
            kind = self._compact(old, new, index)
        nd = len(st.positions)
        c = [int(x) for x in np.bincount(kind, minlength=3)[:3]]
        time_ = fluid.time if fluid.time is not None else index * dt
        if self._scaled():
            st.born = B.born_add(st.born, [time_, *np.bincount(new[3], minlength=3)[:3], *st.type_scale], self.p, dt)
        st.counts.append((index, time_, *c))
        self._track_peak(c, n, index)
        return ParticleFrame(
            positions=st.positions, velocities=st.velocities, ids=st.ids, time=time_,
            arrays={"type": kind, "lifetime": st.lifetime, "radius": np.full(nd, self.p.radius * self.r, np.float32)},
        )

    def _size(self, n: int) -> None:
        """Capacity from the budget (unless set); warn when a set capacity is below the budget."""
        p = self.p
        self.capacity = B.capacity_for(p, n)
        self._sized_for = n
        want = p.budget * n
        if p.auto and p.max_particles is not None and p.max_particles < want and not self._warned_budget:
            self._warned_budget = True
            console.print(
                f"[yellow]warning:[/] foam.budget = {p.budget:g} asks for about {want:,.0f} diffuse particles at the "
                f"peak ({n:,} fluid particles), beyond foam.max_particles = {p.max_particles:,}; the excess will be "
                "dropped (raise max_particles or leave it unset)."
            )

    def _track_peak(self, c: list, n: int, index: int) -> None:
        pk = self.state.peaks
        ratios = np.array(c, np.float64) / max(n, 1)
        if ratios.sum() > pk[0] or pk[1] < 0:
            pk[0], pk[1] = ratios.sum(), index
        pk[2:] = np.maximum(pk[2:], ratios)

    def _advect(self, fx, fv, args, dt, index):
        """(1) classify the existing diffuse particles by their fluid neighbours and advect by type;
        remove the expired, the dissipated foam and those leaving the domain."""
        p, st = self.p, self.state
        nd = len(st.positions)
        if not nd:
            return st.positions, st.velocities, st.lifetime, st.ids, np.zeros(0, np.uint8)
        lo, hi = ti.math.vec3(*self.lo), ti.math.vec3(*self.hi)
        # the live diffuse particles: arrays at the budget's count from the start, grown (geometrically,
        # never past the capacity) only if more live
        start = math.ceil(p.budget * self._sized_for)
        up = {"start": start, "limit": self.capacity, "pool": self._resident}
        xd, vd = self._upload("diffuse_x", st.positions, vec=True, **up), self._upload("diffuse_v", st.velocities, vec=True, **up)
        life = self._upload("diffuse_life", st.lifetime, ti.f32, **up)
        keep, kind = self._buffer("diffuse_keep", nd, **up), self._buffer("diffuse_kind", nd, **up)
        K.advect_diffuse(
            nd, xd, vd, life, *args, self.g, p.buoyancy, p.drag, dt, p.spray_below, p.bubble_above, lo, hi, keep, kind,
            int(p.model == "foamgenerator"),  # FoamGenerator's foam keeps its own velocity
            int(p.model == "foamgenerator" and p.wall_correction),  # foam near the box's faces counted up
        )
        k = keep.to_numpy()[:nd].astype(bool)
        kd = kind.to_numpy()[:nd]
        lf = life.to_numpy()[:nd]
        # Spray and bubbles count down too where their type has a lifetime range.
        for t, rng in ((0, p.spray_lifetime), (2, p.bubble_lifetime)):
            if rng is not None:
                sel = kd == t
                lf[sel] -= dt
                k &= ~(sel & (lf <= 0.0))
        # Foam beyond its share under 'auto' ages faster (budget.foam_aging).
        if st.foam_aging > 1.0:
            sel = kd == 1
            lf[sel] -= (st.foam_aging - 1.0) * dt
            k &= ~(sel & (lf <= 0.0))
        # Foam dissipation: each foam particle survives a frame with probability exp(−λ Δt).
        if p.foam_dissipation > 0:
            foam = kd == 1
            gone = uniform(self.seed, index, st.ids, 0, DRAW_DISSIPATE) >= math.exp(-p.foam_dissipation * dt)
            k &= ~(foam & gone)
        x, v, lf, ids, kd = xd.to_numpy()[:nd][k], vd.to_numpy()[:nd][k], lf[k], st.ids[k], kd[k].astype(np.uint8)
        if self.obstacles:
            x, v, alive = self._obstacles(st.positions[k], x, v, kd)
            x, v, lf, ids, kd = x[alive], v[alive], lf[alive], ids[alive], kd[alive]
        return x, v, lf, ids, kd

    def _obstacles(self, x0: np.ndarray, x: np.ndarray, v: np.ndarray, kind: np.ndarray):
        """Diffuse particles against the obstacles (sim.obstacles.PosedSDF, at this frame's pose and
        the last one's), after advection from x0 to x: foam touching a moving body at the frame's start
        rides on it, carried rigidly over the frame with the body's velocity there; spray that ends the
        frame inside bounces (its normal velocity relative to the body reflected, times
        SPRAY_RESTITUTION) and foam inside moves with the body, both put back outside; a bubble inside,
        or a particle that cannot be put outside (a crease), is removed. Returns (x, v, alive)."""
        x, v = x.astype(np.float64), v.astype(np.float64)
        alive = np.ones(len(x), bool)
        for g in self.obstacles:
            ride = np.zeros(len(x), bool)
            if g.moved:
                ride = (kind == FOAM) & (g.sample(x0, before=True) < BODY_CONTACT * self.r)
                if ride.any():
                    x[ride] = g.carry(x0[ride])
                    v[ride] = g.velocity(x[ride])
            d = g.sample(x)
            self._through(g, x0, x, d, alive & ~ride)  # riders went with the body, not through it
            hit = alive & (d <= 0.0)
            alive &= ~(hit & (kind == BUBBLE))
            hit &= kind != BUBBLE
            if not hit.any():
                continue
            xh, n = self._entry(g, x0[hit], x[hit], d[hit])
            xh = xh + SURFACE_OFFSET * self.r * n
            u = g.velocity(xh)
            vr = v[hit] - u
            vn = np.minimum((vr * n).sum(1), 0.0)
            spray = kind[hit] == SPRAY
            vh = np.where(spray[:, None], u + vr - (1.0 + SPRAY_RESTITUTION) * vn[:, None] * n, u)
            x[hit], v[hit] = xh, vh
            alive[hit] = g.sample(xh) > 0.0
        return x.astype(np.float32), v.astype(np.float32), alive

    @staticmethod
    def _through(g, x0: np.ndarray, x: np.ndarray, d: np.ndarray, alive: np.ndarray) -> None:
        """Particles whose path x0 → x passes through obstacle g but ends outside it: their end
        point ``x`` (and ``d``) is moved, in place, to the first point of the path found inside,
        so that they hit the face they met first (see PATH_SAMPLES)."""
        step = 0.5 * g.grid.spacing
        seg = x - x0
        length = np.linalg.norm(seg, axis=1)
        far = np.flatnonzero(alive & (d > 0.0) & (length > step))
        if not len(far):
            return
        n = int(min(PATH_SAMPLES, np.ceil(length[far].max() / step)))
        first = np.full(len(far), np.inf)
        for j in range(n - 1, 0, -1):  # backwards: the last found is the first along the path
            t = j / n
            inside = g.sample(x0[far] + t * seg[far]) <= 0.0
            first[inside] = t
        hit = np.isfinite(first)
        if hit.any():
            k = far[hit]
            x[k] = x0[k] + first[hit, None] * seg[k]
            d[k] = g.sample(x[k])

    @staticmethod
    def _entry(g, x0: np.ndarray, x: np.ndarray, d: np.ndarray, steps: int = 16):
        """Where particles that moved from x0 to x (inside obstacle g) crossed its surface, and the
        normal there: the crossing on the segment, by bisection on the SDF at this frame's pose, for
        those that started outside it (so a fast drop bounces off the face it came through, not the
        nearest one); the nearest surface point for those the body moved onto."""
        x0 = np.asarray(x0, np.float64)
        out = g.sample(x0) > 0.0
        lo, hi = np.zeros(len(x)), np.ones(len(x))
        for _ in range(steps):
            mid = 0.5 * (lo + hi)
            outside = g.sample(x0 + mid[:, None] * (x - x0)) > 0.0
            lo, hi = np.where(outside, mid, lo), np.where(outside, hi, mid)
        crossing = x0 + lo[:, None] * (x - x0)  # the last point found outside
        p = np.where(out[:, None], crossing, x)
        n = g.normal(p)
        return np.where(out[:, None], p, x - d[:, None] * n), n

    def _buffer(self, name: str, size: int, dtype=ti.i32, vec: bool = False, cols: int = 0, start: int = 0,
                limit: int | None = None, pool: dict | None = None):
        """A Taichi array of at least ``size`` rows kept from frame to frame (in ``pool``, by default
        self._bufs), grown geometrically (never allocated per frame once the run's largest frame has
        been seen): ``start`` rows at least when first made, and never grown past ``limit`` rows
        unless ``size`` needs it. (Taichi does not give an array's memory back to the process when the
        array goes: every array made per frame would grow the memory in use, on the CPU and on CUDA.)"""
        bufs = self._bufs if pool is None else pool
        a = bufs.get(name)
        if a is None or a.shape[0] < size:
            rows = max(size, 2 * a.shape[0] if a is not None else start, 1)
            if limit is not None:
                rows = max(size, min(rows, limit), 1)
            bufs.pop(name, None)  # the old array goes before the new one is made
            self._host.pop(name, None)
            a = None
            if vec:
                a = ti.Vector.ndarray(3, ti.f32, rows)
            else:
                a = ti.ndarray(dtype, (rows, cols) if cols else rows)
            bufs[name] = a
        return a

    def _staging(self, name: str, a) -> np.ndarray:
        """The numpy array, shaped as kept array ``a``, through which ``name`` is uploaded (kept with it)."""
        h = self._host.get(name)
        if h is None:
            shape = tuple(a.shape) + ((3,) if isinstance(a, ti.lang.matrix.VectorNdarray) else ())
            h = self._host[name] = np.zeros(shape, to_numpy_type(a.dtype))
        return h

    def _upload(self, name: str, rows: np.ndarray, dtype=ti.f32, vec: bool = False, **kw):
        """``rows`` into the kept Taichi array ``name`` (see _buffer), the rows after them zero,
        through a kept numpy array: nothing allocated once the array is large enough."""
        n = len(rows)
        a = self._buffer(name, n, dtype, vec, **kw)
        h = self._staging(name, a)
        h[:n] = rows
        h[n:] = 0
        a.from_numpy(h)
        return a

    def _generate(self, fluid, fx, fv, fid, args, pots, n, index, dt):
        """(2) generation: each fluid particle's number of candidates, each its own run of them (offsets
        from a prefix sum of the numbers); the candidates sampled in parallel over them
        (K.generate_candidates), typed only as far as the keep rule needs and thinned by their type's
        multiplier (K.classify_candidates), and the kept compacted in candidate order (K.gather_kept).
        Only the kept candidates come to the host."""
        p = self.p
        v_diff, crest, e_k, vort = pots
        self._dt = dt
        self._split()
        if p.auto and not self.looked_ahead:
            self._running_auto(n, index, dt, fluid)
        elif p.auto and self._scaled():
            self._replan(index, dt)
        tau = self._upload("tau", self.thresholds(), ti.f32)
        mult = self.type_multipliers()
        most = float(mult.max())
        z = np.zeros((0, 3), np.float32)
        none = (z, z, np.zeros(0, np.float32), np.zeros(0, np.uint8), 0)
        self._candidates = None
        if most <= 0:
            return none
        k = [x * most for x in self.multipliers()]  # candidates for the most generous type; cut below
        cap = self._S = p.slots_per_particle or 0
        m = max(n, 1)
        cnt, rate = self._buffer("count", m), self._buffer("rate", m, ti.f32)
        frame = index & 0xFFFFFFFF
        lost = K.birth_counts(n, fid, v_diff, crest, e_k, vort, tau, k[0], k[1], k[2], dt, self.seed, frame, cap, cnt, rate,
                              int(p.model == "foamgenerator"))
        counts = cnt.to_numpy()[:n]
        total = int(counts.sum())
        if not total:
            return none[:4] + (int(lost),)
        off = self._buffer("offset", m)
        offset = self._staging("offset", off)
        offset[0] = 0
        np.cumsum(counts[:-1], out=offset[1:n])
        offset[n:] = 0
        off.from_numpy(offset)
        ox, ov, ol = (self._buffer("cand_x", total, vec=True), self._buffer("cand_v", total, vec=True),
                      self._buffer("cand_life", total, ti.f32))
        owner, kd = self._buffer("cand_owner", total), self._buffer("cand_kind", total, ti.i8)
        K.candidate_owners(n, cnt, off, owner)
        K.generate_candidates(total, owner, off, fx, fv, fid, e_k, tau, p.lifetime_min, p.lifetime_max,
                              p.lifetime_multiplier, self.r, dt, self.seed, frame, ox, ov, ol)
        # The type each new particle is born as; a particle of type t is kept when its slot is
        # below its fluid particle's n_d·m_t, rounded with the kernel's own random number: the
        # particles of a type whose multiplier is unchanged stay exactly the same. The limits
        # (per fluid particle and type) are known before the types, so the classification does
        # only the work that decides whether a candidate is kept.
        rows = np.flatnonzero(counts)
        nd0 = rate.to_numpy()[:n][rows].astype(np.float32) / np.float32(most)
        u0 = uniform(self.seed, index, fluid.ids.astype(np.uint32)[rows], ROUNDING_SLOT, 0)
        want = nd0[:, None] * mult.astype(np.float32)[None, :]  # (generating particle, type)

        def limits(want):
            if p.model == "foamgenerator":  # rounded half up, as kernels.birth_counts does for it
                return np.floor(want + np.float32(0.5))
            return np.floor(want) + (u0[:, None] < want - np.floor(want))

        lim = self._buffer("limit", m, cols=3)
        table = self._staging("limit", lim)
        table.fill(0)
        table[rows] = np.minimum(limits(want), np.float32(2**30))
        lim.from_numpy(table)
        g = self.grid
        K.classify_candidates(total, ox, owner, off, lim, fx, g.nb_count, g.nb, *args[:7],
                              p.spray_below, p.bubble_above, ti.math.vec3(*self.lo), ti.math.vec3(*self.hi),
                              int(p.model == "foamgenerator" and p.wall_correction), kd)
        idx = np.flatnonzero(kd.to_numpy()[:total] >= 0).astype(np.int32)  # the kept, in candidate order
        nk = len(idx)
        sel = self._upload("kept_idx", idx, ti.i32)
        kx, kv, kl = (self._buffer("kept_x", nk, vec=True), self._buffer("kept_v", nk, vec=True),
                      self._buffer("kept_life", nk, ti.f32))
        kk, ko = self._buffer("kept_kind", nk, ti.i8), self._buffer("kept_owner", nk)
        K.gather_kept(nk, sel, ox, ov, ol, kd, owner, kx, kv, kl, kk, ko)
        x, v, life = kx.to_numpy()[:nk], kv.to_numpy()[:nk], kl.to_numpy()[:nk]
        kind, fowner = kk.to_numpy()[:nk].astype(np.uint8), ko.to_numpy()[:nk]
        offset = offset[:n].copy()  # the kept array is the next frame's
        self._candidates = {"total": total, "kept": idx, "offset": offset, "counts": counts}  # for tests
        row = np.searchsorted(rows, fowner)  # the generating particle's row in ``want``
        slot = idx - offset[fowner]
        pid = fluid.ids.astype(np.uint32)[fowner]
        if p.model == "foamgenerator":  # FoamGenerator's lifetime: l_min + (I_k/τmax_k) X (l_max − l_min)
            tau_ = self.thresholds()
            e = e_k.to_numpy()[:n][fowner].astype(np.float64)
            i_k = (np.minimum(e, tau_[5]) - np.minimum(e, tau_[4])) / (tau_[5] - tau_[4])
            x01 = (life - p.lifetime_min) / max(p.lifetime_max - p.lifetime_min, 1e-30)
            life = SP.lifetimes(x01, i_k, float(tau_[5]), p.lifetime_min, p.lifetime_max)

        def kept(want):  # the keep rule, on the candidates the first limits kept (lower limits keep fewer)
            return slot < limits(want)[row, kind]

        keep = kept(want)
        if self._scaled():
            # The type scales can make one frame's births far more than the birth rate foretold
            # (a burst of the type scaled furthest up): never past the budget in one frame, and
            # no type past its share of it (times its own multiplier, which the budget counts at 1),
            # so a type born early and living long (foam) cannot take the room of one born later
            # or living briefly (spray).
            live = np.asarray(self.state.counts[-1][2:] if self.state.counts else (0, 0, 0), np.float64)
            share = np.asarray(p.shares, np.float64) * np.asarray(p.type_multipliers, np.float64)
            room = np.maximum(p.budget * n * share - live, 0.0)
            made = np.bincount(kind[keep], minlength=3)[:3].astype(np.float64)
            cut = np.where(made > room, room / np.maximum(made, 1.0), 1.0)
            if (cut < 1).any():
                want = want * cut.astype(np.float32)[None, :]
                keep = kept(want)
            room = p.budget * n - live.sum()
            if keep.sum() > max(room, 0):
                keep = kept(want * np.float32(max(room, 0) / keep.sum()))
        # Spray and bubbles with their own lifetime range draw it here.
        for t, rng in ((0, p.spray_lifetime), (2, p.bubble_lifetime)):
            if rng is not None:
                sel = kind == t
                u = uniform(self.seed, index, pid[sel], slot[sel], DRAW_LIFE)
                life[sel] = rng[0] + (rng[1] - rng[0]) * u
        return x[keep], v[keep], life[keep], kind[keep], int(lost)

    def _compact(self, old, new, index) -> np.ndarray:
        """(3) survivors first, then the new particles in fluid order: a fixed order, no global counter.
        Returns the type of every particle."""
        p, st = self.p, self.state
        new_x, new_v, new_l, new_k, lost = new
        room = self.capacity - len(old[0])
        if len(new_x) > room or lost:
            if not self._warned_capacity:
                slots = f"{lost:,} beyond foam.slots_per_particle = {self._S} per fluid particle, " if lost else ""
                console.print(
                    f"[yellow]warning:[/] foam capacity saturated at frame {index}: {len(new_x) + lost:,} new particles "
                    f"wanted, {slots}{max(len(new_x) - max(room, 0), 0):,} beyond foam.max_particles = {self.capacity:,} "
                    f"({len(old[0]):,} alive); the excess is dropped (raise these to keep it). Said once per run."
                )
                self._warned_capacity = True
            room = max(room, 0)
            new_x, new_v, new_l, new_k = new_x[:room], new_v[:room], new_l[:room], new_k[:room]
        new_ids = (st.next_id + np.arange(len(new_x))).astype(np.uint32)
        st.next_id += len(new_x)
        st.positions = np.concatenate([old[0], new_x], dtype=np.float32)
        st.velocities = np.concatenate([old[1], new_v], dtype=np.float32)
        st.lifetime = np.concatenate([old[2], new_l], dtype=np.float32)
        st.ids = np.concatenate([old[3], new_ids], dtype=np.uint32)
        kind = np.concatenate([old[4], new_k], dtype=np.uint8)
        if len(st.positions):
            # Inside the domain and outside every obstacle; new particles born outside
            # the domain go at once, as moved ones do in _advect.
            keep = ((st.positions >= self.lo) & (st.positions <= self.hi)).all(axis=1)
            for g in self.obstacles:
                keep &= g.sample(st.positions) > 0.0
            if not keep.all():
                st.positions, st.velocities = st.positions[keep], st.velocities[keep]
                st.lifetime, st.ids, kind = st.lifetime[keep], st.ids[keep], kind[keep]
        return kind

    def with_params(self, **kw) -> None:
        self.p = replace(self.p, **kw)
