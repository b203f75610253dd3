"""Generation of new diffuse particles (diffuse/generator.py FoamGenerator._generate): the kept
candidates are those the old way (every candidate classified by its full fluid-neighbour count, then
the keep rule) keeps, and they are compacted exactly once each, in candidate order."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from whitecap import io
from whitecap.diffuse.params import resolve

R = 0.01
DT = 1.0 / 120.0


def _splash(n: int = 12):
    """A jittered lattice block of water with a sheared, rising velocity field: its upper part throws
    candidates into the air (spray), its lower part keeps them in the water (foam, bubbles)."""
    g = np.arange(n) * 2 * R
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3).astype(np.float32) + 0.3
    x += np.random.default_rng(5).uniform(-0.05 * R, 0.05 * R, x.shape).astype(np.float32)
    z = (x[:, 2] - x[:, 2].min()) / (2 * R * (n - 1))
    v = np.stack([1.5 * z, 0.3 * np.sin(9 * x[:, 0]), 0.8 * z * z + 0.2], axis=1).astype(np.float32) * 3.0
    ids = np.random.default_rng(6).permutation(len(x)).astype(np.uint32)
    return io.ParticleFrame(positions=x, velocities=v, ids=ids)


def _generator(multipliers):
    from whitecap.diffuse.generator import FoamGenerator

    p = resolve(preset="ihmsen2012")
    # low thresholds and a large k: tens of candidates a fluid particle, most of them not kept
    p = replace(p, ta_min=0.0, ta_max=2.0, wc_min=0.0, wc_max=1.0, ke_min=0.0, ke_max=4.0, k_ta=500.0, k_wc=500.0,
                type_multipliers=multipliers, foam_dissipation=0.0)
    return FoamGenerator(p, R, ([-1, -1, -1], [2, 2, 2]), (0, 0, -9.81), seed=11)


def _all_candidates(gen, frame, index):
    """Every candidate of the frame, written by the reference generate (per fluid particle, into stored arrays)."""
    import taichi as ti

    from .diffuse_reference import generate

    p, c, n = gen.p, gen.candidates(), len(frame)
    total = c["total"]
    fx, fv, fid, args = gen._prepare(frame, n)
    out = [ti.Vector.ndarray(3, ti.f32, total), ti.Vector.ndarray(3, ti.f32, total), ti.ndarray(ti.f32, total)]
    generate(n, fx, fv, fid, gen._bufs["e_k"], gen._bufs["tau"], gen._bufs["count"], gen._bufs["offset"],
             p.lifetime_min, p.lifetime_max, p.lifetime_multiplier, gen.r, DT, gen.seed, index, *out)
    return [a.to_numpy()[:total] for a in out], args


def _reference_keep(gen, frame, index):
    """The kept candidates the old way: every candidate's type from its full fluid count
    (kernels.classify), then a candidate at slot s of fluid particle i, of type t, is kept when
    s < n_d·m_t rounded with the particle's own draw."""
    import taichi as ti

    from whitecap.diffuse import kernels as K
    from whitecap.diffuse.generator import ROUNDING_SLOT, _nd, uniform

    p, c, n = gen.p, gen.candidates(), len(frame)
    total, counts, offset = c["total"], c["counts"], c["offset"]
    (x, v, life), args = _all_candidates(gen, frame, index)
    kd = ti.ndarray(ti.i32, total)
    K.classify(total, _nd(x, ti.f32, True), *args, p.spray_below, p.bubble_above, ti.math.vec3(*gen.lo),
               ti.math.vec3(*gen.hi), 0, kd)
    kind = kd.to_numpy()
    mult = gen.type_multipliers()
    rows = np.flatnonzero(counts)
    nd0 = gen._bufs["rate"].to_numpy()[:n][rows].astype(np.float32) / np.float32(mult.max())
    u0 = uniform(gen.seed, index, frame.ids[rows], ROUNDING_SLOT, 0)
    want = nd0[:, None] * mult.astype(np.float32)[None, :]
    limit = np.floor(want) + (u0[:, None] < want - np.floor(want))
    owner = np.repeat(np.arange(len(rows)), counts[rows])
    slot = np.arange(total) - offset[rows][owner]
    return slot < limit[owner, kind], kind, x


