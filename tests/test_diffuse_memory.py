"""Memory of the foam stage that does not grow (issue 31, goal 2): once the run's largest frame has
been seen, FoamGenerator.step makes no Taichi array, and the process's resident memory stays flat
over many frames. (Taichi does not give an array's memory back when the array goes, so an array
made per frame is a leak of its size every frame, on the CPU and on CUDA.)"""

from __future__ import annotations

import gc
import mmap
import os
from dataclasses import replace

import numpy as np
import pytest

from whitecap import io
from whitecap.diffuse.params import resolve

R = 0.01
# glibc's malloc in the measuring process maps every block of this size or more on its own and gives
# it back when freed (a fixed threshold: the default one rises to the largest block freed, after which
# a frame's freed arrays stay in the heap as free space that absorbs the control's leak unseen).
MMAP_THRESHOLD = 65536
DT = 1.0 / 120.0
CYCLE = 10  # the splash repeats its fluid frames with this period


def _splash(i: int, n: int = 14) -> io.ParticleFrame:
    """Frame ``i`` of a small splashing sequence: a jittered block of water whose sheared, rising
    velocity field turns with the frame, so that particles are born, move, change type and die."""
    g = np.arange(n) * 2 * R
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3).astype(np.float32) + 0.3
    x += np.random.default_rng(i).uniform(-0.05 * R, 0.05 * R, x.shape).astype(np.float32)
    z = (x[:, 2] - x[:, 2].min()) / (2 * R * (n - 1))
    ph = 0.4 * i
    v = np.stack([1.5 * z * np.cos(ph), 0.3 * np.sin(9 * x[:, 0] + ph), 0.8 * z * z + 0.2], 1).astype(np.float32) * 3
    return io.ParticleFrame(positions=x, velocities=v, ids=np.arange(len(x), dtype=np.uint32), time=i * DT)


def _generator(preset: str, frames: list):
    from whitecap.diffuse.generator import FoamGenerator

    p = resolve(preset=preset)
    lives = dict(lifetime_min=0.05, lifetime_max=0.2, spray_lifetime=(0.05, 0.2), bubble_lifetime=(0.05, 0.2))
    if p.model == "foamgenerator":
        p = replace(p, **lives)
    else:  # low thresholds: thousands of particles alive, a few hundred born and as many gone each frame
        p = replace(p, ta_min=0.0, ta_max=2.0, wc_min=0.0, wc_max=1.0, ke_min=0.0, ke_max=4.0, k_ta=50.0, k_wc=50.0,
                    **lives)
    gen = FoamGenerator(p, R, ([-1, -1, -1], [2, 2, 2]), (0, 0, -9.81), seed=11)
    if p.model == "foamgenerator":  # its limits from the sequence's maxima (pass 1), lowered to make some
        from whitecap.diffuse import splishsplash as SP

        gen.state.tau = SP.limits_from_maxima(np.array([SP.frame_maxima(gen, f) for f in frames]), R) * np.float32(0.3)
    return gen


class _ArrayCounter:
    """Counts the Taichi arrays made (every ndarray, scalar or vector, goes through Ndarray.__init__)."""

    def __init__(self, monkeypatch):
        from taichi.lang import _ndarray

        self.made = 0
        init = _ndarray.Ndarray.__init__

        def counted(arr, *a, **kw):
            self.made += 1
            init(arr, *a, **kw)

        monkeypatch.setattr(_ndarray.Ndarray, "__init__", counted)


@pytest.mark.parametrize("preset", ["ihmsen2012", "splishsplash"])
def test_no_taichi_array_is_made_per_frame_once_the_largest_frame_was_seen(monkeypatch, preset):
    frames = [_splash(i) for i in range(CYCLE)]
    gen = _generator(preset, frames)
    for i in range(3 * CYCLE):  # warm-up: every fluid frame seen, the births of the largest bursts
        gen.step(frames[i % CYCLE], i, DT)
    counter = _ArrayCounter(monkeypatch)
    alive = []
    for i in range(3 * CYCLE, 9 * CYCLE):
        alive.append(len(gen.step(frames[i % CYCLE], i, DT)))
    assert min(alive) > 1000 and max(alive) < gen.capacity  # a live foam stage, not a saturated or empty one
    assert counter.made == 0, f"{counter.made} Taichi arrays made in {6 * CYCLE} frames"
    # the counter sees an array made per frame (the way the generator made its arrays before)
    from whitecap.diffuse.generator import _nd

    _nd(frames[0].positions, None, vec=True)
    assert counter.made == 1


