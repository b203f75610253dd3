"""CUDA path: the same dam break on CUDA as on the CPU. Skips where no GPU is present."""

from __future__ import annotations

import subprocess
import sys

import pytest

from whitecap.sim.runtime import cuda_available

pytestmark = pytest.mark.skipif(not cuda_available(), reason="no CUDA device")

SCRIPT = """
import sys, numpy as np
from whitecap.config import scene_from_dict
from whitecap.sim.driver import build_solver
from tests.conftest import tiny_scene_dict
s = build_solver(scene_from_dict(tiny_scene_dict()), arch=sys.argv[1])
for f in range(1, 6):
    s.advance_frame(f)
np.save(sys.argv[2], s.arrays()["positions"][np.argsort(s.state.ids.to_numpy())])
"""


def test_cuda_matches_cpu(tmp_path):
    from pathlib import Path

    import numpy as np

    root = Path(__file__).parents[1]
    for arch in ("cpu", "cuda"):
        subprocess.run([sys.executable, "-c", SCRIPT, arch, str(tmp_path / f"{arch}.npy")], cwd=root, check=True)
    a, b = np.load(tmp_path / "cpu.npy"), np.load(tmp_path / "cuda.npy")
    # Float summation order differs between backends; trajectories agree closely over 5 frames.
    assert np.abs(a - b).max() < 0.01


def test_cuda_step_runs_as_compute_graphs(tmp_path):
    """The step's phases build and run as Taichi compute graphs on CUDA too (sim/launch.py), with the
    same result as launching kernel by kernel there."""
    from pathlib import Path

    import numpy as np

    script = """
import sys, numpy as np
from whitecap.config import scene_from_dict
from whitecap.sim.driver import build_solver
from tests.conftest import tiny_scene_dict
out = []
for use_graph in (True, False):
    s = build_solver(scene_from_dict(tiny_scene_dict()), arch="cuda")
    s.use_graph = use_graph
    for f in range(1, 4):
        s.advance_frame(f)
    assert s.use_graph is use_graph, "compute graphs fell back to direct launches on CUDA"
    out.append(s.state.x.to_numpy())
np.save(sys.argv[1], np.stack(out))
"""
    root = Path(__file__).parents[1]
    subprocess.run([sys.executable, "-c", script, str(tmp_path / "x.npy")], cwd=root, check=True)
    x = np.load(tmp_path / "x.npy")
    assert np.abs(x[0] - x[1]).max() < 1e-4  # same launches; CUDA's atomics may reorder float sums


def test_foam_post_processing_on_cuda_matches_the_cpu_in_counts(tiny_run, tmp_path):
    """`whitecap foam RUN --arch cuda`: the diffuse counts of each frame come within a few per cent of
    the CPU's (the generator's random draws are the same; float sums differ between backends)."""
    import shutil
    from pathlib import Path

    import numpy as np

    root = Path(__file__).parents[1]
    rows = {}
    for arch in ("cpu", "cuda"):
        run = tmp_path / arch
        shutil.copytree(tiny_run, run)
        subprocess.run([sys.executable, "-m", "whitecap.cli", "foam", str(run), "--arch", arch], cwd=root, check=True)
        rows[arch] = np.loadtxt(run / "diffuse" / "counts.csv", delimiter=",", skiprows=1)[:, 2:].sum(1)
    assert rows["cpu"].sum() > 0
    assert np.allclose(rows["cuda"], rows["cpu"], rtol=0.1, atol=5)


IDLE_SCRIPT = """
import threading, time
import taichi as ti
from whitecap.sim import runtime
runtime.init("cuda")
a = ti.ndarray(ti.f32, 1 << 22)

@ti.kernel
def churn(a: ti.types.ndarray(), rounds: ti.i32):
    for i in range(a.shape[0]):
        s = 0.0
        for k in range(rounds):
            s = ti.sin(s + i * 1e-6 + k)
        a[i] = s

churn(a, 1)
runtime.device_idle()
ticks = [0]
stop = threading.Event()
def count():
    while not stop.is_set():
        ticks[0] += 1
t = threading.Thread(target=count); t.start(); time.sleep(0.05)
t0 = time.perf_counter(); churn(a, 400000); c0 = ticks[0]
waited = runtime.device_idle(); c1 = ticks[0]; wait = time.perf_counter() - t0
stop.set(); t.join()
print(waited, wait, c1 - c0)
"""