@pytest.mark.parametrize("multipliers, thinned", [
    ((30.0, 1.0, 1.0), 10),  # candidates at spray's rate: most slots can only be spray
    ((1.0, 1.0, 1.0), 1),  # every candidate kept
    ((2.0, 8.0, 0.5), 2),
    ((0.0, 1.0, 3.0), 1),
])
def test_the_kept_candidates_are_those_the_full_classification_keeps(multipliers, thinned):
    gen = _generator(multipliers)
    frame = _splash()
    d = gen.step(frame, 0, DT)
    c = gen.candidates()
    keep, kind, x = _reference_keep(gen, frame, 0)
    # many candidates (with spray first: most not kept)
    assert c["total"] > 3_000 and c["total"] >= thinned * keep.sum()
    np.testing.assert_array_equal(c["kept"], np.flatnonzero(keep))
    # the frame's particles (none alive before it, none outside the domain) are exactly the kept candidates
    np.testing.assert_array_equal(d.positions, x[keep])
    np.testing.assert_array_equal(d.arrays["type"], kind[keep].astype(np.uint8))
    made = np.bincount(kind[keep], minlength=3)
    assert all((made[t] > 20) == (multipliers[t] > 0) for t in range(3)), made  # every type made that may be


def test_compaction_keeps_each_kept_candidate_once_in_candidate_order():
    gen = _generator((30.0, 1.0, 1.0))
    frame = _splash()
    d = gen.step(frame, 0, DT)
    c = gen.candidates()
    kept, total, m = c["kept"], c["total"], len(c["kept"])
    assert m > 100 and np.all(np.diff(kept) > 0) and kept[-1] < total  # once each, in candidate order
    # the first frame's particles (none alive before it, none outside the domain) are the kept candidates
    # as the reference generate (tests/diffuse_reference.py) writes them, bit for bit, in candidate order,
    # with ids 0, 1, 2, ...
    (x, v, life), _ = _all_candidates(gen, frame, 0)
    np.testing.assert_array_equal(d.positions, x[kept])
    np.testing.assert_array_equal(d.velocities, v[kept])
    np.testing.assert_array_equal(d.arrays["lifetime"], life[kept])
    np.testing.assert_array_equal(d.ids, np.arange(m, dtype=np.uint32))
    assert gen.state.next_id == m
    # each fluid particle's run [offset, offset + count) follows the one before
    np.testing.assert_array_equal(c["offset"], np.concatenate([[0], np.cumsum(c["counts"])[:-1]]))


@pytest.mark.parametrize("chunk", [None, 700])
def test_new_particles_beyond_the_capacity_are_dropped_in_candidate_order(monkeypatch, chunk):
    """With room for 50 new particles, the first 50 kept candidates (in candidate order) are born; with room for
    half of them and the candidates taken 700 at a time, the room is the frame's, not each chunk's: the room runs
    out in a later chunk than the first, and no more are born than fit."""
    from whitecap.diffuse import generator as G

    full = _generator((30.0, 1.0, 1.0))
    frame = _splash()
    everything = full.step(frame, 0, DT)
    kept = full.candidates()["kept"]  # the kept candidates' indices, in candidate order (one chunk held them)
    if chunk is not None:
        monkeypatch.setattr(G, "CANDIDATE_CHUNK", chunk)
    room = 50 if chunk is None else len(everything) // 2
    gen = _generator((30.0, 1.0, 1.0))
    gen._size(len(frame))
    gen.capacity = room
    d = gen.step(frame, 0, DT)
    assert len(everything) > 1000 and len(d) == room and gen.state.next_id == room
    if chunk is not None:  # several chunks, and the first one's kept candidates leave room for later ones
        assert gen._candidates["total"] > 3 * chunk and gen._bufs["cand_kind"].shape[0] == chunk
        assert 0 < np.count_nonzero(kept < chunk) < room < len(kept)
    assert d.positions.tobytes() == everything.positions[:room].tobytes()
    assert d.ids.tobytes() == everything.ids[:room].tobytes()


