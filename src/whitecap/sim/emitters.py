"""Inflow and outflow: ``[[emitter]]`` adds particles during the run, ``[[sink]]`` removes them.

Emission (the inlet of SPlisHSPlasH's emitters and DualSPHysics' inout zones, reduced to
its core): an emitter's face carries a square lattice of sites at the rest spacing 2r
(:meth:`whitecap.config.Emitter.sites`). Its k-th particle is due at
t_k = start + k / ṅ (ṅ particles per second, from the rate: ṅ = Q / (2r)³) and takes
site k mod N, the sites visited in a fixed shuffled order so that a partly filled layer
is spread over the face. At the start of each step every particle due by then enters at
its site, moved on along the inflow velocity v by its age: x = site + v (t − t_k). A site
is taken again N / ṅ later, when its last particle has advanced ≥ 2r (the scene check
ṅ ≤ N |v·d| / 2r), so particles enter without overlap, and the count is exact to one
particle at any time.

Removal: after each step, a particle inside any sink is dropped and the others close up
in their order (a stable compaction on the device, sim/scan.py), so no particle ends a step inside a sink.

Ids: the initial fluid has 0 … n−1; each new particle takes ``next_id`` and increments
it, so an id is never given twice, even after its particle left. ``next_id``, the count
each emitter has added and the live count are checkpointed with the state, which makes a
resume continue byte for byte.

The solver's arrays are allocated at a capacity (:func:`capacity`): the initial fluid
plus all the emitters add over the run, or ``solver.max_particles``.
"""


import math

import numpy as np
import taichi as ti

from ..config import Scene
from ..errors import InputError, SimulationError
from .grid import F3, I1
from .scan import SCAN_SUMS, exclusive_scan

#: Rows of the sinks' array, per sink: a box (lo, hi) and a half space (point, normal) that
#: a particle must both be in. A box sink has a zero normal (its half space is everything);
#: a plane sink the domain grown by a metre as its box.
SINK_ROWS = 4


@ti.kernel
def insert_particles(n0: ti.i32, k: ti.i32, src_x: F3, src_v: F3, src_id: I1, x: F3, v: F3, ids: I1):
    """Slots n0 … n0+k−1 take the k staged particles (position, velocity, id)."""
    for j in range(k):
        x[n0 + j] = src_x[j]
        v[n0 + j] = src_v[j]
        ids[n0 + j] = src_id[j]


@ti.kernel
def mark_in_sinks(n: ti.i32, x: F3, sinks: F3, nsinks: ti.i32, gone: I1) -> ti.i32:
    """gone_i = 1 where x_i lies in a sink (in its box and on the removed side of its plane:
    (x_i − p)·n ≥ 0); returns how many are gone."""
    count = 0
    for i in range(n):
        g = 0
        for s in range(nsinks):
            lo, hi = sinks[SINK_ROWS * s], sinks[SINK_ROWS * s + 1]
            p0, nrm = sinks[SINK_ROWS * s + 2], sinks[SINK_ROWS * s + 3]
            xi = x[i]
            inside = 1
            for a in ti.static(range(3)):
                if xi[a] < lo[a] or xi[a] > hi[a]:
                    inside = 0
            if inside == 1 and (xi - p0).dot(nrm) >= 0.0:
                g = 1
        gone[i] = g
        count += g
    return count


@ti.kernel
def close_up(n: ti.i32, gone: I1, before: I1, x: F3, v: F3, ids: I1, tx: F3, tv: F3, tid: I1):
    """The particles left, in order, into the scratch arrays: particle i (not gone) goes to
    i − before_i, before_i the number gone ahead of it (the exclusive prefix sum of gone)."""
    for i in range(n):
        if gone[i] == 0:
            j = i - before[i]
            tx[j], tv[j], tid[j] = x[i], v[i], ids[i]


@ti.kernel
def take_back(m: ti.i32, cap: ti.i32, tx: F3, tv: F3, tid: I1, x: F3, v: F3, ids: I1):
    """Slots 0 … m−1 from the scratch arrays, the rest of the capacity zero (as at the start)."""
    for i in range(cap):
        if i < m:
            x[i], v[i], ids[i] = tx[i], tv[i], tid[i]
        else:
            x[i], v[i], ids[i] = ti.math.vec3(0.0), ti.math.vec3(0.0), 0