def test_device_idle_waits_for_the_gpu_and_lets_other_threads_run(tmp_path):
    """runtime.device_idle on CUDA: it returns once the launched kernel is done, and another Python thread
    (the background writer) goes on running meanwhile, which Taichi's own waits do not allow."""
    from pathlib import Path

    root = Path(__file__).parents[1]
    script = tmp_path / "idle.py"  # a file, not -c: Taichi reads a kernel's source
    script.write_text(IDLE_SCRIPT)
    out = subprocess.run([sys.executable, str(script)], cwd=root, check=True, capture_output=True,
                         text=True).stdout.split()
    waited, wait, ticks = out[-3] == "True", float(out[-2]), int(out[-1])
    assert waited and wait > 0.02, out  # the kernel took a while, and device_idle waited for it
    assert ticks > 1000, out  # the counting thread ran during the wait


ROWS_SCRIPT = """
import os, sys
sys.path.insert(0, os.getcwd())  # tests.conftest, from the repository's root (a script's own folder is the path)
import numpy as np, taichi as ti
from whitecap.config import Foam, scene_from_dict
from whitecap.diffuse import resolve
from whitecap.diffuse.generator import FoamGenerator
from whitecap.sim import runtime
from whitecap.sim.driver import build_solver
from tests.conftest import tiny_scene_dict
s = build_solver(scene_from_dict(tiny_scene_dict()), arch="cuda")
for f in range(1, 4):
    s.advance_frame(f)
n = s.n
a = s.arrays()
assert np.array_equal(a["positions"], s.state.x.to_numpy()[:n])
assert np.array_equal(a["velocities"], s.state.v.to_numpy()[:n])
assert np.array_equal(a["ids"], s.state.ids.to_numpy()[:n].astype(np.uint32))
assert np.array_equal(a["density"], s.state.rho.to_numpy()[:n])
try:
    runtime.rows_to_host((np.empty((s.state.x.shape[0] + 1, 3), np.float32), s.state.x))
    raise SystemExit("rows_to_host read past the ndarray")
except ValueError:
    pass
up = ti.Vector.ndarray(3, ti.f32, n + 5)
assert runtime.rows_to_device((up, a["positions"]))
assert np.array_equal(up.to_numpy()[:n], a["positions"])
# the diffuse particles of a frame: the same arrays through the driver's copies and through the kernel's
box = ([0, 0, 0], [0.6, 0.2, 0.4])
gen = FoamGenerator(resolve(Foam(preset="auto")), 0.01, box, (0, 0, -9.81), seed=1, arch="cuda")
from whitecap.io.frame import ParticleFrame
for f in range(4, 10):
    s.advance_frame(f)
    a = s.arrays()
    d = gen.step(ParticleFrame(a["positions"], a["velocities"], a["ids"], a["density"]), f, 1 / 30)
assert len(d) > 0, "no diffuse particle to compare"
direct = gen._download()
runtime.rows_to_host = lambda *pairs: False
kernel = gen._download()
for k in ("positions", "velocities", "ids"):
    assert np.array_equal(getattr(direct, k), getattr(kernel, k)), k
for k in ("type", "lifetime", "radius"):
    assert direct.arrays[k].dtype == kernel.arrays[k].dtype and np.array_equal(direct.arrays[k], kernel.arrays[k]), k
print("ROWS OK", n, len(d))
"""


def test_rows_read_back_by_the_driver_equal_the_kernels(tmp_path):
    """runtime.rows_to_host on CUDA (one cuMemcpyDtoH an array, the GIL let go): the solver's frame and the diffuse
    particles read back equal what Taichi's own reads give, row for row, and a host array longer than the ndarray
    is refused; rows_to_device puts a frame's rows up as they are."""
    from pathlib import Path

    root = Path(__file__).parents[1]
    script = tmp_path / "rows.py"
    script.write_text(ROWS_SCRIPT)
    run = subprocess.run([sys.executable, str(script)], cwd=root, capture_output=True, text=True)
    assert run.returncode == 0 and "ROWS OK" in run.stdout, run.stderr[-3000:]