def test_the_candidate_buffers_are_reused_from_frame_to_frame():
    gen = _generator((30.0, 1.0, 1.0))
    frame = _splash()
    gen.step(frame, 0, DT)
    before = {k: id(v) for k, v in gen._bufs.items()}
    for _ in range(3):
        gen.step(frame, 0, DT)  # the same candidates again (and the diffuse particles of the frames before)
    grown = [k for k, v in gen._bufs.items() if id(v) != before.get(k)]
    assert not grown, grown


@pytest.mark.parametrize("preset", ["ihmsen2012", "auto"])
def test_candidates_a_chunk_at_a_time_give_the_same_bytes(monkeypatch, preset):
    """A frame's candidates classified and placed in chunks of 700 (the splash makes thousands) give the
    frames one chunk gives, byte for byte, and the candidate arrays stay at the chunk's size."""
    from whitecap.diffuse import generator as G

    thinned = []
    thin = G.K.thin_kept
    monkeypatch.setattr(G.K, "thin_kept", lambda *a: thinned.append(1) or thin(*a))

    def run():
        gen = _generator((30.0, 1.0, 1.0))
        if preset == "auto":  # the budget's multipliers on the low thresholds: each type cut to its share
            gen.p = replace(gen.p, auto=True, budget=0.5)
            gen.looked_ahead, gen.state.tau = True, gen.base_thresholds()
        frames = [_splash()]
        for k in range(1, 4):  # the splash moved on: some die, some change type, new ones are born
            f = _splash()
            f.positions = f.positions + k * DT * f.velocities
            frames.append(f)
        out, most = [], 0
        for k, f in enumerate(frames):
            out.append(gen.step(f, k, DT))
            most = max(most, gen._candidates["total"])
        return out, gen, most

    whole, g1, _ = run()
    monkeypatch.setattr(G, "CANDIDATE_CHUNK", 700)
    chunked, g2, most = run()
    assert most > 3 * 700 and g2._bufs["cand_kind"].shape[0] == 700
    assert sum(len(d) for d in whole) > 1000
    for a, b in zip(whole, chunked):
        for x, y in ((a.positions, b.positions), (a.velocities, b.velocities), (a.ids, b.ids),
                     (a.arrays["type"], b.arrays["type"]), (a.arrays["lifetime"], b.arrays["lifetime"])):
            assert x.tobytes() == y.tobytes()
    assert g1.state.counts == g2.state.counts and g1.state.next_id == g2.state.next_id
    assert bool(thinned) == (preset == "auto")


def test_the_candidates_chunk_is_the_cpu_one_on_the_cpu(monkeypatch):
    """The CPU takes CANDIDATE_CHUNK candidates at a time (its host memory), whatever the GPU's chunk is (the GPU
    side: tests/test_gpu.py)."""
    from whitecap.diffuse import generator as G

    monkeypatch.setattr(G, "CANDIDATE_CHUNK_GPU", 500)
    monkeypatch.setattr(G, "CANDIDATE_CHUNK", 3000)
    gen = _generator((30.0, 1.0, 1.0))
    gen.step(_splash(), 0, DT)
    assert gen._chunk() == 3000 and gen._candidates["total"] > 3000
    assert gen._bufs["cand_kind"].shape[0] == 3000


