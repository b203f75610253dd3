"""A frame's files through the background writer: one after the other, side by side on lanes, frames side by side.

Each frame is a fluid PLY of ``--fluid`` particles (positions, velocities, density, ids: 32 B each) and a
diffuse PLY of ``--diffuse`` particles (positions, velocities, lifetime, type, radius, ids), then a small
run.json, handed to one :class:`whitecap.io.writer.FrameWriter` as ``simulate`` and ``whitecap foam`` hand
theirs. Four ways, in rounds (``--pairs`` of them) in one process, each run's frames new files, as a run's are
(files written over others wait for the old ones' pages still being written back: 42-47 ms a 59 MB file here
against 13 ms new), removed after the run and the disk synced, untimed; which goes first rotates:

- ``one thread``: every job one after the other (whitecap before lanes);
- ``lanes``: the fluid and the diffuse file on lanes of their own, run.json after both, and the next frame's
  files after that run.json (lanes of depth 1, each frame waited for: whitecap before frames side by side);
- ``frames``: as whitecap writes now: lanes of depth 2 (io.writer.LANE_DEPTH), the next frame's files beside
  the last frame's and its run.json;
- ``deeper``: as ``frames``, with lanes of depth :data:`DEEPER` (four frames' files side by side): whether a
  machine with many cores writes more a second with more threads on a lane, where one lane thread could not keep
  up with a frame at 30 frames/s (an H200's RAM disk: 34 ms a diffuse file; its own disk: 68 ms);
- ``bytes``: as ``frames``, but each file's bytes made once beforehand and only written (io.atomic.write_bytes):
  what a frame's files would cost were their records packed elsewhere (on the device, say), the floor that
  packing on the host is measured against.

Printed: ms a frame for each, round by round (the five in a rotating order), the ratios one thread / lanes,
lanes / frames, frames / deeper (above 1: the later way faster) and frames / bytes (what packing the records on the
host adds). The defaults are `whitecap foam` at 1 M fluid particles with 1.6 diffuse particles each (about 32 + 58
MB a frame). ``--dir`` picks the file system (a RAM disk: /dev/shm); the default is a temporary folder.

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
from whitecap.io.atomic import write_bytes, write_text
from whitecap.io.frame import ParticleFrame
from whitecap.io.writer import LANE_DEPTH, FrameWriter


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


MODES = ("one thread", "lanes", "frames", "deeper", "bytes")
#: The lanes' depth of ``deeper``: twice whitecap's own.
DEEPER = 2 * LANE_DEPTH


def run(folder: Path, files: dict, n: int, mode: str) -> float:
    """ms a frame for ``n`` frames written through one FrameWriter, the last flushed. ``files``: the fluid and
    the diffuse frame, and (``bytes``) their files' bytes."""
    lanes = mode != "one thread"
    one_frame = mode in ("one thread", "lanes")  # each frame's files and run.json done before the next frame's
    t0 = time.perf_counter()
    depth = 1 if one_frame else DEEPER if mode == "deeper" else LANE_DEPTH
    with FrameWriter(name="bench-writer", depth=depth) as w:
        for k in range(n):
            for kind in ("fluid", "diffuse"):
                path = folder / f"{kind}_{k:05d}.ply"
                job = (functools.partial(write_bytes, path, files[kind + " bytes"]) if mode == "bytes"
                       else functools.partial(write, path, files[kind]))
                w.submit(job, kind, lane=kind if lanes else None)
            w.submit(functools.partial(write_text, folder / "run.json", f'{{"frame": {k}}}'), "run.json")
            if one_frame:
                w.flush()
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
    ap.add_argument("--pairs", type=int, default=3, help="rounds of the five ways")
    ap.add_argument("--dir", help="folder to write into (default: a temporary one)")
    a = ap.parse_args()
    fluid, diffuse = frames(a.fluid, a.diffuse)
    with tempfile.TemporaryDirectory(dir=a.dir) as tmp:
        folder = Path(tmp)
        files: dict = {"fluid": fluid, "diffuse": diffuse}
        for kind in ("fluid", "diffuse"):
            write(folder / f"{kind}.ply", files[kind])
            files[kind + " bytes"] = (folder / f"{kind}.ply").read_bytes()
            (folder / f"{kind}.ply").unlink()
        mb = (len(files["fluid bytes"]) + len(files["diffuse bytes"])) / 1e6
        for mode in MODES:  # warm-up: the writers' record buffers and threads
            run(folder, files, 2, mode)
        print(f"{a.fluid:,} fluid + {a.diffuse:,} diffuse particles a frame ({mb:.0f} MB), {a.frames} frames a run, "
              f"into {folder}")
        got: dict[str, list[float]] = {m: [] for m in MODES}
        k = len(MODES)
        for i in range(a.pairs):  # the order rotates: each mode goes first, second, ... and last in turn
            for mode in MODES[i % k:] + MODES[:i % k]:
                got[mode].append(run(folder, files, a.frames, mode))
            one, lanes, side, deep, raw = (got[m][-1] for m in MODES)
            print(f"  round {i + 1}: one thread {one:7.1f}, lanes {lanes:7.1f}, frames {side:7.1f}, "
                  f"deeper {deep:7.1f}, bytes {raw:7.1f} ms a frame: one thread / lanes {one / lanes:.2f}x, "
                  f"lanes / frames {lanes / side:.2f}x, frames / deeper {side / deep:.2f}x, "
                  f"frames / bytes {side / raw:.2f}x")
        med = {m: statistics.median(v) for m, v in got.items()}
        rounds = list(zip(*(got[m] for m in MODES)))

        def ratio(a_: int, b_: int) -> str:
            return f"{statistics.median(r[a_] / r[b_] for r in rounds):.2f}x"
        print("median: " + ", ".join(f"{m} {med[m]:.1f} ms a frame ({1e3 / med[m]:.1f} frames/s)" for m in MODES)
              + f"; rounds' ratio medians: one thread / lanes {ratio(0, 1)}, lanes / frames (frames side by side) "
              f"{ratio(1, 2)}, frames / deeper (lanes of depth {DEEPER}) {ratio(2, 3)}, frames / bytes (packing on "
              f"the host) {ratio(2, 4)}")


if __name__ == "__main__":
    main()