LATER_SCRIPT = """
import os, sys
sys.path.insert(0, os.getcwd())
import numpy as np
from whitecap.config import Foam, scene_from_dict
from whitecap.diffuse import resolve
from whitecap.diffuse.generator import FoamGenerator
from whitecap.io.frame import ParticleFrame
from whitecap.sim.driver import build_solver
from tests.conftest import tiny_scene_dict
s = build_solver(scene_from_dict(tiny_scene_dict()), arch="cuda")
box = ([0, 0, 0], [0.6, 0.2, 0.4])
now, later = (FoamGenerator(resolve(Foam(preset="auto")), 0.01, box, (0, 0, -9.81), seed=1, arch="cuda")
              for _ in range(2))
frames = []
for f in range(1, 12):
    s.advance_frame(f)
    a = s.arrays()
    fr = ParticleFrame(a["positions"], a["velocities"], a["ids"], a["density"])
    d0 = now.step(fr, f, 1 / 30)
    d1 = later.step(fr, f, 1 / 30, defer=True)  # its next step waits for this read-back before it changes the rows
    assert (later.pending is not None) == (len(d1) > 0), (f, len(d1))
    frames.append((d0, d1, later.pending))
assert sum(len(d) for d, _, _ in frames) > 0, "no diffuse particle to compare"
for d0, d1, pending in frames:  # each frame whole once its own read-back is done, equal to the one read at once
    if pending is not None:
        assert pending.result() is True
    for k in ("positions", "velocities", "ids"):
        assert np.array_equal(getattr(d0, k), getattr(d1, k)), k
    for k in ("type", "lifetime", "radius"):
        assert d0.arrays[k].dtype == d1.arrays[k].dtype and np.array_equal(d0.arrays[k], d1.arrays[k]), k
print("LATER OK", sum(len(d) for d, _, _ in frames))
"""


def test_a_deferred_read_back_gives_the_frames_read_at_once(tmp_path):
    """FoamGenerator.step(defer=True) on CUDA: each frame's diffuse particles come back on the read-back thread
    (runtime.rows_to_host_later, its own non-blocking stream) while the next frames are computed; every frame,
    once its copy is done, equals the one a generator of the same seed read back at once."""
    from pathlib import Path

    script = tmp_path / "later.py"
    script.write_text(LATER_SCRIPT)
    run = subprocess.run([sys.executable, str(script)], cwd=Path(__file__).parents[1], capture_output=True, text=True)
    assert run.returncode == 0 and "LATER OK" in run.stdout, run.stderr[-3000:]


FREE_ON_A_THREAD = """
import gc, sys, threading
import taichi as ti
from whitecap.sim.runtime import init
init("cuda")
if sys.argv[1] == "without":
    gc.callbacks.clear()
gc.disable()  # collections only where this script asks for them
a = ti.ndarray(ti.f32, 1 << 20)
box = [a]
box.append(box)  # an ndarray held in a cycle: freed only by the cyclic collector
del a, box
t = threading.Thread(target=gc.collect)  # as the background writer's thread did when a collection fell due
t.start()
t.join()
b = ti.ndarray(ti.f32, 1 << 20)
b.fill(2.0)
print("sum", float(b.to_numpy().sum()))
"""


