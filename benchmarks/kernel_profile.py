"""Each Taichi kernel's device time, for the benchmarks' ``--kernels`` runs (bench_simulate_foam.py, bench_foam.py):
where a frame goes on the device, which the host's timers cannot say (a timer that ends at a read-back holds the
wait for every kernel launched before it).

    import kernel_profile
    kernel_profile.enable()        # before whitecap's runtime.init: ti.init with kernel_profiler=True
    ...
    kernel_profile.clear()         # after the warm-up
    ...
    total_ms, rows = kernel_profile.times()
    kernel_profile.show(rows, frames)

Taichi's profiler times kernels one by one: the solver's compute graphs are turned off (it does not see the
kernels inside a graph), and its timing slows the run, so a profiled run's wall time is not the benchmark's figure.
"""

from __future__ import annotations

import re

SHOWN = 24  # kernels listed, most device time first


def enable() -> None:
    """Turn Taichi's kernel profiler on for the next ti.init (whitecap's runtime.init calls it) and the solver's
    compute graphs off (their kernels would not be seen)."""
    import taichi as ti

    from whitecap.sim import pbf

    init = ti.init
    ti.init = lambda *args, **kw: init(*args, kernel_profiler=True, **kw)
    made = pbf.PBFSolver.__init__

    def without_graphs(self, *args, **kw):
        made(self, *args, **kw)
        self.use_graph = False

    pbf.PBFSolver.__init__ = without_graphs


def clear() -> None:
    """Forget the kernels launched so far (a warm-up's)."""
    import taichi as ti

    ti.profiler.clear_kernel_profiler_info()


def _name(name: str) -> str:
    """A Taichi kernel's Python name, from its compiled name (``birth_counts_c80_0_kernel_3_range_for``): the
    profiler has one record a task, and a kernel of several top-level loops launches several tasks."""
    return re.split(r"_c\d+_\d+", name, maxsplit=1)[0]


def times() -> tuple[float, list]:
    """(device time [ms] of every kernel launched since clear(), [[name, ms, tasks], ...] summed by Python
    name, most first). Taichi's public API only prints its table; its profiler's records are read here."""
    import taichi as ti

    prof = ti.profiler.kernel_profiler.get_default_kernel_profiler()
    prof._update_records()
    by: dict[str, list] = {}
    for rec in prof._traced_records:
        t = by.setdefault(_name(rec.name), [0.0, 0])
        t[0] += rec.kernel_time
        t[1] += 1
    rows = sorted(([k, v[0], v[1]] for k, v in by.items()), key=lambda r: -r[1])
    return sum(r[1] for r in rows), rows


def show(rows: list, frames: int, shown: int = SHOWN) -> None:
    """The first ``shown`` rows of times(), a frame each."""
    for k, ms, count in rows[:shown]:
        print(f"  {k:40s} {ms / frames:8.2f} ms/frame {count / frames:7.1f} tasks/frame")
