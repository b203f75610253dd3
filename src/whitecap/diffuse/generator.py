"""The diffuse-particle state and one frame of its evolution.

    state = DiffuseState.empty()
    gen = FoamGenerator(params, radius=r, domain=(lo, hi), gravity=g, seed=s)
    diffuse_frame = gen.step(fluid_frame, index, dt)

``step`` is the same code inside ``simulate`` and in post-processing, so the
same fluid frames and seed give byte-identical diffuse particles.
Per frame: (1) existing diffuse particles are classified by their fluid
neighbours and advected by type, expired foam and escapees removed;
(2) each fluid particle generates into its own fixed slots; (3) survivors
and the new particles are compacted in a fixed order (survivors first, then
slots in fluid order), so no global counter is needed; (4) everything is
classified again for output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import taichi as ti

from ..io import ParticleFrame
from ..progress import console
from ..sim import runtime
from ..sim.grid import NeighborGrid, grid_spec
from ..timing import timer
from . import kernels as K
from . import splishsplash as SP
from .params import FoamParams

SURFACE_FRACTION = 0.25  # |Σ x̂ W̃| / Σ W̃ above which a particle counts as on the surface
AUTO_PERCENTILES = (95.0, 99.9)  # τmin, τmax of 'auto' from the moving particles' potentials


@dataclass
class DiffuseState:
    positions: np.ndarray
    velocities: np.ndarray
    lifetime: np.ndarray
    ids: np.ndarray
    next_id: int = 0
    counts: list = field(default_factory=list)  # rows (frame, time, spray, foam, bubbles)
    tau: np.ndarray | None = None  # thresholds fixed by 'auto' mode

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
        return d

    @classmethod
    def from_arrays(cls, d: dict) -> "DiffuseState":
        return cls(
            np.asarray(d["positions"], np.float32), np.asarray(d["velocities"], np.float32),
            np.asarray(d["lifetime"], np.float32), np.asarray(d["ids"], np.uint32), int(d["next_id"]),
            [tuple(r) for r in np.asarray(d["counts"]).tolist()], np.asarray(d["tau"], np.float32) if "tau" in d else None,
        )


def _nd(a: np.ndarray, dtype, vec: bool = False):
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
        self.seed = int(seed) & 0xFFFFFFFF
        self.state = DiffuseState.empty()
        self.grid: NeighborGrid | None = None
        self._warned_capacity = False
        self._slots = None
        self.obstacles = obstacles or []  # SDF grids (sim.obstacles.SDFGrid): particles inside are removed

    # ------------------------------------------------------------------ thresholds
    def thresholds(self) -> np.ndarray:
        p = self.p
        if self.state.tau is not None:
            return self.state.tau
        return np.array([p.ta_min, p.ta_max, p.wc_min, p.wc_max, p.ke_min, p.ke_max, p.vo_min, p.vo_max], np.float32)

    def _auto_thresholds(self, pots: dict[str, np.ndarray], speed: np.ndarray, index: int) -> None:
        """'auto': τmin/τmax from percentiles of each potential over the moving particles,
        never below a twentieth of the preset's values (so still water stays still)."""
        moving = speed > 0.05 * math.sqrt(float(np.linalg.norm(self.g.to_numpy())) * self.h)
        if moving.sum() < 10:
            return  # wait for a frame with motion
        base = np.array([self.p.ta_min, self.p.ta_max, self.p.wc_min, self.p.wc_max,
                         self.p.ke_min, self.p.ke_max, self.p.vo_min, self.p.vo_max], np.float32)
        tau = base.copy()
        for k, name in enumerate(("ta", "wc", "ke", "vo")):
            vals = pots[name][moving]
            vals = vals[vals > 0]
            if len(vals) < 10:
                continue
            lo_, hi_ = np.percentile(vals, AUTO_PERCENTILES)
            tmin = max(float(lo_), base[2 * k] / 20)
            tau[2 * k] = tmin
            tau[2 * k + 1] = max(float(hi_), 2 * tmin)
        self.state.tau = tau
        console.print(
            f"foam auto thresholds (frame {index}): trapped air {tau[0]:.3g}–{tau[1]:.3g} m/s, wave crest "
            f"{tau[2]:.3g}–{tau[3]:.3g}, kinetic energy {tau[4]:.3g}–{tau[5]:.3g} J/kg, vorticity {tau[6]:.3g}–{tau[7]:.3g} 1/s"
        )

    # ------------------------------------------------------------------ one frame
    def _fluid_grid(self, n: int) -> NeighborGrid:
        if self.grid is None or self.grid.capacity < n:
            self.grid = NeighborGrid(grid_spec(self.lo, self.hi, self.h / 2), max(n, 1), 96, self.h)
        return self.grid

    def _prepare(self, fluid: ParticleFrame, n: int):
        fx = _nd(fluid.positions, ti.f32, vec=True)
        fv = _nd(fluid.velocities, ti.f32, vec=True)
        fid = _nd(fluid.ids.astype(np.uint32), ti.u32)
        g = self._fluid_grid(n)
        g.build(fx, n)
        return fx, fv, fid, (*g.query_args(), self.h, g.order, fv)

    def step(self, fluid: ParticleFrame, index: int, dt: float) -> ParticleFrame:
        st = self.state
        if fluid.velocities is None:
            raise ValueError(f"{fluid.source}: fluid frame has no velocities")
        n = len(fluid)
        with timer("foam.neighbours"):
            fx, fv, fid, args = self._prepare(fluid, n)
        with timer("foam.advect"):
            old = self._advect(args, dt)
        with timer("foam.generate"):
            new = self._generate(fluid, fx, fv, fid, n, index, dt)
        with timer("foam.compact"):
            self._compact(old, new, index)
        with timer("foam.classify"):
            kind = self._classify(args)
        nd = len(st.positions)
        c = [int((kind == t).sum()) for t in range(3)]
        time_ = fluid.time if fluid.time is not None else index * dt
        st.counts.append((index, time_, *c))
        return ParticleFrame(
            positions=st.positions, velocities=st.velocities, ids=st.ids, time=time_,
            arrays={"type": kind, "lifetime": st.lifetime, "radius": np.full(nd, self.p.radius * self.r, np.float32)},
        )

    def _advect(self, args, dt):
        """(1) classify the existing diffuse particles by their fluid neighbours and advect by type."""
        p, st = self.p, self.state
        nd = len(st.positions)
        self._old_kind = np.zeros(0, np.uint8)
        if not nd:
            return st.positions, st.velocities, st.lifetime, st.ids
        lo, hi = ti.math.vec3(*self.lo), ti.math.vec3(*self.hi)
        xd, vd = _nd(st.positions, ti.f32, True), _nd(st.velocities, ti.f32, True)
        life, keep = _nd(st.lifetime, ti.f32), ti.ndarray(ti.i32, nd)
        kind = ti.ndarray(ti.i32, nd)
        K.advect_diffuse(
            nd, xd, vd, life, *args, self.g, p.buoyancy, p.drag, dt, p.spray_below, p.bubble_above, lo, hi, keep, kind,
            int(p.model == "foamgenerator"),  # FoamGenerator's foam keeps its own velocity
        )
        k = keep.to_numpy()[:nd].astype(bool)
        self._old_kind = kind.to_numpy()[:nd][k].astype(np.uint8)
        return xd.to_numpy()[:nd][k], vd.to_numpy()[:nd][k], life.to_numpy()[:nd][k], st.ids[k]

    def _generate(self, fluid, fx, fv, fid, n, index, dt):
        """(2) potentials and generation, in parallel per fluid particle into its own fixed slots."""
        p, st, g = self.p, self.state, self.grid
        m = max(n, 1)
        normal, surface = ti.Vector.ndarray(3, ti.f32, m), ti.ndarray(ti.i32, m)
        v_diff, e_k, vort, crest = (ti.ndarray(ti.f32, m) for _ in range(4))
        if p.model == "foamgenerator":  # SPlisHSPlasH FoamGenerator's potentials (see .splishsplash)
            v_diff, crest, e_k = SP.frame_potentials(self, fx, fv, n)
            vort.fill(0.0)
            K.zero_below(n, g.nb_count, SP.MIN_NEIGHBOURS, e_k)  # too few neighbours: I_k = 0, no generation
        else:
            K.fluid_potentials(n, fx, fv, g.nb_count, g.nb, self.h, SURFACE_FRACTION, normal, surface, v_diff, e_k, vort)
            K.wave_crest(n, fx, fv, g.nb_count, g.nb, normal, surface, self.h, crest)
        if p.auto and st.tau is None:
            pots = {"ta": v_diff.to_numpy()[:n], "wc": crest.to_numpy()[:n], "ke": e_k.to_numpy()[:n], "vo": vort.to_numpy()[:n]}
            self._auto_thresholds(pots, np.linalg.norm(fluid.velocities, axis=1), index)
        tau = _nd(self.thresholds(), ti.f32)
        S = p.slots_per_particle
        if self._slots is None or self._slots[0] < n * S:
            cap = max(n * S, 1)
            self._slots = (cap, ti.Vector.ndarray(3, ti.f32, cap), ti.Vector.ndarray(3, ti.f32, cap), ti.ndarray(ti.f32, cap))
        _, ox, ov, ol = self._slots
        cnt = ti.ndarray(ti.i32, m)
        lost = K.generate(
            n, fx, fv, fid, v_diff, crest, e_k, vort, tau, p.k_ta, p.k_wc, p.k_vo, p.lifetime_min, p.lifetime_max,
            p.lifetime_multiplier, self.r, dt, self.seed, index & 0xFFFFFFFF, S, ox, ov, ol, cnt,
            int(p.model == "foamgenerator"),
        )
        # Slot s of particle i is valid when s < count[i]; only particles that generated are read back.
        counts = cnt.to_numpy()[:n]
        if not counts.any():
            z = np.zeros((0, 3), np.float32)
            return z, z, np.zeros(0, np.float32), int(lost)
        rows = np.flatnonzero(counts)
        idx = (rows[:, None] * S + np.arange(S)[None, :])[np.arange(S)[None, :] < counts[rows, None]]
        life = ol.to_numpy()[idx]
        if p.model == "foamgenerator":  # FoamGenerator's lifetime: l_min + (I_k/τmax_k) X (l_max − l_min)
            tau = self.thresholds()
            src = np.repeat(rows, counts[rows])
            e = e_k.to_numpy()[:n][src].astype(np.float64)
            i_k = (np.minimum(e, tau[5]) - np.minimum(e, tau[4])) / (tau[5] - tau[4])
            x01 = (life - p.lifetime_min) / max(p.lifetime_max - p.lifetime_min, 1e-30)
            life = SP.lifetimes(x01, i_k, float(tau[5]), p.lifetime_min, p.lifetime_max)
        return ox.to_numpy()[idx], ov.to_numpy()[idx], life, int(lost)

    def _compact(self, old, new, index) -> None:
        """(3) survivors first, then the new particles in slot order: a fixed order, no global counter."""
        p, st = self.p, self.state
        new_x, new_v, new_l, lost = new
        room = p.max_particles - len(old[0])
        if len(new_x) > room or lost:
            if not self._warned_capacity:
                console.print(
                    f"[yellow]warning:[/] foam capacity saturated at frame {index}: {len(new_x) + lost:,} new particles "
                    f"wanted, {lost:,} beyond foam.slots_per_particle={p.slots_per_particle} per fluid particle, "
                    f"{max(len(new_x) - max(room, 0), 0):,} beyond foam.max_particles={p.max_particles:,} "
                    f"({len(old[0]):,} alive); the excess is dropped (raise these to keep it). Said once per run."
                )
                self._warned_capacity = True
            room = max(room, 0)
            new_x, new_v, new_l = new_x[:room], new_v[:room], new_l[:room]
        new_ids = (st.next_id + np.arange(len(new_x))).astype(np.uint32)
        st.next_id += len(new_x)
        st.positions = np.concatenate([old[0], new_x]).astype(np.float32)
        st.velocities = np.concatenate([old[1], new_v]).astype(np.float32)
        st.lifetime = np.concatenate([old[2], new_l]).astype(np.float32)
        st.ids = np.concatenate([old[3], new_ids]).astype(np.uint32)
        if len(st.positions):
            # Inside the domain and outside every obstacle; new particles born outside
            # the domain go at once, as moved ones do in _advect.
            keep = ((st.positions >= self.lo) & (st.positions <= self.hi)).all(axis=1)
            for g in self.obstacles:
                keep &= g.sample(st.positions) > 0.0
            if not keep.all():
                n_old = len(old[0])
                self._old_kind = self._old_kind[keep[:n_old]]
                st.positions, st.velocities = st.positions[keep], st.velocities[keep]
                st.lifetime, st.ids = st.lifetime[keep], st.ids[keep]

    def _classify(self, args) -> np.ndarray:
        """(4) spray / foam / bubble for output: survivors keep the type they moved as
        this frame; new particles are classified by their fluid neighbours."""
        st, p = self.state, self.p
        n_old = len(self._old_kind)
        new = st.positions[n_old:]
        if not len(new):
            return self._old_kind
        kd = ti.ndarray(ti.i32, len(new))
        K.classify(len(new), _nd(new, ti.f32, True), *args, p.spray_below, p.bubble_above, kd)
        return np.concatenate([self._old_kind, kd.to_numpy()[: len(new)].astype(np.uint8)])

    def with_params(self, **kw) -> None:
        self.p = replace(self.p, **kw)