def run_duration(scene: Scene, frames: int | None = None) -> float:
    """The simulated time of the run [s]: its frames over the frame rate."""
    return (scene.output.frames if frames is None else max(frames, scene.output.frames)) / scene.solver.frame_rate


def capacity(scene: Scene, n_initial: int, frames: int | None = None) -> int:
    """Particles the solver's arrays hold: ``solver.max_particles``, else the initial count plus
    everything the emitters add over the run (the run's frames, or ``frames`` if more). Without
    emitters, the initial count."""
    if not scene.emitter:
        return n_initial if scene.solver.max_particles is None else max(n_initial, scene.solver.max_particles)
    if scene.solver.max_particles is not None:
        return scene.solver.max_particles
    r, t = scene.solver.particle_radius, run_duration(scene, frames)
    return n_initial + sum(e.emitted_by(r, t) for e in scene.emitter)


class Sources:
    """The scene's emitters and sinks, acting on a :class:`~whitecap.sim.pbf.PBFSolver` each step."""

    def __init__(self, scene: Scene, solver, obstacles=None, where: str = "") -> None:
        r = scene.solver.particle_radius
        self.scene = scene
        self.where = where
        self.sites, self.dirs, self.vel, self.rates, self.starts, self.stops = [], [], [], [], [], []
        for k, e in enumerate(scene.emitter):
            g, d, _ = e.sites(r)
            if obstacles and not obstacles.outside_mask(g.astype(np.float32)).all():
                inside = int((~obstacles.outside_mask(g.astype(np.float32))).sum())
                raise InputError(f"{where}emitter[{k}]: {inside} of its {len(g)} sites lie inside an obstacle or the "
                                 f"terrain; move it (emitter[{k}].lower/upper/center) into open space")
            order = np.random.default_rng([scene.seed, k]).permutation(len(g))  # spread a partial layer
            self.sites.append(g[order])
            self.dirs.append(d)
            self.vel.append(np.asarray(e.velocity, np.float64))
            self.rates.append(e.per_second(r))
            self.starts.append(e.start)
            self.stops.append(math.inf if e.stop is None else e.stop)
        self.emitted = np.zeros(len(scene.emitter), np.int64)  # particles each emitter has added
        # The most one step adds: all that is due over one frame, plus one per emitter.
        frame_dt = 1.0 / scene.solver.frame_rate
        self.staging_size = max(1, sum(math.ceil(q * frame_dt) + 1 for q in self.rates))
        self.stage_x = self.stage_v = self.stage_id = None
        if scene.emitter:
            self.stage_x = ti.Vector.ndarray(3, ti.f32, self.staging_size)
            self.stage_v = ti.Vector.ndarray(3, ti.f32, self.staging_size)
            self.stage_id = ti.ndarray(ti.i32, self.staging_size)
        self.nsinks = len(scene.sink)
        self.sinks = self.gone = None
        if scene.sink:
            lo, hi = np.asarray(scene.domain.lower) - 1.0, np.asarray(scene.domain.upper) + 1.0
            rows: list = []  # 4 vectors a sink
            for s in scene.sink:
                if s.shape == "box":
                    rows += [s.lower, s.upper, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
                else:
                    nrm = np.asarray(s.normal, np.float64)
                    rows += [lo, hi, s.point, nrm / np.linalg.norm(nrm)]
            self.sinks = ti.Vector.ndarray(3, ti.f32, len(rows))
            self.sinks.from_numpy(np.asarray(rows, np.float32))
            cap = solver.capacity
            self.gone = ti.ndarray(ti.i32, cap)
            # made once: the prefix sum of gone and the scratch arrays the rest close up into
            self.before, self.scan_sums = ti.ndarray(ti.i32, cap), ti.ndarray(ti.i32, SCAN_SUMS)
            self.tx, self.tv, self.tid = ti.Vector.ndarray(3, ti.f32, cap), ti.Vector.ndarray(3, ti.f32, cap), \
                ti.ndarray(ti.i32, cap)
        self.removed = 0  # particles the sinks took (statistics; not part of the state)

    def __bool__(self) -> bool:
        return bool(self.rates) or self.nsinks > 0

    # ------------------------------------------------------------ per step
    def due(self, t: float) -> np.ndarray:
        """How many particles each emitter has added by time ``t`` (those with t_k ≤ t)."""
        out = np.zeros(len(self.rates), np.int64)
        for k, (q, t0, t1) in enumerate(zip(self.rates, self.starts, self.stops)):
            end = min(t, t1)
            out[k] = 0 if end < t0 else math.floor(q * (end - t0) + 1e-9) + 1
        return out

    def emit(self, solver) -> int:
        """Add every particle due by the solver's time; returns how many."""
        if not self.rates:
            return 0
        t = solver.time
        due = self.due(t)
        new = int((due - self.emitted).sum())
        if new <= 0:
            return 0
        if solver.n + new > solver.capacity:
            raise SimulationError(
                f"{self.where}solver.max_particles: the particle capacity ({solver.capacity:,}) is full at "
                f"t={t:.4f} s: the emitters add faster than the sinks remove; raise solver.max_particles or "
                "lower the emitters' rates")
        xs, vs = [], []
        for k in range(len(self.rates)):
            ks = np.arange(self.emitted[k], due[k], dtype=np.int64)
            if not len(ks):
                continue
            age = t - (self.starts[k] + ks / self.rates[k])  # t − t_k ≥ 0
            sites = self.sites[k][ks % len(self.sites[k])]
            xs.append(sites + age[:, None] * self.vel[k])
            vs.append(np.broadcast_to(self.vel[k], sites.shape))
        self.emitted = due
        x, v = np.concatenate(xs), np.concatenate(vs)
        ids = np.arange(solver.next_id, solver.next_id + new, dtype=np.int64)
        assert self.stage_x is not None and self.stage_v is not None and self.stage_id is not None  # made with rates
        if ids[-1] >= 2**31:
            raise SimulationError(f"{self.where}emitter: particle ids ran past 2³¹ at t={t:.4f} s")
        for lo in range(0, new, self.staging_size):  # in batches of the staging arrays' size
            hi = min(new, lo + self.staging_size)
            pad = lambda a, dt: np.concatenate([a, np.zeros((self.staging_size - len(a),) + a.shape[1:], dt)])  # noqa: E731
            self.stage_x.from_numpy(pad(x[lo:hi].astype(np.float32), np.float32))
            self.stage_v.from_numpy(pad(v[lo:hi].astype(np.float32), np.float32))
            self.stage_id.from_numpy(pad(ids[lo:hi].astype(np.int32), np.int32))
            st = solver.state
            insert_particles(solver.n, hi - lo, self.stage_x, self.stage_v, self.stage_id, st.x, st.v, st.ids)
            solver.n += hi - lo
        solver.next_id += new
        return new

    def drain(self, solver) -> int:
        """Remove every particle inside a sink, the others kept in order; returns how many."""
        if not self.nsinks or solver.n == 0:
            return 0
        st = solver.state
        k = int(mark_in_sinks(solver.n, st.x, self.sinks, self.nsinks, self.gone))
        if k == 0:
            return 0
        n = solver.n
        # on the device, in a fixed order (sim/scan.py): nothing crosses to the host
        exclusive_scan(n, self.gone, self.scan_sums, self.before)
        close_up(n, self.gone, self.before, st.x, st.v, st.ids, self.tx, self.tv, self.tid)
        take_back(n - k, solver.capacity, self.tx, self.tv, self.tid, st.x, st.v, st.ids)
        solver.n = n - k
        self.removed += k
        return k

    # ------------------------------------------------------------ checkpoint
    def checkpoint(self) -> dict[str, np.ndarray]:
        return {"emitted": self.emitted.copy()}

    def restore(self, data: dict) -> None:
        if "emitted" in data:
            self.emitted = np.asarray(data["emitted"], np.int64).copy()