def _check_frames_reused(way: str) -> None:
    """test_frames_are_read_back_into_host_arrays_used_again_and_a_held_frame_is_never_written_over, in a process of
    its own (see there)."""
    from whitecap.sim import records

    if way == "arrays":
        records.WORDS_MAX = 0
    frames = [_splash(i) for i in range(CYCLE)]
    gen = _generator("ihmsen2012", frames)
    pool = gen._records.pool if way == "records" else gen._frames
    for i in range(4 * CYCLE):  # warm-up: the largest frames seen (blocks grow with the count until then)
        gen.step(frames[i % CYCLE], i, DT)
    made = pool.made
    assert made > 0, "the frames did not come back through this pool"
    held = kept = None
    made_at = []  # (frame, its count, the kept blocks' rows and which were free after it): what a failure says
    for i in range(4 * CYCLE, 7 * CYCLE):
        before = pool.made
        d = gen.step(frames[i % CYCLE], i, DT)
        if pool.made != before:
            made_at.append((i, len(d), [(b.rows, pool._is_free(b)) for b in pool._blocks]))
        if i == 45:
            held = d
            kept = {k: a.copy() for k, a in [("x", d.positions), ("v", d.velocities), ("ids", d.ids),
                                             *d.arrays.items()]}
        del d
    assert held is not None and kept is not None and len(held) > 1000
    assert (held.records is not None) == (way == "records")
    assert pool.made - made <= 1, f"{pool.made - made} blocks made in {3 * CYCLE} frames: {made_at}"
    got = {"x": held.positions, "v": held.velocities, "ids": held.ids, **held.arrays}
    for k, a in kept.items():
        assert np.array_equal(got[k], a), f"frame 45's {k} changed after it was handed out"
    last = gen.step(frames[0], 7 * CYCLE, DT)
    assert not np.shares_memory(last.positions, held.positions)


@pytest.mark.parametrize("way", ["records", "arrays"])
def test_frames_are_read_back_into_host_arrays_used_again_and_a_held_frame_is_never_written_over(way):
    """The diffuse frames step hands out are views of a few host blocks (io.array_pool), not new pages every
    frame: once warm, 30 frames make one block, for the frame the caller holds (here frame 45, as the writer's
    queue would), which keeps its values while 25 more frames are made; the others use the blocks again. Both
    ways a frame comes back: as the file's records (FoamGenerator._download), and array by array where a frame
    holds more records than a Taichi array (_download_arrays; here every frame).

    In a process of its own, as a run has: in the suite's process, after some hundreds of tests, an early small
    block of this test was sometimes held by something outside whitecap for the rest of the test (2 runs of the
    whole suite in 6 on 2026-11-28, the records way; never alone, never after the same tests run by name), and a
    block was made every other frame. Not found; a run's own process never showed it."""
    import subprocess
    import sys

    from .conftest import ROOT

    script = f"from tests.test_diffuse_memory import _check_frames_reused; _check_frames_reused({way!r}); print('ok')"
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-3000:]


def test_a_frame_comes_back_as_the_files_records_and_is_written_as_it_is(tmp_path, monkeypatch):
    """A diffuse frame comes back as the vertex records of its PLY (made by sim.records' kernel, into one host
    block): its arrays are views of them, the writer writes them without packing, and the files are the bytes of
    the frames that come back array by array and are packed by the writer (sim.records.WORDS_MAX: above it, every
    frame), frame for frame, with the state the same too."""
    from whitecap.diffuse import generator as G
    from whitecap.io import ply
    from whitecap.sim import records

    frames = [_splash(i) for i in range(CYCLE)]
    got: dict[str, list] = {}
    for way in ("arrays", "records"):
        with monkeypatch.context() as m:
            if way == "arrays":
                m.setattr(records, "WORDS_MAX", 0)
            else:
                def no_packing(*a):
                    raise AssertionError("the writer packed a frame that came back as its records")

                m.setattr(ply, "_pack", no_packing)
            gen = _generator("ihmsen2012", frames)
            files = []
            for i in range(2 * CYCLE):
                d = gen.step(frames[i % CYCLE], i, DT)
                assert (d.records is not None) == (way == "records")
                if d.records is not None:
                    assert np.shares_memory(d.positions, d.records) and np.shares_memory(d.ids, d.records)
                    assert d.records.dtype == G.RECORD == ply.record_dtype(d)
                io.write(tmp_path / f"{way}_{i}.ply", d)
                files.append((tmp_path / f"{way}_{i}.ply").read_bytes())
            got[way] = [files, {k: np.array(a) for k, a in gen.state.to_arrays().items()}]
    assert max(len(f) for f in got["records"][0]) > 1000 * G.RECORD.itemsize  # frames of thousands of particles
    assert got["records"][0] == got["arrays"][0]
    for k, a in got["arrays"][1].items():
        assert np.array_equal(got["records"][1][k], a), k