def test_an_ndarray_collected_on_another_thread_is_freed_without_aborting():
    """simulate at 1 M particles on an H100 was aborted (CUDA_ERROR_INVALID_CONTEXT in cuMemFreeAsync, SIGABRT)
    when Python's cyclic collector ran on the writer's thread and freed a Taichi ndarray there. Taichi's context
    is now made current on such a thread before a collection (runtime._free_on_any_thread); without that
    (argument "without") the same script aborted on an H100."""
    from pathlib import Path

    r = subprocess.run([sys.executable, "-c", FREE_ON_A_THREAD, "with"], cwd=Path(__file__).parents[1],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"sum {float(1 << 21)}" in r.stdout


def test_foam_on_cuda_takes_its_candidates_in_the_gpu_chunk_with_the_same_particles(tmp_path):
    """On CUDA a frame's candidates go CANDIDATE_CHUNK_GPU at a time; in chunks of 700 there (the splash makes
    thousands) the frames are the same, byte for byte."""
    from pathlib import Path

    script = """
import sys, numpy as np
from whitecap.sim import runtime
runtime.init("cuda")
from whitecap.diffuse import generator as G
from tests.test_diffuse_generate import _generator, _splash, DT
def run():
    gen = _generator((30.0, 1.0, 1.0))
    out = []
    for k in range(3):
        f = _splash()
        f.positions = f.positions + k * DT * f.velocities
        d = gen.step(f, k, DT)
        # (the frame's arrays may be strided views of the records made on the device: bytes, not views)
        out.append(b"".join(np.ascontiguousarray(a).tobytes() for a in
                            (d.positions, d.velocities, d.ids, d.arrays["type"])))
    return gen, out
gen, whole = run()
assert gen._chunk() == G.CANDIDATE_CHUNK_GPU and gen._candidates["total"] > 3 * 700
G.CANDIDATE_CHUNK_GPU = 700
gen, chunked = run()
assert gen._bufs["cand_kind"].shape[0] == 700
assert whole == chunked and sum(len(a) for a in whole) > 1000
"""
    subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).parents[1], check=True)


def test_the_prefix_sum_on_cuda_is_numpys_exclusive_cumsum(tmp_path):
    """sim.scan's GPU layout (many short blocks, their sums scanned in groups) run on CUDA, across groups."""
    script = """
import numpy as np, taichi as ti
from whitecap.sim import runtime
from whitecap.sim.scan import SCAN_SUMS, exclusive_scan, scan_block
runtime.init("cuda")
for n in (1, 17, 8193, 3_000_000, 33_554_432):
    a = np.random.default_rng(n).integers(0, 3, n).astype(np.int32)
    src, out, sums = ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, SCAN_SUMS)
    src.from_numpy(a)
    assert scan_block(n) == scan_block(n, gpu=True)
    assert exclusive_scan(n, src, sums, out) == int(a.sum()), n
    assert np.array_equal(out.to_numpy(), np.concatenate([[0], np.cumsum(a)[:-1]])), n
print("ok")
"""
    from pathlib import Path

    root = Path(__file__).parents[1]
    done = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-2000:]



def test_the_birth_sums_on_cuda_count_each_particle_once_in_either_layout(tmp_path):
    """K.birth_sums on CUDA, interleaved (a GPU's layout, as the generator launches it there) and in runs: the same
    bits, and where every φ is 0 or 1, each sum is the count of particles times Δt's units (none left out or counted
    twice, many threads' sums added atomically)."""
    script = """
import numpy as np, taichi as ti
from whitecap.sim import runtime
runtime.init("cuda")
from whitecap.diffuse import kernels as K
from whitecap.diffuse.generator import _nd
for n in (5, 3_000_001):
    rng = np.random.default_rng(n)
    dt, unit = np.float32(1 / 120), K.birth_unit(n, 1 / 120)
    total = ti.ndarray(ti.i64, 3)
    def sums(pots, tau):
        arrays = [_nd(np.asarray(a, np.float32), ti.f32) for a in [*pots, tau]]
        got = [[int(x) for x in K.birth_sums(n, *arrays, dt, unit, gpu, total)] for gpu in (True, False)]
        assert got[0] == got[1], (n, got)
        return got[0]
    on = [rng.random(n) < 0.6 for _ in range(4)]
    pots = [np.where(m, 100.0, 0.0) for m in on]
    per = int(np.floor(float(dt) * unit + 0.5))
    assert sums(pots, [1, 3] * 4) == [int(np.count_nonzero(on[2] & on[c])) * per for c in (0, 1, 3)], n
    pots = [rng.exponential(s, n) * (rng.random(n) < 0.7) for s in (2.0, 1.0, 30.0, 8.0)]
    assert min(sums(pots, [0.5, 4.0, 0.2, 2.0, 5.0, 60.0, 1.0, 12.0])) > 0
print("ok")
"""
    from pathlib import Path

    root = Path(__file__).parents[1]
    done = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-2000:]