def test_candidates_generated_in_parallel_over_them_equal_those_per_fluid_particle():
    """kernels.generate_candidates (what the generator runs, a chunk at a time) writes the bits the reference
    generate (per fluid particle, tests/diffuse_reference.py) writes, for every candidate a type may keep: the
    classification sees the positions the particles are born at. Not generated: the spray-only slots (only
    spray's limit above them) of a fluid particle whose reach holds its whole generation cylinder
    (kernels.owner_reach), and those generate_candidates finds within the reach of their probe (their lifetime
    SETTLED): none of them can be spray."""
    from whitecap.diffuse import kernels as K
    from whitecap.io.diffuse_types import BUBBLE, FOAM, SPRAY

    gen = _generator((30.0, 1.0, 1.0))
    frame = _splash()
    gen.step(frame, 0, DT)
    b, c, n = gen._bufs, gen.candidates(), len(frame)
    total = c["total"]
    (x, v, life), _ = _all_candidates(gen, frame, 0)
    owner = np.repeat(np.arange(n), c["counts"])
    slot = np.arange(total) - c["offset"][owner]
    lim = b["limit"].to_numpy()[:n][owner]
    spray_only = (slot >= lim[:, FOAM]) & (slot >= lim[:, BUBBLE]) & (slot < lim[:, SPRAY])
    reach = b["owner_reach"].to_numpy()[:n * K.REACH_PROBES].reshape(n, K.REACH_PROBES)
    inside = spray_only & (reach[owner, 0] >= K.REACH_ALL)
    settled = spray_only & ~inside & (b["cand_life"].to_numpy()[:total] == K.SETTLED)  # within their probe's reach
    need = (slot[:, None] < lim).any(1) & ~inside & ~settled
    assert need.sum() > 1000 and inside.sum() > 1000 and settled.sum() > 100
    for ref, got in ((x, "cand_x"), (v, "cand_v"), (life, "cand_life")):
        assert ref[need].tobytes() == b[got].to_numpy()[:total][need].tobytes()


def test_the_candidate_arrays_never_grow_past_a_chunk(monkeypatch):
    """Frames of more and more candidates (the multipliers doubled each frame) grow the candidate arrays
    geometrically, but never past CANDIDATE_CHUNK rows."""
    from whitecap.diffuse import generator as G

    monkeypatch.setattr(G, "CANDIDATE_CHUNK", 3000)
    gen = _generator((30.0, 1.0, 1.0))
    frame = _splash()
    totals = []
    for k in range(4):
        gen.p = replace(gen.p, k_ta=10.0 * 4**k, k_wc=10.0 * 4**k)
        gen.step(frame, k, DT)
        totals.append(gen._candidates["total"])
    assert totals[0] < 3000 < totals[-1]
    for name in ("cand_kind", "cand_owner", "cand_x", "cand_v", "cand_life", "cand_flag", "cand_rank", "cand_pos"):
        assert gen._bufs[name].shape[0] <= 3000, name


def test_a_point_within_an_owners_reach_is_not_spray():
    """kernels.owner_reach's promise, counted by brute force: a point nearer one of a fluid particle's probes (along
    its generation cylinder's axis) than that probe's reach has at least spray_below fluid particles within h, and
    so does any point of the generation cylinder (radius r_V about the axis from x to x + Δt v) of a particle
    whose reach is REACH_ALL."""
    from whitecap.diffuse import kernels as K

    gen = _generator((30.0, 1.0, 1.0))
    frame = _splash()
    gen.step(frame, 0, DT)
    n, x, h, P = len(frame), frame.positions.astype(np.float64), gen.h, K.REACH_PROBES
    v = frame.velocities.astype(np.float64)
    reach = gen._bufs["owner_reach"].to_numpy()[:n * P].reshape(n, P).astype(np.float64)
    probe = gen._bufs["owner_probe"].to_numpy()[:n * P].reshape(n, P, 3).astype(np.float64)
    rng = np.random.default_rng(3)
    some = (reach > 0) & (reach < K.REACH_ALL)
    assert some.sum() > 50 and (reach[:, 0] >= K.REACH_ALL).sum() > 50
    for i in np.flatnonzero(reach[:, 0] > 0):
        if reach[i, 0] >= K.REACH_ALL:  # points of the cylinder
            d = rng.normal(size=(16, 3))
            q = x[i] + rng.uniform(0, 1, (16, 1)) * DT * v[i] + d / np.linalg.norm(d, axis=1)[:, None] * gen.r
        else:  # points just within each probe's reach
            k = reach[i] > 0
            d = rng.normal(size=(k.sum(), 3))
            q = probe[i, k] + d / np.linalg.norm(d, axis=1)[:, None] * reach[i, k, None] * 0.999
        counts = (np.linalg.norm(x[None, :, :] - q[:, None, :], axis=2) < h).sum(1)
        assert (counts >= gen.p.spray_below).all(), (i, reach[i], counts)


