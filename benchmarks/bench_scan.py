"""The device's exclusive prefix sum (sim/scan.py, the foam stage's compaction and the sinks') in its two layouts.

- ``cpu layout``: at most 4,096 blocks of 256 or more elements, one thread a block, the block sums by one thread
  (the only layout before 3bdd46b, on every arch);
- ``gpu layout``: up to 131,072 blocks of 16 or more, the block sums scanned in groups of 512.

Both run on the chosen arch, alternately, on the same keep flags (0 or 1, as compaction scans); printed: the
median ms a scan (each returns its total, so each is waited for) and the ratio cpu layout / gpu layout (above
1: the GPU's layout faster). The sums are checked equal.

    python benchmarks/bench_scan.py --arch cuda [--sizes 1000000,2700000,33554432] [--repeats 50]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--sizes", default="1000000,2700000,33554432")
    ap.add_argument("--repeats", type=int, default=50)
    a = ap.parse_args()

    import taichi as ti

    from whitecap.sim import runtime
    from whitecap.sim.scan import SCAN_SUMS, exclusive_scan, scan_block

    runtime.init(a.arch)
    print(f"exclusive prefix sum on {a.arch}, median of {a.repeats} a layout, alternating")
    for n in (int(s) for s in a.sizes.split(",")):
        flags = (np.random.default_rng(n).random(n) < 0.6).astype(np.int32)
        src, out, sums = ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, SCAN_SUMS)
        src.from_numpy(flags)
        times: dict[bool, list[float]] = {False: [], True: []}
        for gpu in (False, True):  # compiled and checked before timing
            assert exclusive_scan(n, src, sums, out, gpu=gpu) == int(flags.sum())
        for _ in range(a.repeats):
            for gpu in (False, True):
                t = time.perf_counter()
                exclusive_scan(n, src, sums, out, gpu=gpu)
                times[gpu].append(time.perf_counter() - t)
        c, g = (1e3 * statistics.median(times[k]) for k in (False, True))
        print(f"  {n:>11,}: cpu layout {c:7.3f} ms ({scan_block(n, False)} a block), gpu layout {g:7.3f} ms "
              f"({scan_block(n, True)} a block): {c / g:.2f}x")


if __name__ == "__main__":
    main()
