"""Does spreading the per-frame part of foam post-processing pay (issue 17)?

    PYTHONPATH=src python benchmarks/bench_foam_prefetch.py [--repeat 3] [--input DIR]

The diffuse advection is sequential in time (frame k needs the diffuse
particles of frame k − 1); what is per-frame is reading the input frames and
the fluid potentials. The potentials share the neighbour grid the advection of
the same frame uses, so only reading can move out without doing work twice.
This times `whitecap foam` on the DualSPHysics dam break (81 PartVTK frames)
three ways, interleaved so that all see the same machine load:

- serial: as `whitecap foam` does (read frame k, then process it);
- thread prefetch: frame k + 1 is read on a thread while frame k is processed;
- process prefetch: the same in a spawned process (the frame is pickled back).

It prints the medians, the load, and whether the diffuse files are byte-identical.
"""

from __future__ import annotations

import argparse
import contextlib
import io as _io
import os
import statistics
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from multiprocessing import get_context
from pathlib import Path

os.environ.setdefault("WHITECAP_PROGRESS", "0")

from whitecap import io  # noqa: E402
from whitecap.diffuse import driver, postprocess  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_INPUT = str(ROOT.parent / "shared/data/dualsphysics_dambreak")


def prefetching(pool):
    """A _Reader.read that starts reading frame k + 1 on ``pool`` when frame k is taken."""

    def read(self, k, keep=False):
        if k in self.cache:
            return self.cache.pop(k) if not keep else self.cache[k]
        fut = getattr(self, "_next", {}).pop(k, None)
        fr = fut.result() if fut is not None else io.read(self.files[k][1], **self.kw)
        if k + 1 < len(self.files) and not keep:
            self._next = {k + 1: pool.submit(io.read, self.files[k + 1][1], **self.kw)}
        if keep:
            self.cache[k] = fr
        return fr

    return read


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--input", default=DEFAULT_INPUT, help="folder with PartFluid_*.vtk and CaseDambreak.xml")
    a = ap.parse_args()
    frames, case = f"{a.input}/PartFluid_*.vtk", f"{a.input}/CaseDambreak.xml"
    ways = {"serial": driver._Reader.read,
            "thread prefetch": prefetching(ThreadPoolExecutor(1)),
            "process prefetch": prefetching(ProcessPoolExecutor(1, mp_context=get_context("spawn")))}
    times: dict[str, list[float]] = {k: [] for k in ways}
    quiet = (contextlib.redirect_stdout(_io.StringIO()), contextlib.redirect_stderr(_io.StringIO()))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        files = sorted(Path(a.input).glob("PartFluid_*.vtk"))
        t0 = time.perf_counter()
        for f in files:
            io.read(f)
        t_read = (time.perf_counter() - t0) / len(files)
        with quiet[0], quiet[1]:
            postprocess(files[0], out=tmp / "warm", show_progress=False)  # Taichi kernels compiled
        for rep in range(a.repeat):
            for name, read in ways.items():
                driver._Reader.read = read
                t0 = time.perf_counter()
                with contextlib.redirect_stdout(_io.StringIO()), contextlib.redirect_stderr(_io.StringIO()):
                    postprocess(frames, out=tmp / f"{name.split()[0]}{rep}", case=case, show_progress=False)
                times[name].append(time.perf_counter() - t0)
        ref = tmp / "serial0" / "diffuse"
        same = all((ref / f.name).read_bytes() == (tmp / d / "diffuse" / f.name).read_bytes()
                   for d in ("thread0", "process0") for f in ref.iterdir() if f.is_file())
    print(f"{len(files)} frames; load {' '.join(Path('/proc/loadavg').read_text().split()[:3])}; "
          f"reading alone {1e3 * t_read:.0f} ms/frame")
    for name, ts in times.items():
        print(f"{name:17s}: {statistics.median(ts):6.2f} s median (runs {', '.join(f'{t:.2f}' for t in ts)})")
    print(f"diffuse files byte-identical across the three: {same}")


if __name__ == "__main__":
    main()
