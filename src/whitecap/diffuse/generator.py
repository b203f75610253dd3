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

The live particles stay on the device (issue 31): positions, velocities, lifetimes, ids and types
live in Taichi arrays made once at the capacity (budget.capacity_for; again, INFLOW_GROWTH times larger,
only when an inflow outgrows them), two sets that compaction writes one from the other. Advection, expiry,
foam aging and dissipation, the obstacles, the keep rule, lifetimes and compaction (exclusive prefix sums of
keep flags, sim/scan.py) all run in kernels; the host reads back counts only, and the live particles once a
frame, for the frame's output (they are also ``state``'s host view, for checkpoints; a state set on the host, as a
resume does, is uploaded at the next step, see FoamGenerator._sync_in). A frame's candidates are
generated, classified and placed CANDIDATE_CHUNK at a time, in arrays made once: no Taichi array is
made per frame once the largest frame was seen, and the candidates' memory does not grow with the fluid.
Output against the host version before it (main at 80c2fce): byte-identical without obstacles (the
same float operations in the same order, the same counter-based draws). With obstacles it differs in
the last bits and, rarely, more: the SDFs are now sampled by sim.obstacles.sdf_sample in f32 (the
fluid's own collisions) instead of SciPy in f64, the normal is that sampler's analytic gradient
instead of central differences, and a path is sampled at most half a cell apart for each particle
(the host version used one sample count for all, from the longest path).
"""

from __future__ import annotations

import math
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import taichi as ti
from taichi.lang.util import to_numpy_type

from ..io import ParticleFrame
from ..io.array_pool import ArrayPool
from ..io.diffuse_types import BUBBLE, FOAM, SPRAY  # noqa: F401 (the codes, for the generator's users)
from ..io.ply import record_dtype
from ..progress import console
from ..sim import runtime
from ..sim.grid import NeighborGrid, gather_vec3, grid_spec
from ..sim.records import RecordReader
from ..sim.scan import SCAN_SUMS, exclusive_scan
from ..timing import timer
from . import budget as B, kernels as K, splishsplash as SP

# the draw numbers, the rounding slot and the obstacle constants: one definition, in .kernels
from .kernels import (  # noqa: F401
    BODY_CONTACT,
    DRAW_DISSIPATE,
    DRAW_LIFE,
    PATH_SAMPLES,
    ROUNDING_SLOT,
    SPRAY_RESTITUTION,
    SURFACE_OFFSET,
)
from .params import FoamParams

#: A diffuse file's vertex record (io.ply.record_dtype of a frame of diffuse particles: x y z vx vy vz type lifetime
#: radius id, 37 bytes), made on the device from the live particles' arrays (sim.records), for the writer to write
#: as it is: the packer's sources (a, b: positions, velocities; c: lifetimes; d: ids; e: types; const: the radius).
RECORD = record_dtype(ParticleFrame(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.uint32),
                                    arrays={"type": np.zeros(0, np.uint8), "lifetime": np.zeros(0, np.float32),
                                            "radius": np.zeros(0, np.float32)}))
RECORD_SOURCES = {"x": ("a", 0), "y": ("a", 1), "z": ("a", 2), "vx": ("b", 0), "vy": ("b", 1), "vz": ("b", 2),
                  "lifetime": ("c", 0), "id": ("d", 0), "type": ("e", 0), "radius": ("const", 0)}

SURFACE_FRACTION = 0.25  # |Σ x̂ W̃| / Σ W̃ above which a particle counts as on the surface
# Neighbour-list length per fluid particle: a lattice of spacing 2r has 4/3·π·(h/2r)³ ≈ 34
# neighbours within h = 4r; 96 leaves ~3× room for water compressed in a splash.
MAX_FLUID_NEIGHBOURS = 96
# What is sized by the fluid's count (the fluid neighbour grid; the live particles' arrays, at the capacity the
# budget gives that count), when the fluid outgrows it (inflow), is made again this many times larger: not at the
# new count exactly, which would make it anew every frame of a steady inflow, and Taichi keeps the memory of every
# array that goes (an inflow of 1.5 % a frame made the live particles' twelve arrays every frame).
INFLOW_GROWTH = 1.25


def _outgrown(asked: int, held: int) -> int:
    """Rows to make for ``asked`` where ``held`` rows (0: none yet) are too few: ``asked`` the first time, and at
    least INFLOW_GROWTH times ``held`` after it."""
    return max(int(asked), 1, int(INFLOW_GROWTH * held))
# A frame's candidates are generated, classified and placed this many at a time, in arrays of this size
# made once (45 bytes a candidate: 190 MB at most): a splash makes up to ~86 a fluid particle (2.4M
# from the r = 4 mm dam break's 125k), which stored whole would grow with the fluid (3.9 kB a fluid
# particle). A frame with more is generated and classified again when it is placed (and where the
# budget thins it): a cost only past ~50k-200k fluid particles, depending on the splash.
CANDIDATE_CHUNK = 1 << 22
# The chunk on a GPU: 33.5M candidates, 1.5 GB of device memory at most. At r = 2 mm (1 M fluid particles) a splash
# makes some 19M candidates (the r = 4 mm dam break's 2.4M from 125k, eight times over): in chunks of 4M each
# frame's candidates were generated and classified two or three times over (placing, thinning), each chunk with
# its own launches and the counts it reads back. An H100 has 80 GB; the CPU keeps its 190 MB of host memory.
CANDIDATE_CHUNK_GPU = 1 << 25


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
    # (5, rows, HISTORY_SAMPLE), column by column, row j holding history_frames[j] frames, history_stride per
    # full row (budget.history_add)
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
        """The state as named arrays for a checkpoint; its numbers as 0-d arrays (what a checkpoint file
        gives back)."""
        d = {
            "positions": self.positions, "velocities": self.velocities, "lifetime": self.lifetime, "ids": self.ids,
            "next_id": np.asarray(self.next_id, np.int64), "counts": np.asarray(self.counts, np.float64).reshape(-1, 5),
        }
        if self.tau is not None:
            d["tau"] = self.tau
        d["scale"], d["history"], d["peaks"] = np.asarray(self.scale, np.float64), self.history, self.peaks
        d["history_frames"], d["history_stride"] = self.history_frames, np.asarray(self.history_stride, np.int64)
        d["type_scale"] = np.asarray(self.type_scale, np.float64)
        d["born"] = np.asarray(self.born, np.float64)
        d["foam_aging"] = np.asarray(self.foam_aging, np.float64)
        return d

    @classmethod
    def from_arrays(cls, d: dict) -> "DiffuseState":
        return cls(
            np.asarray(d["positions"], np.float32), np.asarray(d["velocities"], np.float32),
            np.asarray(d["lifetime"], np.float32), np.asarray(d["ids"], np.uint32), int(d["next_id"]),
            [tuple(r) for r in np.asarray(d["counts"]).tolist()],
            np.asarray(d["tau"], np.float32) if "tau" in d else None,
            float(d.get("scale", 1.0)),
            *_history(d),
            np.asarray(d.get("peaks", [0.0, -1.0, 0.0, 0.0, 0.0]), np.float64),
            np.asarray(d.get("type_scale", np.ones(3)), np.float64),
            np.asarray(d.get("born", np.zeros((0, 7))), np.float64).reshape(-1, 7),
            float(d.get("foam_aging", 1.0)),
        )


def _history(d: dict) -> tuple[np.ndarray, np.ndarray, int]:
    """The history from a checkpoint; one from before it was bounded has a row per frame (stride 1)
    and is bounded from here on."""
    if "history_frames" in d:
        return B.history_from_rows(d["history"]), np.asarray(d["history_frames"], np.int64), int(d["history_stride"])
    h = B.history_empty()
    for row in np.asarray(d.get("history", np.zeros((0, 0, 5))), np.float32):  # replayed a frame at a time
        h = B.history_add(*h, lambda m, row=row: row[np.linspace(0, len(row) - 1, m).astype(np.int64)])
    return h


def _velocities(fluid: ParticleFrame) -> np.ndarray:
    """The fluid frame's velocities, which the foam needs (the drivers check their files for them)."""
    if fluid.velocities is None:
        raise ValueError(f"{fluid.source}: fluid frame has no velocities")
    return fluid.velocities


def speed_squared(v: np.ndarray) -> np.ndarray:
    """|v|² of the rows of ``v`` (N × 3), in its own precision, component by component: the bits of
    ``np.einsum("ij,ij->i", v, v)`` (the same sums in the same order), 2-3× faster on a frame's velocities, which are
    strided views of its records (1.8 against 0.6 ms for a 1 M-particle frame's 65k sampled rows on 2 cores)."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    return x * x + y * y + z * z


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
    per_id = _hash_u32(np.asarray(pid, np.uint32) ^ inner)
    h = _hash_u32(np.uint32(seed) ^ _hash_u32(np.uint32(frame & 0xFFFFFFFF) ^ per_id))
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / 16777216.0)


def _rows(a: np.ndarray, dtype) -> np.ndarray:
    """``a`` as a contiguous host array for a kernel, with one zero row where it has none (the kernels read only
    the first n rows; an empty array is never handed to a kernel, which CUDA's launches would allocate at 0 bytes)."""
    a = np.ascontiguousarray(a, dtype)
    return a if len(a) else np.zeros((1, *a.shape[1:]), dtype)


def _tally(n: int, kd) -> np.ndarray:
    """How many of kd[0..n) are spray, foam and bubbles (K.tally_kinds; nothing launched for none). On a GPU the
    kernels launched before it (a chunk's classification, the compaction) are waited for first with the GIL let go
    (runtime.device_idle): the count's own wait, in Taichi, holds the GIL, and the writer's threads with it."""
    if n <= 0:
        return np.zeros(3)
    runtime.device_idle()
    return np.array(K.tally_kinds(n, kd), np.float64)


def history_picks(n: int, m: int) -> np.ndarray:
    """The m of n fluid particles (indices) a frame's history sample takes, spread evenly over the frame."""
    return np.linspace(0, n - 1, m).astype(np.int64)


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
        # the live diffuse particles on the device (_allocate_live): two sets of arrays at the capacity, the
        # current one self._live[self._cur] holding self._nd particles; self._mirror: the host arrays last
        # handed out (the state's host view), see _sync_in
        self._live: list = []
        self._cur = 0
        self._nd = 0
        self._mirror: tuple | None = None
        self.pending: Future | None = None  # the last frame's read-back while it runs (step's ``defer``; settle)
        self._pending_reads_live = False  # whether it copies from the live arrays (array by array), not the records
        # the host arrays frames are read back into (_download), used again once no frame handed out holds them
        pin, unpin = runtime.host_pinning()  # page-locked for the GPU's copies, where that is on
        self._frames = ArrayPool({"x": (np.float32, (3,)), "v": (np.float32, (3,)), "life": (np.float32, ()),
                                  "ids": (np.uint32, ()), "kind": (np.uint8, ()), "radius": (np.float32, ()),
                                  "kind32": (np.int32, ())}, pin=pin, unpin=unpin)
        self._records = RecordReader(RECORD, RECORD_SOURCES, pin=pin, unpin=unpin)  # (_download)
        self._geo: dict = {}  # the obstacles' SDFs and poses for the kernels (_obstacle_arrays)
        self._host: dict = {}  # numpy copies of some of them, reused to upload into them (see _upload)
        self._uploaded: set[str] = set()  # those whose copy in _host is what the Taichi array holds (_upload)
        self._candidates: dict | None = None
        self._S = 0
        self.capacity: int | None = None
        self._sized_for = 0  # fluid particle count the capacity was sized for
        self.last_frame: int | None = None  # the run's last frame index, where known: no peak after it
        self.looked_ahead = False  # post-processing has set 'auto' from the whole run (calibrate)
        self.obstacles = obstacles or []  # sim.obstacles.PosedSDF: see _obstacles, and nothing is born inside
        # The potentials of frames that calibrate sampled (numpy, by frame number), each dropped when step
        # uses it: a sampled frame's potentials are computed once, not again when it is processed.
        self._known: dict[int, dict[str, np.ndarray]] = {}
        self._lists = False
        self._sampled = np.zeros(0, np.int64)  # the particles _potential_arrays computed for its sample
        # the last potentials (_potential_arrays): their Taichi arrays (v_diff, crest, e_k, vort), their count, and
        # their host copy once read back (_host_potentials)
        self._pot_arrays: tuple = ()
        # Inside simulate: the solver's (positions, velocities, ids) Taichi arrays, whose first n rows are the frame
        # each step is given (FoamStage.on_start), copied on the device instead of uploaded from the host.
        self.fluid_on_device: Callable[[], tuple] | None = None
        self._pot_n = 0
        self._pots: dict[str, np.ndarray] | None = None

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

    def _moving(self, fluid: ParticleFrame, speed2: np.ndarray | None = None, rows=slice(None)) -> np.ndarray:
        """Whether each fluid particle (of ``rows``) moves, from |v|² (``speed2`` where the caller has it)."""
        if speed2 is None:
            speed2 = speed_squared(_velocities(fluid)[rows])
        return speed2 > B.moving_speed(self.g_norm, self.h) ** 2

    def calibrate(self, samples: list[ParticleFrame], times: np.ndarray, n_fluid: np.ndarray, dt: float,
                  indices: list[int] | None = None, sample_indices: list[int] | None = None) -> None:
        """Post-processing 'auto': thresholds from the potentials of frames sampled across the run
        (``samples``), of at most B.LOOK_AHEAD_SAMPLE fluid particles of each, in runs of neighbours spread
        evenly over the frame (_potential_arrays), the moving ones pooled; then the scale that puts the
        predicted peak on the budget, predicted at every frame time in ``times`` (fluid counts ``n_fluid``;
        frame numbers ``indices``) from each sample's births under those thresholds. As frames are processed
        their real birth rates replace the interpolated ones and the scale is set again (see _replan). With
        ``sample_indices`` (the samples' frame numbers), their potentials are kept until :meth:`step` reaches
        them, which then does not compute them again (_known).

        τ_k of the kinetic energy comes first, from every particle of the frames (E_k needs no neighbours; here
        in f64, on the device in f32): the floor below which a particle makes nothing (_energetic_floor) is then
        known before the other potentials, and one list build a frame serves both the sample and the births,
        which are exact (those of every particle that can make something)."""
        speed2 = [speed_squared(_velocities(f).astype(np.float64)) for f in samples]  # sum(1)'s bits, 4x faster
        moving = [self._moving(f, s) for f, s in zip(samples, speed2)]
        ke = 0.5 * np.concatenate(speed2)
        none = np.zeros_like(ke)
        tau_k = self._auto_tau({"ta": none, "wc": none, "ke": ke, "vo": none}, np.concatenate(moving))
        floor = self._energetic_floor(tau_k)
        got, rows = [], []
        for f in samples:
            self._potential_arrays(f, len(f), sample=B.LOOK_AHEAD_SAMPLE, ke_floor=floor)
            got.append(self._host_potentials())
            rows.append(self._sampled)
        pooled = {k: np.concatenate([pots[k][r] for pots, r in zip(got, rows)]) for k in ("ta", "wc", "ke", "vo")}
        tau = self._auto_tau(pooled, np.concatenate([m[r] for m, r in zip(moving, rows)]))
        tau[4:6] = tau_k[4:6]
        self.state.tau = tau
        self.looked_ahead = True
        if sample_indices is not None:
            self._known = {int(i): pots for i, pots in zip(sample_indices, got)}
        if self._scaled():
            k0 = (self.p.k_ta, self.p.k_wc, self.p.k_vo)
            t_s = np.array([f.time for f in samples], np.float64)
            rate_s = np.array([B.birth_rate(pots, tau, k0, dt) for pots in got])
            rate = np.interp(times, t_s, rate_s)
            self._plan = (B.survival_matrix(times, self.p, dt), rate, np.asarray(n_fluid, np.float64),
                          {int(i): k for k, i in enumerate(indices if indices is not None else range(len(times)))})
            self._set_scale()
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
        assert self.state.tau is not None, "calibrate set the thresholds with the plan"
        rate[k] = self._birth_rate(self.state.tau, k0, dt)
        n_fluid[k] = self._pot_n  # the real count replaces the one interpolated between samples
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
        # Only the sampled rows' flags are kept, so the whole frame's |v|² (5 ms a frame at 1 M particles, on the
        # loop's thread while the GPU waits) is computed only where an even sample finds too few moving.
        spread = slice(None, None, max(1, n // 65536))
        if all(np.count_nonzero(self._moving(fluid, rows=r)) < B.MIN_SAMPLES for r in (spread, slice(None))):
            return  # nothing moves yet: nothing would be generated

        def sample(m: int) -> np.ndarray:  # m fluid particles spread evenly over the frame (their rows alone read back)
            pick = history_picks(n, m)
            return np.concatenate([self._potentials_at(pick), self._moving(fluid, rows=pick)[None]]).T.astype(
                np.float32)

        st.history, st.history_frames, st.history_stride = B.history_add(
            st.history, st.history_frames, st.history_stride, sample)
        # τ from the moving particles of the frames so far, pooled, as post-processing does with its samples.
        h = B.history_columns(st.history, st.history_frames, st.history_stride)
        tau = self._auto_tau({k: h[c] for c, k in enumerate(("ta", "wc", "ke", "vo"))}, h[4] > 0)
        first = st.tau is None
        st.tau = tau if st.tau is None else np.maximum(st.tau, tau)
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
                st.scale = B.within_budget(st.scale, self._birth_rate(st.tau, k0, dt) * self._boost(), alive, n,
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
            f"{tau[2]:.3g}–{tau[3]:.3g}, kinetic energy {tau[4]:.3g}–{tau[5]:.3g} J/kg, "
            f"vorticity {tau[6]:.3g}–{tau[7]:.3g} 1/s; "
            + budget
        )

    def peak_report(self) -> str:
        pk = self.state.peaks
        k = self.multipliers()
        return (f"peak diffuse per fluid particle: {pk[0]:.2f} at frame {int(pk[1])} "
                f"(spray {pk[2]:.2f}, foam {pk[3]:.2f}, bubbles {pk[4]:.2f} at their own peaks)"
                + (f"; budget {self.p.budget:g} "
                   f"(spray, foam, bubbles {', '.join(f'{x:.2g}' for x in self.p.shares)} of it), "
                   f"last multipliers k_ta {k[0]:.3g}, k_wc {k[1]:.3g}, k_vo {k[2]:.3g} 1/s, by type "
                   f"{', '.join(f'{x:.3g}' for x in self.state.type_scale)}"
                   if self._scaled() else ""))

    # ------------------------------------------------------------------ one frame
    def _fluid_grid(self, n: int) -> NeighborGrid:
        if self.grid is None or self.grid.capacity < n:
            rows = _outgrown(n, self.grid.capacity if self.grid is not None else 0)
            self.grid = None  # the old grid's arrays go before the new ones are made
            self.grid = NeighborGrid(grid_spec(self.lo, self.hi, self.h / 2), rows, MAX_FLUID_NEIGHBOURS, self.h)
        return self.grid

    def _prepare(self, fluid: ParticleFrame, n: int, lists: bool = True):
        """The fluid frame in the kept Taichi arrays, its neighbour grid and, with ``lists``, its neighbour lists
        (only the potentials read them)."""
        fx, fv = self._buffer("fluid_x", n, vec=True), self._buffer("fluid_v", n, vec=True)
        fid = self._buffer("fluid_id", n, ti.u32)
        if self.fluid_on_device is not None:  # the solver's arrays hold this very frame (simulate)
            K.copy_fluid(n, *self.fluid_on_device(), fx, fv, fid)
        else:
            x, v, ids = (_rows(fluid.positions, np.float32), _rows(_velocities(fluid), np.float32),
                         _rows(fluid.ids, np.uint32))
            if runtime.rows_to_device((fx, x), (fv, v), (fid, ids)):  # CUDA: up in one copy each, the rest zeroed
                K.clear_fluid_rows(n, fx, fv, fid)
            else:
                K.copy_fluid(n, x, v, ids, fx, fv, fid)
        g = self._fluid_grid(n)
        vs = self._buffer("fluid_v_sorted", n, vec=True)  # the velocities in cell order, as the queries meet them
        if lists:
            g.build(fx, n)
            gather_vec3(n, g.order, fv, vs)
        else:
            g.build_sorted(fx, n, fv, vs)
        self._lists = lists  # whether this frame's neighbour lists were built (classify_candidates reads them)
        return fx, fv, fid, (*g.query_args(), self.h, vs)

    def _energetic_floor(self, tau: np.ndarray | None = None) -> float | None:
        """The kinetic energy below which a fluid particle surely makes nothing this frame (K.mark_energetic):
        from the thresholds of a preset or of 'auto' set from the whole run, and under a simulation's running
        'auto' from those of the frames before (they only rise: this frame's are at least these; the particles
        its history samples are marked as well, _potential_arrays). None where every particle's potentials are
        computed: FoamGenerator's model (its own potentials), and the running 'auto' until it has thresholds.
        With ``tau``, from those thresholds (calibrate's, before it sets them)."""
        p = self.p
        if p.model == "foamgenerator" or (tau is None and p.auto and not self.looked_ahead and self.state.tau is None):
            return None
        tau = np.asarray(self.thresholds() if tau is None else tau, np.float64)
        if not (np.isfinite(tau[4:6]).all() and tau[5] > tau[4]):
            return None
        return float(np.float32(tau[4]) * (1.0 - K.KE_MARGIN)) if tau[4] > 0 else -1.0

    def _potential_arrays(self, fluid: ParticleFrame, n: int, known: dict[str, np.ndarray] | None = None,
                          energetic: bool = False, sample: int | None = None, ke_floor: float | None = None):
        """Neighbours and the potentials (Taichi arrays; numpy copies in self._pots); ``known``: the frame's
        potentials as calibrate computed them, uploaded instead of computed again (the same values). With
        ``energetic`` and fixed thresholds (_energetic_floor), the potentials other than E_k are computed only
        where I_k can be > 0 (and the normals of their neighbours that the wave crest reads), 0 elsewhere:
        the same births, for a fraction of the neighbour lists. With ``sample`` (a count) and ``ke_floor``,
        those where E_k ≥ ``ke_floor`` and of ``sample`` particles alone, their indices in self._sampled: all,
        or the slots B.sample_slots of the grid's cell order (calibrate's births and sample). Runs of slots
        are neighbours, which share the normals their crests read: single particles spread evenly each took
        their own neighbours' lists as well."""
        if known is not None and all(len(a) == n for a in known.values()):
            fx, fv, fid, args = self._prepare(fluid, n, lists=False)
            pots = tuple(self._upload(k, known[name], ti.f32) for k, name in
                         (("v_diff", "ta"), ("crest", "wc"), ("e_k", "ke"), ("vort", "vo")))
            self._pots, self._pot_arrays, self._pot_n = known, pots, n
            return args, fx, fv, fid, pots
        if energetic:
            ke_floor = self._energetic_floor()
        fx, fv, fid, args = self._prepare(fluid, n, lists=False)
        g = self.grid
        assert g is not None, "_prepare built the fluid grid"
        normal, surface = self._buffer("normal", n, vec=True), self._buffer("surface", n)
        v_diff, e_k, vort, crest = (self._buffer(k, n, ti.f32) for k in ("v_diff", "e_k", "vort", "crest"))
        lists = (g.nb_count, g.nb, g.pad, g.max_neighbors)
        # Only where I_k can be > 0 and the normals the crests there read; without a floor, every particle
        # (the same kernels: each compiled once, where a run may use both ways).
        mark = self._buffer("energetic", n)
        K.mark_energetic(n, fv, -math.inf if ke_floor is None else ke_floor, e_k, mark, normal, surface, v_diff,
                         vort, crest)
        if energetic and ke_floor is not None and self.p.auto and not self.looked_ahead:  # running 'auto' samples
            picks = history_picks(n, B.history_per_frame(self.state.history_stride))
            K.mark_rows(len(picks), self._upload("history_picks", picks.astype(np.int32), ti.i32), mark, K.ENERGETIC)
        if sample is not None:  # these too (and the normals their crests read); without a floor, every particle
            self._sampled = np.arange(n) if n <= sample else g.order.to_numpy()[:n][B.sample_slots(n, sample)]
            if ke_floor is not None:
                K.mark_rows(len(self._sampled), self._upload("sample", self._sampled.astype(np.int32), ti.i32),
                            mark, K.ENERGETIC)
        subset = ke_floor is not None
        g.build_marked(n, mark, K.ENERGETIC)
        self._lists = True  # the owners' lists (classify_candidates): every owner is marked
        if self.p.model == "foamgenerator":  # SPlisHSPlasH FoamGenerator's potentials (see .splishsplash)
            self._foamgenerator_potentials(fx, fv, n, normal, v_diff, crest, e_k)
            K.zero_below(n, g.nb_count, SP.MIN_NEIGHBOURS, e_k)  # too few neighbours: I_k = 0, no generation
        else:
            pots = (SURFACE_FRACTION, normal, surface, v_diff, e_k, vort, mark)
            K.fluid_potentials(n, fx, fv, *lists, self.h, *pots, K.ENERGETIC)
            if subset:
                runtime.device_idle()  # the lists and potentials so far, waited for with the GIL let go (the count)
                if K.mark_crest_neighbours(n, fv, normal, surface, g.nb_count, g.nb, mark):
                    g.build_marked(n, mark, K.CREST_NEIGHBOUR)
                    K.fluid_potentials(n, fx, fv, *lists, self.h, *pots, K.CREST_NEIGHBOUR)
            K.wave_crest(n, fx, fv, *lists, normal, surface, self.h, crest, mark, K.ENERGETIC)
        runtime.device_idle()  # the potentials run on a GPU while the writer's thread writes (the GIL let go)
        self._pots, self._pot_arrays, self._pot_n = None, (v_diff, crest, e_k, vort), n  # read back only if asked
        return args, fx, fv, fid, (v_diff, crest, e_k, vort)

    def _host_potentials(self) -> dict[str, np.ndarray]:
        """The last _potential_arrays' potentials on the host (numpy, by name: ta, wc, ke, vo), read back once."""
        if self._pots is None:
            self._pots = dict(zip(("ta", "wc", "ke", "vo"), self._potentials_at(None)))
        return self._pots

    def _potentials_at(self, rows: np.ndarray | None) -> np.ndarray:
        """The last potentials (I_ta, I_wc, E_k, I_vo: 4 rows) of the fluid particles ``rows``, or of all where
        None, read back in one launch (K.pack_potentials)."""
        m = self._pot_n if rows is None else len(rows)
        out = np.empty((4, m), np.float32)
        if m:  # never an empty array handed to a kernel (all: one row stands in for ``rows``, unread)
            picked = _rows(np.zeros(0) if rows is None else rows, np.int32)
            K.pack_potentials(m, int(rows is not None), picked, *self._pot_arrays, out)
        return out

    def _birth_rate(self, tau: np.ndarray, k0: tuple, dt: float) -> float:
        """G, the particles the last potentials give in one frame with multipliers ``k0`` and thresholds ``tau``
        (budget.birth_rate), summed on the device (K.birth_sums): the potentials stay there."""
        n = self._pot_n
        if n <= 0:
            return 0.0
        unit = K.birth_unit(n, dt)
        s = K.birth_sums(n, *self._pot_arrays, self._upload("tau_rate", np.asarray(tau), ti.f32, unless_same=True),
                         dt, unit, runtime.on_gpu(), self._buffer("birth_total", 3, ti.i64))
        s_ta, s_wc, s_vo = (float(x) / unit for x in s)  # each exact to f64 rounding
        return float(k0[0] * s_ta + k0[1] * s_wc + k0[2] * s_vo)

    def _foamgenerator_potentials(self, fx, fv, n: int, normal, v_diff, crest, e_k) -> None:
        """SP.frame_potentials into this generator's kept arrays (v_diff, κ, E; ``normal`` as scratch)."""
        g = self.grid
        assert g is not None, "_prepare built the fluid grid"
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
        """Bytes of the Taichi arrays this generator keeps (its buffers, the live particles' two sets,
        the obstacles' SDFs, the fluid neighbour grid and the records' device array)."""
        total = (self.grid.nbytes() if self.grid is not None else 0) + self._records.nbytes
        arrays = [*self._bufs.values(), *self._geo.values()] + [a for live in self._live for a in live.values()]
        for a in arrays:
            vec = a.n * a.m if isinstance(a, ti.lang.matrix.MatrixNdarray) else (
                a.n if isinstance(a, ti.lang.matrix.VectorNdarray) else 1)
            total += int(np.prod(a.shape)) * vec * np.dtype(to_numpy_type(a.dtype)).itemsize
        return total

    def resume_arrays(self) -> dict[str, np.ndarray]:
        """What the next step depends on beyond :class:`DiffuseState`: the fluid count the capacity was sized
        for (:meth:`_size`), and post-processing 'auto''s plan as its frames so far corrected it (:meth:`_replan`:
        the birth rates and fluid counts, the scales used), so that a resumed run makes the same bytes."""
        d = {"sized_for": np.asarray(self._sized_for, np.int64)}
        plan = getattr(self, "_plan", None)
        if plan is not None:
            d["plan_rate"], d["plan_fluid"], d["plan_scales"] = plan[1], plan[2], self._scales
        return d

    def restore_resume(self, d: dict) -> None:
        """Set what :meth:`resume_arrays` gave (after :meth:`calibrate`, which makes the plan; the state is
        :attr:`state`'s). A plan of another length (another run's frames) is refused."""
        sized = int(d.get("sized_for", 0))
        if sized > 0:
            self._size(sized)
        plan = getattr(self, "_plan", None)
        if plan is not None and "plan_rate" in d:
            rate, fluid, scales = (np.asarray(d[k], np.float64) for k in ("plan_rate", "plan_fluid", "plan_scales"))
            if not len(rate) == len(fluid) == len(scales) == len(plan[1]):
                raise ValueError(f"a plan of {len(rate)} frames for a run of {len(plan[1])}")
            plan[1][:], plan[2][:], self._scales[:] = rate, fluid, scales

    def step(self, fluid: ParticleFrame, index: int, dt: float, defer: bool = False) -> ParticleFrame:
        """The diffuse particles after frame ``index`` of the fluid (``dt`` since the last frame). With ``defer``,
        on CUDA, the returned frame's arrays (and the state's host view) are still being read back from the
        device when step returns, by a thread of its own (runtime.rows_to_host_later): the caller waits for
        :attr:`pending` before it reads them (or calls :meth:`settle`); anything here that reads them, or writes
        what the copy reads, waits first. The copy reads the records' device array, which only the next frame's
        _download packs again, so the next step's potentials, advection and generation run on the device while
        it comes (a `foam` pass has little else to overlap it with; `simulate` has the solver's frame). A frame read
        back array by array (too many particles for one records array) is copied from the live arrays, which
        advection changes in place: the next step waits for it first. Elsewhere, or without ``defer``, the frame
        is whole."""
        if self._pending_reads_live:
            with timer("foam.settle"):  # the last frame's read-back, from the live arrays (defer)
                self.settle()
        st = self.state
        _velocities(fluid)  # a frame without velocities stops here, before anything is sized
        n = len(fluid)
        if self.capacity is None or n > self._sized_for:
            self._size(n)  # from the first frame, again when the fluid grows (empty first frames, inflow)
        with timer("foam.potentials"):
            args, fx, fv, fid, pots = self._potential_arrays(fluid, n, self._known.pop(index, None), energetic=True)
        with timer("foam.advect"):
            self._age(n)
            self._sync_in()
            self._advect(args, dt, index)
        with timer("foam.generate"):
            nk, born, lost = self._generate(fluid, fx, fv, fid, args, pots, n, index, dt)
        with timer("foam.compact"):
            c = self._compact(nk, lost, index)
            frame = self._download(later=defer)
        time_ = fluid.time if fluid.time is not None else index * dt
        frame.time = time_
        if self._scaled():
            st.born = B.born_add(st.born, [time_, *born, *st.type_scale], self.p, dt)
        st.counts.append((index, time_, *c))
        self._track_peak(c, n, index)
        return frame

    def _size(self, n: int) -> None:
        """Capacity from the budget (unless set); warn when a set capacity is below the budget. The live
        particles' arrays are made at the capacity, once (again, by INFLOW_GROWTH at least, only when the fluid
        outgrows it)."""
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
        self._allocate_live(self.capacity)

    # ------------------------------------------------------------------ the live particles, on the device
    def _allocate_live(self, rows: int) -> None:
        """The live particles' two sets of arrays (positions, velocities, lifetimes, ids, types; compaction
        writes one from the other) and their keep flags and places, ``rows`` each; made again larger (by
        INFLOW_GROWTH at least) only when more rows are asked for, the live ones copied over."""
        held = self._live[0]["x"].shape[0] if self._live else 0
        if held >= max(int(rows), 1):
            return
        rows = _outgrown(rows, held)  # outgrown (an inflow): larger than asked, not to be made again next frame
        self.settle()
        keep = self._download() if self._live and self._nd else None
        self._live = []  # the old arrays go before the new ones are made
        for k in ("live_keep", "live_pos"):
            self._bufs.pop(k, None)
        for _ in range(2):
            # unfilled (runtime.empty_ndarray): the rows past the live count are never read
            self._live.append({"x": runtime.empty_ndarray(ti.f32, rows, 3), "v": runtime.empty_ndarray(ti.f32, rows, 3),
                               "life": runtime.empty_ndarray(ti.f32, rows), "ids": runtime.empty_ndarray(ti.u32, rows),
                               "kind": runtime.empty_ndarray(ti.i32, rows)})
        self._cur = 0
        self._buffer("live_keep", rows)
        self._buffer("live_pos", rows)
        if keep is not None:
            self._mirror = None
            self._sync_in()

    def _sync_in(self) -> None:
        """The host's state into the live arrays where it is not the one this generator last handed out
        (a resumed checkpoint, a state set by hand): the device is otherwise the state's only home. A deferred
        read-back still running is waited for first."""
        st = self.state
        host = (st.positions, st.velocities, st.lifetime, st.ids)
        if self._mirror is not None and all(a is b for a, b in zip(host, self._mirror)):
            return
        self.settle()  # (a state set from outside while a read-back runs: the copy is done before it is replaced)
        n = len(st.positions)
        if not self._live or self._live[0]["x"].shape[0] < n:
            self._allocate_live(max(n, self.capacity or 0))
        live = self._live[self._cur]
        if n:
            K.upload_state(
                n, np.ascontiguousarray(st.positions, np.float32), np.ascontiguousarray(st.velocities, np.float32),
                np.ascontiguousarray(st.lifetime, np.float32), np.ascontiguousarray(st.ids, np.uint32),
                live["x"], live["v"], live["life"], live["ids"],
            )
        self._nd = n
        self._mirror = host

    def _download(self, later: bool = False) -> ParticleFrame:
        """The live particles as this frame's ParticleFrame, also the state's host view: their records as the
        diffuse file holds them (RECORD, sim.records), made on the device and copied back in one piece (on the
        CPU written in place), the frame's arrays views of them (ParticleFrame.from_records), so that the writer
        writes the records as they are and never packs them. The host memory is a block that no frame handed out
        before and still held anywhere shares, so a frame handed out is never changed by a later step
        (io.array_pool: blocks used again once the writer is done with them, not new pages every frame).
        ``later``: on CUDA the copy is left running (:attr:`pending`; see :meth:`step`). A frame of more records
        than one Taichi array holds (sim.records.WORDS_MAX) comes back array by array (_download_arrays)."""
        st, n = self.state, self._nd
        with timer("foam.compact.settle"):  # the last frame's read-back, where it is still coming: its records
            self.settle()  # array is packed again below (step: the frame's kernels ran meanwhile)
        if not self._records.fits(n):
            frame = self._download_arrays(later)
        else:
            live = self._live[self._cur]
            radius_bits = int(np.float32(self.p.radius * self.r).view(np.uint32))
            # (on a GPU through a device array made for as many as the live arrays hold, as they are made)
            frame, pending = self._records.read(
                n, (live["x"], live["v"], live["life"], live["ids"], live["kind"], radius_bits), live["x"].shape[0],
                later)
            if pending is not None:
                self.pending, self._pending_reads_live = pending, False
        assert frame.velocities is not None, "a diffuse frame has velocities"
        st.positions, st.velocities, st.lifetime, st.ids = (frame.positions, frame.velocities, frame.arrays["lifetime"],
                                                            frame.ids)
        self._mirror = (st.positions, st.velocities, st.lifetime, st.ids)
        return frame

    def _download_arrays(self, later: bool = False) -> ParticleFrame:
        """:meth:`_download` array by array (one copy each from the device, into an io.array_pool block of
        arrays), for the writer to pack."""
        n = self._nd
        h = self._frames.take(n)  # arrays no earlier frame still handed out holds (io.array_pool)
        x, v, life, ids, kind, radius = h["x"], h["v"], h["life"], h["ids"], h["kind"], h["radius"]
        if n:
            live = self._live[self._cur]
            kind32 = h["kind32"]  # on CUDA straight from the device, one copy each (runtime.rows_to_host)
            rows = ((x, live["x"]), (v, live["v"]), (life, live["life"]), (ids, live["ids"]), (kind32, live["kind"]))

            def narrow() -> None:  # after the driver's copies (on the read-back thread where deferred)
                kind[:] = kind32
                radius.fill(self.p.radius * self.r)

            if later and (pending := runtime.rows_to_host_later(*rows, then=narrow)) is not None:
                self.pending, self._pending_reads_live = pending, True
            elif runtime.rows_to_host(*rows):
                narrow()
            else:
                K.download_state(n, live["x"], live["v"], live["life"], live["ids"], live["kind"], x, v, life, ids,
                                 kind)
                radius.fill(self.p.radius * self.r)
        return ParticleFrame(positions=x, velocities=v, ids=ids, time=None,
                             arrays={"type": kind, "lifetime": life, "radius": radius})

    def settle(self) -> None:
        """Wait for the last frame's read-back where :meth:`step` left it running (``defer``): its arrays and the
        state's host view whole from here on, or the copy's error raised."""
        pending, self.pending = self.pending, None
        if pending is not None:
            pending.result()

    def _scan(self, n: int, a, out) -> int:
        """out[0..n) = the exclusive prefix sum of the integers a[0..n) (sim.scan); returns Σ a."""
        if n <= 0:
            return 0
        return exclusive_scan(n, a, self._buffer("scan_sums", SCAN_SUMS), out)

    def _track_peak(self, c: list, n: int, index: int) -> None:
        pk = self.state.peaks
        ratios = np.array(c, np.float64) / max(n, 1)
        if ratios.sum() > pk[0] or pk[1] < 0:
            pk[0], pk[1] = ratios.sum(), index
        pk[2:] = np.maximum(pk[2:], ratios)

    def _advect(self, args, dt, index) -> None:
        """(1) classify the live diffuse particles by their fluid neighbours and advect by type (K.advect_diffuse),
        count lifetimes down, age and dissipate foam (K.expire_diffuse), meet the obstacles
        (K.obstacles_diffuse): keep flags in live_keep, the type each moved as in the live 'kind'."""
        p, st, nd = self.p, self.state, self._nd
        if not nd:
            return
        src, dst = self._live[self._cur], self._live[1 - self._cur]
        keep = self._bufs["live_keep"]
        if self.obstacles:
            K.copy_vec3(nd, src["x"], dst["x"])  # the frame's start, for the obstacles (dst is free until compaction)
        K.advect_diffuse(
            nd, src["x"], src["v"], src["life"], *args, self.g, p.buoyancy, p.drag, dt, p.spray_below, p.bubble_above,
            ti.math.vec3(*self.lo), ti.math.vec3(*self.hi), keep, src["kind"],
            int(p.model == "foamgenerator"),  # FoamGenerator's foam keeps its own velocity
            int(p.model == "foamgenerator" and p.wall_correction),  # foam near the box's faces counted up
        )
        # Spray and bubbles count down where their type has a lifetime range; foam beyond its share under
        # 'auto' ages faster (budget.foam_aging); each foam particle survives a frame with probability exp(−λ Δt).
        extra = (st.foam_aging - 1.0) * dt if st.foam_aging > 1.0 else 0.0
        K.expire_diffuse(nd, src["life"], src["ids"], src["kind"], keep, dt, int(p.spray_lifetime is not None),
                         int(p.bubble_lifetime is not None), extra, int(p.foam_dissipation > 0),
                         math.exp(-p.foam_dissipation * dt), self.seed, index & 0xFFFFFFFF)
        if self.obstacles:
            geo = self._obstacle_arrays()
            K.obstacles_diffuse(nd, dst["x"], src["x"], src["v"], src["kind"], keep, *self._geometry(geo),
                                geo["rot0"], geo["trans0"], geo["rot1"], geo["trans1"], geo["carry_a"], geo["carry_b"],
                                geo["vel_a"], geo["vel_b"], geo["moved"], self.r)
        # On a GPU, waited for here with the GIL let go: generation's first read-back (the running 'auto''s sample,
        # the look-ahead's birth rate, the births' count) would wait for it holding the GIL, and the foam.advect
        # timer then holds the advection's own time, not generation's.
        runtime.device_idle()

    # ------------------------------------------------------------------ obstacles
    def _obstacle_arrays(self) -> dict:
        """The obstacles' SDF grids packed as sim.obstacles.ObstacleCollider packs them (made once), and their
        poses of this frame and the last (uploaded each call): what K.obstacles_diffuse reads."""
        geo = self.__dict__.get("_geo") or {}
        k = len(self.obstacles)
        if not geo:
            grids = [g.grid for g in self.obstacles]
            sizes = [g.values.size for g in grids]

            def arr(data, dtype, shape=None):
                data = np.asarray(data, to_numpy_type(dtype))
                a = (ti.Vector.ndarray(shape[0], dtype, k) if shape and len(shape) == 1 else
                     ti.Matrix.ndarray(3, 3, dtype, k) if shape else ti.ndarray(dtype, len(data)))
                a.from_numpy(data)
                return a

            geo["values"] = arr(np.concatenate([g.values.ravel() for g in grids]), ti.f32)
            geo["off"] = arr(np.concatenate([[0], np.cumsum(sizes)[:-1]]), ti.i32)
            geo["origin"] = arr([g.origin for g in grids], ti.f32, (3,))
            geo["inv_dx"] = arr([1.0 / g.spacing for g in grids], ti.f32)
            geo["dims"] = arr([g.values.shape for g in grids], ti.i32, (3,))
            geo["beyond"] = arr([g.beyond for g in grids], ti.f32)
            for name in ("rot0", "rot1", "carry_a", "vel_a"):
                geo[name] = ti.Matrix.ndarray(3, 3, ti.f32, k)
            for name in ("trans0", "trans1", "carry_b", "vel_b"):
                geo[name] = ti.Vector.ndarray(3, ti.f32, k)
            geo["moved"] = ti.ndarray(ti.i32, k)
            self._geo = geo
        from ..sim.bodies import step_velocity

        R0 = np.array([g.R0 for g in self.obstacles], np.float64)
        T0 = np.array([g.T0 for g in self.obstacles], np.float64)
        R1 = np.array([g.R1 for g in self.obstacles], np.float64)
        T1 = np.array([g.T1 for g in self.obstacles], np.float64)
        C = R1 @ R0.transpose(0, 2, 1)  # carry: x ← R1 R0ᵀ (x − T0) + T1 = C x + c
        c = T1 - np.einsum("kij,kj->ki", C, T0)
        A, b = np.zeros((k, 3, 3)), np.zeros((k, 3))
        for j, g in enumerate(self.obstacles):
            if g.dt > 0:
                A[j], b[j] = step_velocity(g.R0, g.T0, g.R1, g.T1, g.dt)
        for name, a in (("rot0", R0), ("trans0", T0), ("rot1", R1), ("trans1", T1), ("carry_a", C), ("carry_b", c),
                        ("vel_a", A), ("vel_b", b)):
            geo[name].from_numpy(a.astype(np.float32))
        geo["moved"].from_numpy(np.array([int(g.moved) for g in self.obstacles], np.int32))
        return geo

    @staticmethod
    def _geometry(geo: dict) -> tuple:
        return tuple(geo[k] for k in ("values", "off", "origin", "inv_dx", "dims", "beyond"))

    def _free(self, n: int, x, flag) -> None:
        """flag[p] = 0 for the particles inside an obstacle at this frame's pose (poses set by
        _advect/_obstacle_arrays)."""
        if self.obstacles and n:
            geo = self.__dict__.get("_geo") or self._obstacle_arrays()
            K.outside_obstacles(n, x, flag, *self._geometry(geo), geo["rot1"], geo["trans1"])

    def _obstacles(self, x0: np.ndarray, x: np.ndarray, v: np.ndarray, kind: np.ndarray):
        """Diffuse particles against the obstacles (sim.obstacles.PosedSDF, at this frame's pose and the
        last one's), after advection from x0 to x, on host arrays (K.obstacles_diffuse; the generator runs
        it on its live arrays): foam touching a moving body at the frame's start rides on it, carried
        rigidly over the frame with the body's velocity there; spray that ends the frame inside bounces
        (its normal velocity relative to the body reflected, times SPRAY_RESTITUTION) and foam inside
        moves with the body, both put back outside; a bubble inside, or a particle that cannot be put
        outside (a crease), is removed. Returns (x, v, alive). New arrays each call: for tests."""
        runtime.init(runtime.current() or "cpu")
        n = len(x)
        geo = self._obstacle_arrays()
        a0, a, av = (_nd(np.asarray(q, np.float32), ti.f32, vec=True) for q in (x0, x, v))
        kd, keep = _nd(np.asarray(kind, np.int32), ti.i32), _nd(np.ones(n, np.int32), ti.i32)
        K.obstacles_diffuse(n, a0, a, av, kd, keep, *self._geometry(geo), geo["rot0"], geo["trans0"], geo["rot1"],
                            geo["trans1"], geo["carry_a"], geo["carry_b"], geo["vel_a"], geo["vel_b"], geo["moved"],
                            self.r)
        return a.to_numpy()[:n], av.to_numpy()[:n], keep.to_numpy()[:n].astype(bool)

    # ------------------------------------------------------------------ Taichi arrays kept from frame to frame
    def _buffer(self, name: str, size: int, dtype=ti.i32, vec: bool = False, cols: int = 0, start: int = 0,
                limit: int | None = None, zeroed: bool = True):
        """A Taichi array of at least ``size`` rows kept from frame to frame (in self._bufs), grown
        geometrically (never allocated per frame once the run's largest frame has been seen): ``start`` rows
        at least when first made, and never grown past ``limit`` rows unless ``size`` needs it. (Taichi does
        not give an array's memory back to the process when the array goes: every array made per frame would
        grow the memory in use, on the CPU and on CUDA.) ``zeroed=False``: made unfilled
        (runtime.empty_ndarray), for an array whose rows are written before they are read."""
        bufs = self._bufs
        a = bufs.get(name)
        if a is None or a.shape[0] < size:
            rows = max(size, 2 * a.shape[0] if a is not None else start, 1)
            if limit is not None:
                rows = max(size, min(rows, limit), 1)
            bufs.pop(name, None)  # the old array goes before the new one is made
            self._host.pop(name, None)
            self._uploaded.discard(name)
            a = None
            shape = (rows, cols) if cols else rows
            if not zeroed:
                a = runtime.empty_ndarray(ti.f32 if vec else dtype, shape, 3 if vec else 0)
            elif vec:
                a = ti.Vector.ndarray(3, ti.f32, rows)
            else:
                a = ti.ndarray(dtype, shape)
            bufs[name] = a
        return a

    def _staging(self, name: str, a) -> np.ndarray:
        """The numpy array, shaped as kept array ``a``, through which ``name`` is uploaded (kept with it)."""
        h = self._host.get(name)
        if h is None:
            shape = tuple(a.shape) + ((3,) if isinstance(a, ti.lang.matrix.VectorNdarray) else ())
            h = self._host[name] = np.zeros(shape, to_numpy_type(a.dtype))
        return h

    def _upload(self, name: str, rows: np.ndarray, dtype=ti.f32, vec: bool = False, unless_same: bool = False, **kw):
        """``rows`` into the kept Taichi array ``name`` (see _buffer), the rows after them zero,
        through a kept numpy array: nothing allocated once the array is large enough. ``unless_same``: not
        again when the array holds these very rows (a few numbers the kernels only read, such as the
        thresholds, which are often the same from frame to frame: an upload is a launch)."""
        n = len(rows)
        a = self._buffer(name, n, dtype, vec, **kw)
        if unless_same:  # through the staging array, which then holds what the device array holds
            h = self._staging(name, a)
            cast = np.asarray(rows, h.dtype)
            if name in self._uploaded and np.array_equal(h[:n], cast) and not h[n:].any():
                return a
            h[:n], h[n:] = cast, 0
            a.from_numpy(h)
            self._uploaded.add(name)
            return a
        shape = tuple(a.shape) + ((3,) if vec else ())
        if rows.shape == shape and rows.dtype == to_numpy_type(a.dtype) and rows.flags.c_contiguous:
            a.from_numpy(rows)  # the whole array: straight from the caller's (one copy, not two)
            return a
        h = self._staging(name, a)
        h[:n] = rows
        h[n:] = 0
        a.from_numpy(h)
        return a

    # ------------------------------------------------------------------ (2) generation
    def _generate(self, fluid, fx, fv, fid, args, pots, n, index, dt):
        """(2) generation, in kernels: each fluid particle's number of candidates (K.birth_counts), each its
        own run of them (offsets: the exclusive prefix sum of the numbers, _scan); the candidates, computed
        where they are needed and never stored (K.candidate), typed only as far as the keep rule needs and
        thinned by their type's multiplier (K.candidate_limits, K.classify_candidates), CANDIDATE_CHUNK at a
        time. Under 'auto' with the budget, the kept are thinned again (K.thin_kept) so that no type passes its
        share and the frame not the budget: that reads back three counts. Returns (kept, kept by type, beyond
        slots_per_particle); _compact places the kept (the limits they were kept with in 'want')."""
        p = self.p
        v_diff, crest, e_k, vort = pots
        self._dt = dt
        self._split()
        with timer("foam.generate.auto"):  # (nested timers: where generate's time goes, in --profile)
            if p.auto and not self.looked_ahead:
                self._running_auto(n, index, dt, fluid)
            elif p.auto and self._scaled():
                self._replan(index, dt)
        tau = self._upload("tau", self.thresholds(), ti.f32, unless_same=True)
        mult = self.type_multipliers()
        most = float(mult.max())
        self._candidates = {"total": 0, "n": n}
        if most <= 0:
            return 0, [0, 0, 0], 0
        k = [x * most for x in self.multipliers()]  # candidates for the most generous type; cut below
        cap = self._S = p.slots_per_particle or 0
        m = max(n, 1)
        cnt, rate = self._buffer("count", m), self._buffer("rate", m, ti.f32)
        frame = index & 0xFFFFFFFF
        half_up = int(p.model == "foamgenerator")  # FoamGenerator rounds half up
        with timer("foam.generate.counts"):
            lost = int(K.birth_counts(n, fid, v_diff, crest, e_k, vort, tau, k[0], k[1], k[2], dt, self.seed, frame,
                                      cap, cnt, rate, half_up))
            off = self._buffer("offset", m)
            total = self._scan(n, cnt, off)
        self._candidates["total"] = total
        if not total:
            return 0, [0, 0, 0], lost
        # The type each new particle is born as; a particle of type t is kept when its slot is
        # below its fluid particle's n_d·m_t, rounded with the kernel's own random number: the
        # particles of a type whose multiplier is unchanged stay exactly the same. The limits
        # (per fluid particle and type) are known before the types, so the classification does
        # only the work that decides whether a candidate is kept.
        mult32 = self._upload("mult", mult.astype(np.float32), ti.f32, unless_same=True)
        most32 = np.float32(most)
        lim, want = self._buffer("limit", m, cols=3), self._buffer("want", m, ti.f32, cols=3)
        K.candidate_limits(n, cnt, rate, fid, most32, mult32, self.seed, frame, half_up, want, lim)
        chunk = min(total, self._chunk())
        # grown geometrically, never past a chunk; first made for as many as the live particles' capacity (a
        # splash's candidates grow over its first frames: made at the first frame's count, they grew 5 times)
        up = self._candidate_sizes()
        kd, owner = self._buffer("cand_kind", chunk, ti.i8, **up), self._buffer("cand_owner", chunk, **up)
        g = self.grid
        box = (p.spray_below, p.bubble_above, ti.math.vec3(*self.lo), ti.math.vec3(*self.hi),
               int(p.model == "foamgenerator" and p.wall_correction))
        self._thin = False  # no thinning beyond the limits (yet)

        cx, cv = self._buffer("cand_x", chunk, vec=True, **up), self._buffer("cand_v", chunk, vec=True, **up)
        cl = self._buffer("cand_life", chunk, ti.f32, **up)

        probe = self._buffer("owner_probe", m * K.REACH_PROBES, vec=True)
        reach = self._buffer("owner_reach", m * K.REACH_PROBES, ti.f32)
        if self._lists:  # the owners' reach, for their spray-only candidates (K.owner_reach)
            K.owner_reach(n, lim, fx, fv, g.nb_count, g.nb, self.h, p.spray_below, self.r, dt, probe, reach)
        else:
            reach.fill(-1.0)

        def classify(base: int, size: int) -> None:
            K.chunk_owners(n, base, size, cnt, off, owner)
            K.generate_candidates(size, base, owner, off, lim, fx, fv, fid, e_k, tau, p.lifetime_min, p.lifetime_max,
                                  p.lifetime_multiplier, self.r, dt, self.seed, frame, reach, cx, cv, cl)
            K.classify_candidates(size, base, owner, off, lim, cx, cl, fx, g.nb_count, g.nb, int(self._lists), probe,
                                  reach, *args[:3], *box, kd)

        def thin(base: int, size: int) -> None:
            K.thin_kept(size, base, kd, owner, off, want, fid, self.seed, frame, half_up)

        self._chunks = (total, chunk, classify, thin)
        made = np.zeros(3)
        with timer("foam.generate.classify"):
            for base in range(0, total, chunk):
                classify(base, min(chunk, total - base))
                made += _tally(min(chunk, total - base), kd)
        if self._scaled():
            with timer("foam.generate.thin"):
                made = self._within_shares(made, n, want)
        return int(made.sum()), [int(x) for x in made], lost

    def _within_shares(self, made: np.ndarray, n: int, want) -> np.ndarray:
        """The kept by type, thinned (K.scale_want, then _thinned) where a type would pass its share of the
        budget or the frame the budget itself."""
        p = self.p
        # The type scales can make one frame's births far more than the birth rate foretold
        # (a burst of the type scaled furthest up): never past the budget in one frame, and
        # no type past its share of it (times its own multiplier, which the budget counts at 1),
        # so a type born early and living long (foam) cannot take the room of one born later
        # or living briefly (spray).
        live = np.asarray(self.state.counts[-1][2:] if self.state.counts else (0, 0, 0), np.float64)
        share = np.asarray(p.shares, np.float64) * np.asarray(p.type_multipliers, np.float64)
        room = np.maximum(p.budget * n * share - live, 0.0)
        cut = np.where(made > room, room / np.maximum(made, 1.0), 1.0).astype(np.float32)
        if (cut < 1).any():
            K.scale_want(n, want, self._upload("cut", cut, ti.f32))
            made = self._thinned()
        room = p.budget * n - live.sum()
        if made.sum() > max(room, 0):
            K.scale_want(n, want, self._upload("cut", np.full(3, max(room, 0) / made.sum(), np.float32), ti.f32))
            made = self._thinned()
        return made

    def _candidate_sizes(self) -> dict:
        """_buffer's sizes for the candidates' arrays: at most a chunk, first made at the live capacity; unfilled
        (each kernel writes a chunk's rows before the next reads them)."""
        most = self._chunk()
        return {"limit": most, "start": min(self.capacity or 0, most), "zeroed": False}

    @staticmethod
    def _chunk() -> int:
        """Candidates generated, classified and placed at a time: CANDIDATE_CHUNK, CANDIDATE_CHUNK_GPU on a GPU (the
        same particles either way: tests/test_diffuse_generate.py)."""
        return CANDIDATE_CHUNK_GPU if runtime.on_gpu() else CANDIDATE_CHUNK

    def _thinned(self) -> np.ndarray:
        """The kept candidates by type under the limits in 'want' (K.thin_kept: in place where one chunk holds
        them all, thinner limits keep a subset; chunk by chunk, classified again, otherwise)."""
        self._thin = True
        total, chunk, classify, thin = self._chunks
        made = np.zeros(3)
        for base in range(0, total, chunk):
            if total > chunk:
                classify(base, min(chunk, total - base))
            thin(base, min(chunk, total - base))
            made += _tally(min(chunk, total - base), self._bufs["cand_kind"])
        return made

    def candidates(self) -> dict:
        """The last frame's candidates (tests): total, each fluid particle's count and offset, and the kept
        (their indices, in candidate order) where one chunk held them all."""
        c = self._candidates
        assert c is not None, "step made the last frame's candidates"
        n = c["n"]
        total = c["total"]
        out = {
            "total": total, "counts": self._bufs["count"].to_numpy()[:n], "offset": self._bufs["offset"].to_numpy()[:n],
        }
        if 0 < total <= self._chunk():
            out["kept"] = np.flatnonzero(self._bufs["cand_kind"].to_numpy()[:total] >= 0)
        return out

    # ------------------------------------------------------------------ (3) compaction
    def _compact(self, nk: int, lost: int, index: int) -> list[int]:
        """(3) survivors first, in their order, then the new particles in candidate order (their ids
        next_id + their rank among the kept, as many as fit the capacity): a fixed order, no global counter.
        Places are exclusive prefix sums of keep flags (_scan); particles outside the domain or inside an
        obstacle go. The new particles are placed a chunk of candidates at a time (classified and thinned
        again where the frame had more than one chunk). Returns the count of each type."""
        st = self.state
        src, dst = self._live[self._cur], self._live[1 - self._cur]
        keep, pos = self._bufs["live_keep"], self._bufs["live_pos"]
        lo, hi = ti.math.vec3(*self.lo), ti.math.vec3(*self.hi)
        nd = self._nd
        ns = self._scan(nd, keep, pos)  # the survivors of advection, expiry and the obstacles
        assert self.capacity is not None, "step sized the capacity (_size) before compacting"
        room = self.capacity - ns
        if nk > room or lost:
            if not self._warned_capacity:
                slots = f"{lost:,} beyond foam.slots_per_particle = {self._S} per fluid particle, " if lost else ""
                console.print(
                    f"[yellow]warning:[/] foam capacity saturated at frame {index}: {nk + lost:,} new particles "
                    f"wanted, {slots}{max(nk - max(room, 0), 0):,} beyond foam.max_particles = {self.capacity:,} "
                    f"({ns:,} alive); the excess is dropped (raise these to keep it). Said once per run."
                )
                self._warned_capacity = True
            room = max(room, 0)
        if self.obstacles and ns:  # moved out of the domain or into another obstacle by the obstacle pass
            K.outside_box(nd, src["x"], keep, lo, hi)
            self._free(nd, src["x"], keep)
            ns = self._scan(nd, keep, pos)
        if ns:
            K.scatter_survivors(nd, keep, pos, src["x"], src["v"], src["life"], src["ids"], src["kind"],
                                dst["x"], dst["v"], dst["life"], dst["ids"], dst["kind"])
        placed = 0
        if nk and room:
            placed = self._place_new(room, ns, index, dst)
            st.next_id += min(nk, room)
        self._cur = 1 - self._cur
        self._nd = ns + placed
        return [int(x) for x in _tally(self._nd, dst["kind"])]

    def _place_new(self, room: int, ns: int, index: int, dst: dict) -> int:
        """The kept candidates that fit ``room``, in the domain and outside the obstacles, into ``dst`` after
        the ``ns`` survivors, chunk by chunk; returns how many."""
        p, st, b = self.p, self.state, self._bufs
        total, chunk, classify, thin = self._chunks
        kd, owner, off, fid = b["cand_kind"], b["cand_owner"], b["offset"], b["fluid_id"]
        up = self._candidate_sizes()
        flag = self._buffer("cand_flag", chunk, **up)
        rank = self._buffer("cand_rank", chunk, **up)
        at, cx = self._buffer("cand_pos", chunk, **up), b["cand_x"]
        frame = index & 0xFFFFFFFF
        lo, hi = ti.math.vec3(*self.lo), ti.math.vec3(*self.hi)
        rng = [ti.math.vec3(r[0], r[1] - r[0], 1.0) if r is not None else ti.math.vec3(0.0)
               for r in (p.spray_lifetime, p.bubble_lifetime)]
        kept_before, placed = 0, 0
        for base in range(0, total, chunk):
            size = min(chunk, total - base)
            if total > chunk:  # the chunk's types again, thinned as _generate thinned them
                classify(base, size)
                if self._thin:
                    thin(base, size)
            K.kept_flags(size, kd, flag)
            kept = self._scan(size, flag, rank)
            if kept:
                K.place_new(size, kd, rank, kept_before, room, cx, lo, hi, flag)
                self._free(size, cx, flag)  # nothing is born inside an obstacle
                here = self._scan(size, flag, at)
                if here:
                    K.scatter_new(size, base, flag, at, rank, kept_before, ns + placed, st.next_id & 0xFFFFFFFF, kd,
                                  owner, off, fid, b["e_k"], b["tau"], cx, b["cand_v"], b["cand_life"],
                                  p.lifetime_min, rng[0], rng[1], int(p.model == "foamgenerator"),
                                  max(p.lifetime_max - p.lifetime_min, 1e-30), p.lifetime_min,
                                  p.lifetime_max - p.lifetime_min, self.seed, frame,
                                  dst["x"], dst["v"], dst["life"], dst["ids"], dst["kind"])
                placed += here
            kept_before += kept
            if kept_before >= room:
                break  # no later candidate fits
        return placed

    def with_params(self, **kw) -> None:
        self.p = replace(self.p, **kw)