def test_potentials_of_the_energetic_particles_alone_give_the_same_births(monkeypatch):
    """With fixed thresholds the potentials are computed only where I_k can be > 0 (E_k at least τ_k,min) and
    for the neighbours whose normals those particles' wave crests read (their lists alone built): the
    diffuse particles, byte for byte, and those particles' potentials are what every particle's give."""
    from whitecap.diffuse import generator as G

    def run(every: bool):
        if every:
            monkeypatch.setattr(G.FoamGenerator, "_energetic_floor", lambda self: None)
        gen = _generator((30.0, 1.0, 1.0))
        ke = 0.5 * (_splash().velocities.astype(np.float64) ** 2).sum(1)
        # about a third of the water energetic enough; the wave crest weighs as much as the trapped air
        gen.p = replace(gen.p, ke_min=float(np.quantile(ke, 0.7)), ke_max=float(ke.max()), wc_max=0.2)
        out, pots, marks = [], [], []
        for k in range(4):  # the splash moving on: some die, some change type, new ones are born
            f = _splash()
            f.positions = f.positions + k * DT * f.velocities
            out.append(gen.step(f, k, DT))
            pots.append({name: a.copy() for name, a in gen._host_potentials().items()})
            if not every:
                marks.append(gen._bufs["energetic"].to_numpy()[:len(f)])
        monkeypatch.undo()
        return out, pots, marks, gen

    part, pots_part, marks, g1 = run(False)
    every, pots_every, _, g2 = run(True)
    assert sum(len(d) for d in part) > 1000
    for a, b in zip(part, every):
        for x, y in ((a.positions, b.positions), (a.velocities, b.velocities), (a.ids, b.ids),
                     (a.arrays["type"], b.arrays["type"]), (a.arrays["lifetime"], b.arrays["lifetime"])):
            assert x.tobytes() == y.tobytes()
    assert g1.state.counts == g2.state.counts
    for p1, p2, m in zip(pots_part, pots_every, marks):
        hot = m == G.K.ENERGETIC
        assert 0.15 < hot.mean() < 0.6 and (m == G.K.CREST_NEIGHBOUR).any()
        assert (p1["wc"][hot] > 0).any()  # crests among them, read from the neighbours' normals
        assert p1["ke"].tobytes() == p2["ke"].tobytes()
        for name in ("ta", "wc", "vo"):
            assert p1[name][hot].tobytes() == p2[name][hot].tobytes()
            assert not p1[name][m == G.K.IDLE].any()  # the others' are 0 (they make nothing)


