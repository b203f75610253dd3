"""Neighbour-grid benchmark (issue 31 goal 3): the dense cell table against the hashed one.

For each size, the fluid of bench_solver.py's dam break (a column of width a, depth a/2, height 2a in
a 4a × a/2 × 2.5a tank; its lattice jittered by up to 0.3 spacings, about the disorder of a fluid in
motion) is sorted and its neighbour lists built (NeighborGrid.build: the solver's list building, once
a step), in the same run:

- in the tank with the dense table (what the solver chooses there) and with the hashed one;
- in a domain 1000× the fluid's volume (the tank stretched alike along each axis), hashed: the dense
  table there would need the number of cells printed, and is not allocated;
- in the tank, dense, with the cell counts' prefix sum in the other arch's layout (``dense*``: on a GPU the
  block sums walked by one thread, as before 2026-11-28; on the CPU scanned in groups, as a GPU now does).

Prints ms a build (the least of --repeats, after a warm-up that compiles), hashed over dense, the
grid's bytes per particle (NeighborGrid.nbytes: lists, sort arrays and cell table; the table's own
share apart) and whether all three gave the same neighbour counts. The CPU time (all the process's
threads) is printed beside the wall time: on a machine shared with other jobs it is the steadier figure.

    python benchmarks/bench_grid.py [--arch cpu|cuda] [--sizes 120000] [--repeats 10]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_solver import JITTER, cpu_model, gpu_names, load_average, scene_for

VOLUME_RATIO = 1000  # the large domain's volume over the fluid's


def positions(n_target: int):
    """(scene, jittered lattice of its fluid) for about ``n_target`` particles."""
    from whitecap.sim.pbf import lattice_points

    sc = scene_for(n_target)
    r = sc.solver.particle_radius
    x, _ = lattice_points(sc)
    x = x + np.random.default_rng(0).uniform(-JITTER, JITTER, x.shape) * 2 * r
    lo, hi = np.asarray(sc.domain.lower) + r, np.asarray(sc.domain.upper) - r
    return sc, np.clip(x, lo, hi).astype(np.float32)


def time_build(grid, xs, n: int, repeats: int) -> tuple[float, float]:
    """The least wall time and the least CPU time of the process (all its threads) of ``repeats`` builds
    [ms] (build reads the overflow back: it waits for the device). Beside other jobs the CPU time varies
    far less than the wall time."""
    grid.build(xs, n)  # compiles
    wall = cpu = float("inf")
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        grid.build(xs, n)
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return 1e3 * wall, 1e3 * cpu


def run_size(n_target: int, repeats: int) -> None:
    import taichi as ti

    from whitecap.sim import grid as G, runtime
    from whitecap.sim.grid import NeighborGrid, grid_layout, grid_spec

    sc, x = positions(n_target)
    n = len(x)
    s = sc.solver
    h = s.kernel_support * s.particle_radius
    xs = ti.Vector.ndarray(3, ti.f32, n)
    xs.from_numpy(x)
    lo, hi = np.asarray(sc.domain.lower), np.asarray(sc.domain.upper)
    tank = grid_spec(lo, hi, h / 2)
    # The tank stretched alike along each axis until its volume is VOLUME_RATIO × the fluid's (n (2r)³).
    stretch = (VOLUME_RATIO * n * (2 * s.particle_radius) ** 3 / np.prod(hi - lo)) ** (1 / 3)
    big = grid_spec(lo, lo + (hi - lo) * stretch, h / 2)
    rows = []
    counts = {}
    other = runtime.current() == "cpu"  # dense*: the other arch's scan of the cell counts (sim.grid.GROUPED_SCAN)
    for name, spec, layout in (("tank", tank, "dense"), ("tank", tank, "hashed"), (f"{VOLUME_RATIO}x", big, "hashed"),
                               ("tank", tank, "dense*")):
        G.GROUPED_SCAN = other if layout == "dense*" else None
        g = NeighborGrid(spec, n, s.max_neighbors, h, layout.rstrip("*"))
        G.GROUPED_SCAN = None
        ms, cpu_ms = time_build(g, xs, n, repeats)
        counts[(name, layout)] = g.nb_count.to_numpy()[:n]
        rows.append((name, spec, layout, ms, cpu_ms, g.nbytes() / n, g.table_size, g.overflow))
        del g
    same = all((c == counts[("tank", "dense")]).all() for c in counts.values())
    dense_ms, dense_cpu = rows[0][3], rows[0][4]
    print(f"{n} particles, h = {h * 1e3:.2f} mm, cells of h/2; tank {tank.dims} = {tank.ncells / n:.1f} cells "
          f"a particle (auto layout: {grid_layout(tank, n)}), {VOLUME_RATIO}x domain {big.dims} = "
          f"{big.ncells / n:.0f} cells a particle (auto: {grid_layout(big, n)})")
    print(f"dense*: the cell counts' block sums {'scanned in groups (a GPU' if other else 'by one thread (before'}'s "
          "layout); the others in this arch's own")
    print(f"{'domain':8s} {'layout':7s} {'ms/build':>9s} {'vs dense':>8s} {'CPU ms':>8s} {'vs dense':>8s} "
          f"{'B/particle':>10s} {'table B/p':>9s} {'overflow':>8s}")
    for name, spec, layout, ms, cpu_ms, bpp, table, ovf in rows:
        print(f"{name:8s} {layout:7s} {ms:9.2f} {ms / dense_ms:7.2f}x {cpu_ms:8.2f} {cpu_ms / dense_cpu:7.2f}x "
              f"{bpp:10.0f} {4 * (table + 1) / n:9.1f} {ovf:8d}")
    print(f"same neighbour counts in all four: {same}; the dense table of the {VOLUME_RATIO}x domain would be "
          f"{4 * big.ncells / n:.0f} B a particle ({big.ncells:,} cells)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--sizes", default="120000")
    ap.add_argument("--repeats", type=int, default=10)
    a = ap.parse_args()
    from whitecap.sim import runtime

    runtime.init(a.arch)
    where = f"GPU {', '.join(gpu_names())}" if a.arch == "cuda" else f"{os.cpu_count()} cores ({cpu_model()})"
    print(f"neighbour grid: dense vs hashed cell table, list building, {a.arch} on {where}; "
          f"load {load_average():.1f}")
    for n in (int(v) for v in a.sizes.split(",")):
        run_size(n, a.repeats)
    print(f"load {load_average():.1f} (1-minute average; figures beside other jobs are slow)")


if __name__ == "__main__":
    main()
