"""A frame's files through the background writer: one after the other on its thread, or side by side on lanes.

Each frame is a fluid PLY of ``--fluid`` particles (positions, velocities, density, ids: 32 B each) and a
diffuse PLY of ``--diffuse`` particles (positions, velocities, lifetime, type, radius, ids), then a small
run.json, handed to one :class:`whitecap.io.writer.FrameWriter` as ``simulate`` and ``whitecap foam`` hand
theirs. Two ways, alternating in pairs in one process, each run's frames new files, as a run's are (files
written over others wait for the old ones' pages still being written back: 42-47 ms a 59 MB file here against
13 ms new), removed after the run and the disk synced, untimed; which of the two goes first alternates:

- ``one thread``: every job on the writer's own thread (whitecap before lanes);
- ``lanes``: the fluid and the diffuse file on lanes of their own, run.json after both.

Printed: ms a frame for each, pair by pair, and the ratio one thread / lanes (above 1: lanes faster). The
defaults are `whitecap foam` at 1 M fluid particles with 1.6 diffuse particles each (about 32 + 58 MB a frame).
``--dir`` picks the file system (a RAM disk: /dev/shm); the default is a temporary folder.

    python benchmarks/bench_writer.py [--fluid 1000000] [--diffuse 1600000] [--frames 10] [--pairs 3]
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from whitecap.io import write
from whitecap.io.atomic import write_text
from whitecap.io.frame import ParticleFrame
from whitecap.io.writer import FrameWriter


def frames(n_fluid: int, n_diffuse: int) -> tuple[ParticleFrame, ParticleFrame]:
    rng = np.random.default_rng(0)
    fluid = ParticleFrame(rng.random((n_fluid, 3), np.float32), rng.random((n_fluid, 3), np.float32),
                          np.arange(n_fluid, dtype=np.int32), rng.random(n_fluid, np.float32), time=0.0)
    diffuse = ParticleFrame(rng.random((n_diffuse, 3), np.float32), rng.random((n_diffuse, 3), np.float32),
                            np.arange(n_diffuse, dtype=np.int32), time=0.0,
                            arrays={"lifetime": rng.random(n_diffuse, np.float32),
                                    "type": rng.integers(0, 3, n_diffuse).astype(np.uint8),
                                    "radius": np.full(n_diffuse, 0.004, np.float32)})
    return fluid, diffuse


def run(folder: Path, fluid: ParticleFrame, diffuse: ParticleFrame, n: int, lanes: bool) -> float:
    """ms a frame for ``n`` frames written through one FrameWriter, the last flushed."""
    t0 = time.perf_counter()
    with FrameWriter(name="bench-writer") as w:
        for k in range(n):
            w.submit(functools.partial(write, folder / f"fluid_{k:05d}.ply", fluid), "fluid",
                     lane="fluid" if lanes else None)
            w.submit(functools.partial(write, folder / f"diffuse_{k:05d}.ply", diffuse), "diffuse",
                     lane="diffuse" if lanes else None)
            w.submit(functools.partial(write_text, folder / "run.json", f'{{"frame": {k}}}'), "run.json")
        w.flush()
    ms = 1e3 * (time.perf_counter() - t0) / n
    for f in folder.glob("*.ply"):
        f.unlink()
    os.sync()  # the next run starts with nothing of this one's still being written back
    return ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fluid", type=int, default=1_000_000)
    ap.add_argument("--diffuse", type=int, default=1_600_000)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--dir", help="folder to write into (default: a temporary one)")
    a = ap.parse_args()
    fluid, diffuse = frames(a.fluid, a.diffuse)
    with tempfile.TemporaryDirectory(dir=a.dir) as tmp:
        folder = Path(tmp)
        write(folder / "f.ply", fluid)
        write(folder / "d.ply", diffuse)
        mb = sum(p.stat().st_size for p in folder.glob("*.ply")) / 1e6
        run(folder, fluid, diffuse, 2, True)  # warm-up: the writers' record buffers and threads
        print(f"{a.fluid:,} fluid + {a.diffuse:,} diffuse particles a frame ({mb:.0f} MB), {a.frames} frames a run, "
              f"into {folder}")
        ratios, one, two = [], [], []
        for i in range(a.pairs):  # which goes first alternates
            if i % 2 == 0:
                t1 = run(folder, fluid, diffuse, a.frames, False)
                t2 = run(folder, fluid, diffuse, a.frames, True)
            else:
                t2 = run(folder, fluid, diffuse, a.frames, True)
                t1 = run(folder, fluid, diffuse, a.frames, False)
            one.append(t1)
            two.append(t2)
            ratios.append(t1 / t2)
            print(f"  pair {i + 1}: one thread {t1:7.1f} ms a frame, lanes {t2:7.1f} ms a frame: {t1 / t2:.2f}x")
        m1, m2 = statistics.median(one), statistics.median(two)
        print(f"median: one thread {m1:.1f} ms a frame ({1e3 / m1:.1f} frames/s), lanes {m2:.1f} ({1e3 / m2:.1f} "
              f"frames/s); pairs' ratio median {statistics.median(ratios):.2f}x")


if __name__ == "__main__":
    main()