def test_a_simulations_running_auto_marks_its_history_sample_and_makes_the_same_particles(monkeypatch):
    """Under a simulation's running 'auto' (thresholds from the frames so far, which only rise) the potentials
    are computed from its second moving frame for the energetic particles and for those the history samples
    alone: the thresholds, the scale and the diffuse particles are those of every particle's potentials."""
    from whitecap.diffuse import budget as B, generator as G

    def run(every: bool):
        monkeypatch.setattr(B, "HISTORY_SAMPLE", 128)  # a sample of the splash's 1728 particles, not all of them
        if every:
            monkeypatch.setattr(G.FoamGenerator, "_energetic_floor", lambda self: None)
        gen = _generator((1.0, 1.0, 1.0))
        ke = 0.5 * (_splash().velocities.astype(np.float64) ** 2).sum(1)
        # the multipliers set by the budget, the thresholds kept as set (the running 'auto' still samples)
        names = ("ta_min", "ta_max", "wc_min", "wc_max", "ke_min", "ke_max", "vo_min", "vo_max")
        gen.p = replace(gen.p, auto=True, budget=4.0, ke_min=float(np.quantile(ke, 0.7)), ke_max=float(ke.max()),
                        explicit=frozenset(names))
        gen.last_frame = 4  # the run's end, so the budget's scale is not held down for frames to come
        out, idle = [], []
        for k in range(5):
            f = _splash()
            f.positions = f.positions + k * DT * f.velocities
            out.append(gen.step(f, k, DT))
            idle.append(int((gen._bufs["energetic"].to_numpy()[:len(f)] == G.K.IDLE).sum()))
        monkeypatch.undo()
        return out, idle, gen

    part, idle, g1 = run(False)
    every, idle_every, g2 = run(True)
    assert idle[0] == 0 and min(idle[1:]) > 100 and not any(idle_every)  # marked from the second frame on
    assert sum(len(d) for d in part) > 1000
    for a, b in zip(part, every):
        for x, y in ((a.positions, b.positions), (a.ids, b.ids), (a.arrays["type"], b.arrays["type"])):
            assert x.tobytes() == y.tobytes()
    assert g1.state.tau.tobytes() == g2.state.tau.tobytes() and g1.state.scale == g2.state.scale
    assert g1.state.history.tobytes() == g2.state.history.tobytes()


def test_sample_slots_are_runs_spread_over_the_whole_order():
    from whitecap.diffuse import budget as B

    assert (B.sample_slots(1000, 1000) == np.arange(1000)).all() and (B.sample_slots(10, 64) == np.arange(10)).all()
    n, m = 100_003, 4096
    s = B.sample_slots(n, m)
    runs = s.reshape(-1, B.SAMPLE_RUN)
    assert len(s) == m and len(np.unique(s)) == m and s.min() == 0 and s.max() == n - 1
    assert (np.diff(runs, axis=1) == 1).all()  # each a run of consecutive slots
    gaps = runs[1:, 0] - runs[:-1, 0]
    assert gaps.min() >= B.SAMPLE_RUN and gaps.max() - gaps.min() <= 1  # evenly spread, apart


def test_the_look_ahead_takes_the_thresholds_and_births_from_a_sample_of_each_frame(monkeypatch):
    """'auto' post-processing takes its thresholds from at most LOOK_AHEAD_SAMPLE particles of each sampled
    frame (in runs of the grid's cell order; E_k's from all): where a frame has no more, they are those of
    all its moving particles; where it has more, only the lists of the sample and of the particles that can make
    something are built, the thresholds stay within a few per cent of all particles', and each sampled frame's
    predicted births are exact: what all particles' potentials give under those thresholds."""
    from whitecap.diffuse import budget as B
    from whitecap.sim import grid as grid_mod

    def frames(n):
        out = []
        for k in range(3):
            f = _splash(n)
            f.positions = f.positions + k * DT * f.velocities
            f.velocities += np.random.default_rng(k).normal(0.0, 0.5, f.velocities.shape).astype(np.float32)
            f.velocities[f.positions[:, 2] < np.quantile(f.positions[:, 2], 0.3)] = 0.0  # the bottom at rest
            f.time = k * DT
            out.append(f)
        return out

    def auto():
        gen = _generator((1.0, 1.0, 1.0))
        gen.p = replace(gen.p, auto=True, budget=4.0)
        return gen

    def whole(gen, fr, tau=None):  # every particle's potentials: the thresholds of all, the births under tau
        got = []
        for f in fr:
            gen._potential_arrays(f, len(f))
            got.append((gen._host_potentials(), gen._moving(f)))
        pooled = {k: np.concatenate([g[0][k] for g in got]) for k in ("ta", "wc", "ke", "vo")}
        tau_all = gen._auto_tau(pooled, np.concatenate([g[1] for g in got]))
        tau = tau_all if tau is None else tau
        return tau_all, [B.birth_rate(g[0], tau, (gen.p.k_ta, gen.p.k_wc, gen.p.k_vo), DT) for g in got]

    built = []
    marked = grid_mod.NeighborGrid.build_marked

    def counted(self, n, mark, value):
        built.append(int((mark.to_numpy()[:n] == value).sum()))
        return marked(self, n, mark, value)

    monkeypatch.setattr(grid_mod.NeighborGrid, "build_marked", counted)
    small = frames(12)  # 1,728 particles a frame: all taken
    gen = auto()
    gen.calibrate(small, np.arange(3) * DT, np.full(3, len(small[0]), float), DT)
    tau = whole(auto(), small)[0]
    assert gen.state.tau[[0, 1, 2, 3, 6, 7]].tobytes() == tau[[0, 1, 2, 3, 6, 7]].tobytes()
    assert np.allclose(gen.state.tau[4:6], tau[4:6], rtol=1e-6)  # E_k's, from f64 (the device's are f32)

    big = frames(30)  # 27,000 a frame, 4,096 taken
    monkeypatch.setattr(B, "LOOK_AHEAD_SAMPLE", 4096)
    built.clear()
    gen = auto()
    gen.calibrate(big, np.arange(3) * DT, np.full(3, len(big[0]), float), DT)
    assert sum(built) < 0.3 * 3 * len(big[0])  # of 81,000 (the crests' neighbours' lists included)
    assert min(built[0::2]) > 4096  # the sample's, and the energetic particles'
    tau, rates = whole(auto(), big, gen.state.tau)
    assert np.allclose(gen.state.tau, tau, rtol=0.05) and not np.array_equal(gen.state.tau, tau)
    assert np.allclose(gen.state.tau[4:6], tau[4:6], rtol=1e-6)  # E_k's from every particle
    assert np.allclose(gen._plan[1], rates, rtol=1e-9, atol=0) and min(rates) > 1  # each frame's births