PINNED_SCRIPT = """
import sys
import numpy as np
from whitecap.sim import runtime
runtime.PIN_READBACK = sys.argv[1] == "on"
from whitecap.config import scene_from_dict
from whitecap.io.array_pool import ArrayPool
from whitecap.pipeline import simulate
from tests.conftest import tiny_scene_dict
scene = scene_from_dict(tiny_scene_dict(output={"frames": 6}, foam={"preset": "auto", "k_ta": 400.0, "k_wc": 5000.0}))
simulate(scene, out=sys.argv[2], arch="cuda", show_progress=False)
from whitecap.diffuse import postprocess
from whitecap.diffuse.params import resolve
postprocess(sys.argv[2], out=sys.argv[2] + "/pass", params=resolve(preset="auto"), seed=11, arch="cuda",
            show_progress=False)  # a foam pass too
pin, unpin = runtime.host_pinning()
pool = ArrayPool({"x": (np.float32, (3,))}, pin=pin, unpin=unpin)
pool.take(1000)
print("PINNED", pool.pinned)
"""


def test_a_pinned_read_back_writes_the_same_frames(tmp_path):
    """runtime.PIN_READBACK (on by default since 2026-11-28): the host arrays frames are read back into are
    page-locked (cuMemHostRegister) and the driver copies into them by DMA; simulate with foam, and a foam pass over
    its frames, write the same fluid and diffuse files as without."""
    from pathlib import Path

    root = Path(__file__).parents[1]
    files, pinned = {}, {}
    for mode in ("off", "on"):  # (-c: the repository's root on sys.path, for tests.conftest)
        run = subprocess.run([sys.executable, "-c", PINNED_SCRIPT, mode, str(tmp_path / mode)], cwd=root,
                             capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr[-3000:]
        pinned[mode] = int(run.stdout.split("PINNED")[-1].split()[0])
        out = tmp_path / mode
        files[mode] = {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*.ply"))}
    assert pinned == {"off": 0, "on": 1}
    made = {d: sum(len(b) for k, b in files["on"].items() if k.startswith(d)) for d in ("diffuse/", "pass/diffuse/")}
    assert min(made.values()) > 50_000, made  # each writes thousands of diffuse particles (37 B each)
    assert files["on"] == files["off"]


RECORDS_SCRIPT = """
import sys
from whitecap.sim import records
if sys.argv[1] == "arrays":
    records.WORDS_MAX = 0  # every frame read back array by array, the writer packing it
from whitecap.config import scene_from_dict
from whitecap.pipeline import simulate
from tests.conftest import tiny_scene_dict
scene = scene_from_dict(tiny_scene_dict(output={"frames": 6}, foam={"preset": "auto", "k_ta": 400.0, "k_wc": 5000.0}))
simulate(scene, out=sys.argv[2], arch="cuda", show_progress=False)
"""


def test_diffuse_records_packed_on_the_device_are_the_files_the_writer_packs(tmp_path):
    """On CUDA the fluid and the diffuse particles come back as their files' records, made on the device
    (sim.records) and copied back in one piece: simulate with foam writes the same files as with every frame read
    back array by array and packed by the writer."""
    from pathlib import Path

    root = Path(__file__).parents[1]
    files = {}
    for way in ("arrays", "records"):  # (-c: the repository's root on sys.path, for tests.conftest)
        run = subprocess.run([sys.executable, "-c", RECORDS_SCRIPT, way, str(tmp_path / way)], cwd=root,
                             capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr[-3000:]
        out = tmp_path / way
        files[way] = {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*.ply"))}
    diffuse = [k for k in files["records"] if k.startswith("diffuse/")]
    assert diffuse and max(len(files["records"][k]) for k in diffuse) > 400 + 37 * 10  # (a header and 10 records)
    assert files["records"] == files["arrays"]
