"""Named phase timers, in the spirit of Warp's ``ScopedTimer``.

    with timer("pbf.neighbours"):
        ...

Totals accumulate in :data:`TIMERS`; ``--profile`` and the benchmarks print
:func:`report`. Taichi kernels launch asynchronously on GPUs, so a timer that
wraps kernels calls ``ti.sync()`` when ``sync`` is set.
"""

from __future__ import annotations

import contextlib
import time
from collections import defaultdict
from typing import Iterator

TIMERS: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])  # name -> [seconds, count]
ENABLED = True
SYNC = False


@contextlib.contextmanager
def timer(name: str) -> Iterator[None]:
    if not ENABLED:
        yield
        return
    if SYNC:
        import taichi as ti

        ti.sync()
    t0 = time.perf_counter()
    try:
        yield
    finally:
        if SYNC:
            import taichi as ti

            ti.sync()
        rec = TIMERS[name]
        rec[0] += time.perf_counter() - t0
        rec[1] += 1


def reset() -> None:
    TIMERS.clear()


#: Timers of a background thread (io.writer.FrameWriter's ``writer.<label>``): overlapped with the caller's phases,
#: so never part of a report's total.
BACKGROUND_PREFIX = "writer."


def top_level(names) -> list[str]:
    """The phases a report's total is the sum of: the undotted names (``simulate``: step, diffuse, output); where
    every name is dotted (a ``foam`` pass: foam.potentials, foam.generate, output.wait), those no other name is the
    parent of (foam.generate.auto is foam.generate's), the background thread's left out."""
    names = list(names)
    plain = [k for k in names if "." not in k]
    if plain:
        return plain
    return [k for k in names if not k.startswith(BACKGROUND_PREFIX)
            and not any(k.startswith(parent + ".") for parent in names if parent != k)]


def report(title: str = "profile") -> str:
    if not TIMERS:
        return f"{title}: no timings"
    total = sum(TIMERS[k][0] for k in top_level(TIMERS)) or sum(v[0] for v in TIMERS.values())
    lines = [f"{title}:", f"  {'phase':32s} {'calls':>7s} {'total s':>9s} {'ms/call':>9s} {'share':>6s}"]
    for name, (sec, n) in sorted(TIMERS.items(), key=lambda kv: -kv[1][0]):
        lines.append(f"  {name:32s} {n:7d} {sec:9.3f} {1e3 * sec / max(n, 1):9.2f} {100 * sec / total:5.1f}%")
    return "\n".join(lines)