def test_the_birth_rate_summed_on_the_device_is_the_hosts():
    """budget.birth_rate's G, summed on the device by blocks (K.birth_sums) where the potentials are, is the sum
    of the same f32 births NumPy makes on the host, to f32 rounding, for any multipliers: the 'auto' budget reads
    it every frame without reading the frame's potentials back."""
    from whitecap.diffuse import budget as B

    gen = _generator((1.0, 1.0, 1.0))
    f = _splash()
    gen._potential_arrays(f, len(f))
    pots = gen._host_potentials()
    assert len(pots["ta"]) == len(f) > 1000 and (pots["ke"] > 0).mean() > 0.5
    tau = np.array([np.quantile(pots[k][pots[k] > 0], q) for k in ("ta", "wc", "ke", "vo") for q in (0.2, 0.9)])
    for k0 in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (4000.0, 50000.0, 20.0)):
        host = float(B.births(pots, tau, k0, DT).astype(np.float64).sum())
        assert host > 0
        assert gen._birth_rate(tau, k0, DT) == pytest.approx(host, rel=1e-5)
    assert gen._birth_rate(tau * 1e6, (1.0, 1.0, 1.0), DT) == 0.0  # no particle above any threshold
    # The rows of a history sample, read back alone, are those of the whole read-back.
    rows = np.array([0, 7, len(f) - 1])
    np.testing.assert_array_equal(gen._potentials_at(rows), np.stack([pots[k][rows] for k in ("ta", "wc", "ke", "vo")]))