def _rss() -> int:
    """Resident bytes of this process, after a collection."""
    gc.collect()
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _measure_resident_memory(leaking: bool = False) -> dict:
    """The measurement of the test below, in this process (which must be fresh: a heap that earlier
    work left with free space absorbs a small leak, so the control would not see it): the growth of
    the resident memory from frame 20 to frame 60, with ``leaking`` keeping half of each frame's data
    (the control). Control and measurement run the same frames from a fresh process each, so the
    memory that comes and goes with the live diffuse particles is the same in both."""
    frames = [_splash(i) for i in range(CYCLE)]
    gen = _generator("ihmsen2012", frames)
    sizes = []
    leak: list = []

    def run(first: int, last: int, keep: bool):
        for i in range(first, last):
            d = gen.step(frames[i % CYCLE], i, DT)
            f = frames[i % CYCLE]
            # the frame's data: the fluid frame in, the diffuse frame out (with type, lifetime, radius)
            sizes.append(f.positions.nbytes + f.velocities.nbytes + f.ids.nbytes + len(d) * (12 + 12 + 4 + 1 + 4 + 4))
            if keep:  # pages of its own, every one touched: resident whatever the allocator keeps free
                block = mmap.mmap(-1, sizes[-1] // 2)
                block.write(b"\1" * (sizes[-1] // 2))
                leak.append(block)

    run(0, 20, False)
    before = _rss()
    run(20, 60, leaking)
    return {"grown": _rss() - before, "per_frame": int(np.mean(sizes[20:]))}


def test_resident_memory_does_not_grow_over_many_frames():
    """60 frames of the splash: between frame 20 and frame 60 the resident memory grows by less than
    ten frames' data (fluid frame and live diffuse particles). Before, the foam stage made its arrays
    every frame and grew by about one frame's data a frame. Control: the same frames keeping half a
    frame's data each (a leak of half the old one) grow past the bound. Each measured in a fresh process
    whose malloc maps large blocks on their own (MMAP_THRESHOLD), so freed frames give their memory back
    and the two see the same coming and going of the live particles' arrays."""
    import json
    import subprocess
    import sys

    from .conftest import ROOT

    def measure(leaking: bool) -> dict:
        out = subprocess.run([sys.executable, "-c", "import json; from tests.test_diffuse_memory import "
                              f"_measure_resident_memory as m; print(json.dumps(m({leaking})))"],
                             cwd=ROOT, capture_output=True, text=True, check=True,
                             env={**os.environ, "WHITECAP_PROGRESS": "0",
                                  "MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD)})
        return json.loads(out.stdout.strip().splitlines()[-1])

    r = measure(False)
    per_frame, grown = r["per_frame"], r["grown"]
    bound = 10 * per_frame
    assert per_frame > 100_000  # enough data a frame for a leak to stand out of the noise
    assert grown < bound, (f"resident memory grew {grown:,} bytes over 40 frames "
                           f"(bound {bound:,}; {per_frame:,} a frame)")
    control = measure(True)
    assert control["grown"] > bound, f"a leak of {per_frame // 2:,} bytes a frame grew {control['grown']:,} bytes"


def test_readers_of_one_record_layout_share_one_kernel():
    """Every RecordReader of a layout (a run's foam stage, the next run's, a benchmark's timed run after its warm-up)
    takes the kernel made for the first: a kernel made anew is compiled anew (210 ms for the diffuse record on 2
    cores, once for each FoamGenerator and PBFSolver made). Another layout has its own."""
    from whitecap.diffuse.generator import RECORD, RECORD_SOURCES
    from whitecap.sim.pbf import FLUID_RECORD, FLUID_RECORD_SOURCES
    from whitecap.sim.records import RecordReader, record_packer

    a, b = RecordReader(RECORD, RECORD_SOURCES), RecordReader(np.dtype(RECORD.descr), dict(RECORD_SOURCES))
    assert a.pack is b.pack
    fluid = RecordReader(FLUID_RECORD, FLUID_RECORD_SOURCES)
    assert fluid.pack is not a.pack and (fluid.per, fluid.words) == (1, 8)
    assert record_packer(FLUID_RECORD, dict(reversed(list(FLUID_RECORD_SOURCES.items()))))[0] is fluid.pack


@pytest.mark.parametrize("layout", ["diffuse", "no type"])
def test_the_record_packer_makes_the_writers_bytes_for_any_count(layout):
    """sim.records.record_packer: records made a whole number of 32-bit words a thread (4 records of 37 bytes, or 1
    of 36 without the type) are the bytes io.ply packs from the arrays, for counts that end inside a thread's
    records, none of the rows past the count read; a field it has no source for is refused."""
    import taichi as ti

    from whitecap.diffuse.generator import RECORD_SOURCES
    from whitecap.io import ParticleFrame
    from whitecap.io.ply import _groups, _pack, record_dtype
    from whitecap.sim import runtime
    from whitecap.sim.records import record_packer

    runtime.init("cpu")
    rng = np.random.default_rng(4)
    m = 11
    x, v = rng.normal(0, 1, (m, 3)).astype(np.float32), rng.normal(0, 1, (m, 3)).astype(np.float32)
    life, ids, kind = rng.random(m).astype(np.float32), rng.integers(0, 2**32, m, np.uint32), rng.integers(0, 3, m)
    radius = np.float32(0.0123)
    arrays = {"type": kind.astype(np.uint8), "lifetime": life, "radius": np.full(m, radius)}
    if layout == "no type":
        del arrays["type"]
    dtype = record_dtype(ParticleFrame(x, v, ids, arrays=arrays))
    pack, per, words = record_packer(dtype, RECORD_SOURCES)
    assert (per, words) == ((4, 37) if layout == "diffuse" else (1, 9))
    live = [ti.Vector.ndarray(3, ti.f32, m), ti.Vector.ndarray(3, ti.f32, m), ti.ndarray(ti.f32, m),
            ti.ndarray(ti.u32, m), ti.ndarray(ti.i32, m)]
    for nd, a in zip(live, (x, v, life, ids, kind.astype(np.int32))):
        nd.from_numpy(a)
    for n in range(0, 10):
        out = np.full((-(-n // per) + 1) * words, 0xDEADBEEF, np.uint32)  # a thread's worth more than needed
        pack(n, *live, int(radius.view(np.uint32)), out)
        frame = ParticleFrame(x[:n], v[:n], ids[:n], arrays={k: a[:n] for k, a in arrays.items()})
        want = np.empty(n, dtype)
        _pack(want, _groups(frame), 0, n)
        got = out.view(np.uint8)
        assert got[:n * dtype.itemsize].tobytes() == want.tobytes(), n
        assert not got[n * dtype.itemsize:-(-n // per) * words * 4].any(), n  # the last thread's rows past n: zero
        assert (out[-(-n // per) * words:] == 0xDEADBEEF).all(), n  # nothing written past its words
    with pytest.raises(ValueError, match="not one it can make"):
        record_packer(np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("density", "<f4")]), RECORD_SOURCES)


def test_an_inflow_makes_the_arrays_sized_by_the_fluid_again_only_as_it_grows_by_a_quarter(monkeypatch):
    """A fluid that grows every frame (an inflow: emitters, a foreign sequence's inlet) under 'auto', whose capacity
    follows the fluid's count frame by frame: what is sized by that count (the live particles' arrays at the
    capacity, the fluid grid, the kept buffers) is made again in a few frames as the fluid grows by a third, not in
    every frame (Taichi keeps the memory of every array that goes, so an array made per frame is a leak of its size
    every frame)."""
    frames = [_splash(i, n=16) for i in range(CYCLE)]
    gen = _generator("ihmsen2012", frames)
    gen.p = replace(gen.p, auto=True, budget=2.0)  # the capacity from the budget: it rises with the fluid
    gen.looked_ahead, gen.state.tau = True, gen.base_thresholds()

    def fluid(i: int, share: float) -> io.ParticleFrame:
        f = frames[i % CYCLE]
        m = int(share * len(f))
        return io.ParticleFrame(positions=f.positions[:m], velocities=f.velocities[:m], ids=f.ids[:m], time=f.time)

    for i in range(2 * CYCLE):  # warm-up at the first count: the splash's births at their largest
        gen.step(fluid(i, 0.7), i, DT)
    counter = _ArrayCounter(monkeypatch)
    made, capacity = [], []
    for k in range(25):
        before = counter.made
        gen.step(fluid(2 * CYCLE + k, 0.7 + 0.012 * (k + 1)), 2 * CYCLE + k, DT)
        made.append(counter.made - before)
        capacity.append(gen.capacity)
    assert all(b > a for a, b in zip(capacity, capacity[1:])), "the capacity did not follow the fluid"
    assert capacity[-1] > 1.3 * capacity[0] and len(gen.step(fluid(0, 1.0), 99, DT)) > 1000
    assert sum(1 for m in made if m) <= 4, f"arrays made in these frames of 25: {made}"