@pytest.mark.parametrize("n", [5, 2 * 256, 100_003])
def test_the_birth_sums_count_each_particle_once_to_the_same_bits_in_either_layout(n):
    """K.birth_sums counts each f32 term in units of 1/birth_unit as a 64-bit integer, summed without rounding: the
    CPU's layout (runs of consecutive particles a thread) and a GPU's (interleaved) give the same bits. Where every φ
    is exactly 0 or 1 (thresholds a power of two apart), each term is Δt or 0, so each sum is a count of particles
    times Δt's units, exactly: no particle is left out or counted twice. With potentials of every size, the sums are
    math.fsum's of the f32 terms NumPy makes (the kernel's own f32 arithmetic may differ in the last bit)."""
    import math

    import taichi as ti

    from whitecap.diffuse import kernels as K
    from whitecap.diffuse.generator import _nd

    _generator((1.0, 1.0, 1.0))  # (Taichi initialised as the other tests have it)
    rng = np.random.default_rng(n)
    dt = np.float32(DT)
    unit = K.birth_unit(n, float(DT))
    assert n * float(DT) * unit < 2.0**K.BIRTH_BITS <= 2 * n * float(DT) * unit  # the largest power of two that fits
    total = ti.ndarray(ti.i64, 3)

    def sums(pots, tau) -> list[int]:
        arrays = [_nd(a.astype(np.float32), ti.f32) for a in pots] + [_nd(np.asarray(tau, np.float32), ti.f32)]
        got = [[int(x) for x in K.birth_sums(n, *arrays, dt, unit, interleaved, total)]
               for interleaved in (False, True)]  # the CPU's layout, a GPU's
        assert got[0] == got[1]
        return got[0]

    on = [rng.random(n) < 0.6 for _ in range(4)]  # ta, wc, ke, vo: above τmax (φ = 1) or 0 (φ = 0)
    on[2][:2] = True
    pots = [np.where(m, np.float32(100.0), np.float32(0.0)) for m in on]
    pots[2][0] = np.inf  # E_k infinite: φ = 1 as well
    tau01 = [1.0, 3.0, 1.0, 3.0, 1.0, 3.0, 1.0, 3.0]
    per = int(np.floor(float(dt) * unit + 0.5))
    assert sums(pots, tau01) == [int(np.count_nonzero(on[2] & on[c])) * per for c in (0, 1, 3)]

    pots = [rng.exponential(s, n).astype(np.float32) * (rng.random(n) < 0.7) for s in (2.0, 1.0, 30.0, 8.0)]
    pots[2][:2] = np.float32(1e-30), np.float32(3e4)  # a tiny E_k, a large one
    tau = np.array([0.5, 4.0, 0.2, 2.0, 5.0, 60.0, 1.0, 12.0], np.float32)

    def phi(i, lo, hi):  # kernels.clamp_phi in f32
        return (np.minimum(i, hi) - np.minimum(i, lo)) / (hi - lo)

    w = phi(pots[2], tau[4], tau[5]) * dt
    terms = [w * phi(pots[0], tau[0], tau[1]), w * phi(pots[1], tau[2], tau[3]), w * phi(pots[3], tau[6], tau[7])]
    for s, t in zip(sums(pots, tau), terms):
        exact = math.fsum(t.astype(np.float64))
        assert exact > 0 and s / unit == pytest.approx(exact, rel=1e-6)


def test_speed_squared_is_einsums_bits_on_a_frames_records():
    """generator.speed_squared, component by component, gives the bits of np.einsum("ij,ij->i", v, v) (the
    'moving' flags of the running 'auto' and the files it shapes stay the same), on a frame's velocities as they
    come: a strided view of its records, every 15th row as the running 'auto' samples them, and a contiguous copy."""
    from whitecap.diffuse.generator import speed_squared

    rng = np.random.default_rng(3)
    n = 200_000
    fields = ("x", "y", "z", "vx", "vy", "vz", "density")
    records = np.zeros(n, np.dtype({"names": [*fields, "id"], "formats": ["<f4"] * 7 + ["<u4"]}))
    scale = 10.0 ** rng.uniform(-3, 2, n)
    for k in fields:
        records[k] = rng.standard_normal(n) * (scale if k.startswith("v") else 1.0)
    strided = io.ParticleFrame.from_records(records).velocities
    assert strided is not None and not strided.flags.c_contiguous
    for a in (strided, strided[::15], np.ascontiguousarray(strided)):
        got, ref = speed_squared(a), np.einsum("ij,ij->i", a, a)
        assert got.dtype == np.float32 and len(got) == len(a)
        assert np.array_equal(got.view(np.uint32), ref.view(np.uint32))
