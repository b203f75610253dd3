"""Solver benchmark: dam break at ~30k and ~120k particles, 4 iterations, fixed dt.

Prints ms per step, particle-iterations per second (particles × iterations /
step time, the whole step included: neighbour search, all iterations,
vorticity, XSPH and the density map), its ratio to the 6 M target and to
SPlisHSPlasH's 1.7 M, the scaling ratio of per-particle cost between the
sizes, memory per particle (solver arrays, and resident growth of the
process) and the machine's load average before and after each size, since
figures taken beside other jobs are low. Runs on the CPU, and on CUDA when
present.

    python benchmarks/bench_solver.py [--arch cpu|cuda|auto] [--sizes 30000,120000] [--steps 30] [--moving]
    WHITECAP_BENCH_1M=1 python benchmarks/bench_solver.py   # adds a 1 M-particle size (minutes on 2 cores)

Each size runs in its own process (one Taichi runtime per process).
Reference run: SPlisHSPlasH PBF (C++, OpenMP) on this kind of 2-core machine,
about 1.7 M particle-iterations/s (30k: ~54 ms/step, 120k: ~410 ms/step).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time

REFERENCE_PITS = 1.7e6  # SPlisHSPlasH PBF, particle-iterations per second
TARGET_PITS = 6.0e6  # issue 20: whole step, 4 iterations, 2 CPU cores
BIG_SIZE = 1_000_000  # added when WHITECAP_BENCH_1M is set
JITTER = 0.3  # --moving: lattice jitter [spacings]
COLUMN_HEIGHT = 0.8  # [m], 2a in scene_for: the column falls at up to sqrt(2 g H) (--moving's CFL dt)


def scene_for(n_target: int, iterations: int = 4, reorder_interval: int | None = None):
    from whitecap.config import scene_from_dict

    # Column of width a, depth a/2, height 2a in a 4a × a/2 × 2.5a tank.
    # n = (a/2r)·(a/4r)·(2a/2r) = a³/(8 r³)  →  r = a / (2·(n)^(1/3)).
    a = 0.4
    r = a / (2.0 * n_target ** (1.0 / 3.0))
    return scene_from_dict(
        {
            "domain": {"upper": [4 * a, a / 2, 2.5 * a]},
            "solver": {"particle_radius": r, "iterations": iterations, "substeps": 10, "frame_rate": 30,
                       **({} if reorder_interval is None else {"reorder_interval": reorder_interval})},
            "fluid": [{"lower": [0, 0, 0], "upper": [a, a / 2, 2 * a]}],
        }
    )


def run_one(n_target: int, arch: str, steps: int, reorder_interval: int | None = None, moving: bool = False) -> dict:
    from whitecap import timing
    from whitecap.sim.driver import build_solver

    sc = scene_for(n_target, reorder_interval=reorder_interval)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    res0 = resident_bytes()
    s = build_solver(sc, arch)
    dt = 1.0 / sc.solver.frame_rate / sc.solver.substeps
    if moving:
        # A fluid in motion: the lattice jittered by up to JITTER spacings (about the neighbour count of
        # a disordered fluid at rest density), and dt at the CFL limit for the fastest the falling
        # column gets, so that the fluid is not compressed as it moves (the fixed dt above is beyond
        # that limit at r = 4 mm and finer).
        import numpy as np

        r = sc.solver.particle_radius
        ck = s.checkpoint()
        jit = np.random.default_rng(0).uniform(-JITTER, JITTER, ck["x"].shape) * 2 * r
        lo, hi = np.asarray(sc.domain.lower) + r, np.asarray(sc.domain.upper) - r
        ck["x"] = np.clip(ck["x"] + jit, lo, hi).astype(np.float32)
        s.restore(ck)
        del ck, jit  # not counted as the solver's memory
        release_freed_heap()
        dt = sc.solver.cfl * 2 * r / math.sqrt(2 * 9.81 * COLUMN_HEIGHT)
    for _ in range(5):  # warm-up: compile kernels, settle the first contacts
        s.step(dt)
    import taichi as ti

    ti.sync()
    timing.reset()
    timing.SYNC = arch != "cpu"
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        s.step(dt)
    ti.sync()
    el = time.perf_counter() - t0
    cpu = time.process_time() - c0
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    res1 = resident_bytes()
    ms = 1e3 * el / steps
    phases = {k: 1e3 * v[0] / max(v[1], 1) * (v[1] / steps) for k, v in timing.TIMERS.items()}
    return {
        "arch": arch,
        "particles": s.n,
        "ms_per_step": ms,
        # CPU time of all the process's threads per step: beside other jobs it varies far less than the
        # wall time, so A/B comparisons on a loaded machine use it (on a quiet machine ≈ cores × wall).
        "cpu_ms_per_step": 1e3 * cpu / steps,
        "pits": s.n * sc.solver.iterations / (el / steps),
        "bytes_per_particle_device": s.memory_bytes() / s.n,
        "bytes_per_particle_rss": (rss1 - rss0) / s.n,  # growth of the peak (set-up copies included)
        "bytes_per_particle_resident": (res1 - res0) / s.n,  # growth of what stays resident while stepping
        "phases_ms_per_step": phases,
        # the lists' slots (fewer than max_neighbors where 32-bit indices cut them, as at 50 M) and the pairs
        # a step that did not fit them
        "list_slots": s.grid.max_neighbors,
        "overflow_per_step": s.take_overflow() / steps,
    }


def cpu_model() -> str:
    """The processor's name, so that a figure says which machine it came from."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or "unknown CPU"


def gpu_names() -> list[str]:
    """The NVIDIA GPUs' names from nvidia-smi (empty when it is not there)."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                             text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return []
    return [line.strip() for line in out.stdout.splitlines() if line.strip()]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--sizes", default="30000,120000")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--reorder-interval", type=int, help="solver.reorder_interval (default: the scene default)")
    ap.add_argument("--moving", action="store_true",
                    help="a fluid in motion: jittered start, CFL-limited dt (default: the lattice and a fixed dt)")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one:
        print(json.dumps(run_one(a.one, a.arch, a.steps, a.reorder_interval, a.moving)))
        return
    archs = [a.arch]
    if a.arch == "cpu":
        from whitecap.sim.runtime import cuda_available

        if cuda_available():
            archs.append("cuda")
    sizes = [int(v) for v in a.sizes.split(",")]
    if os.environ.get("WHITECAP_BENCH_1M") and BIG_SIZE not in sizes:
        sizes.append(BIG_SIZE)
    results = []
    for arch in archs:
        for n in sizes:
            load0 = load_average()
            out = subprocess.run(
                [sys.executable, __file__, "--one", str(n), "--arch", arch, "--steps", str(a.steps)]
                + ([] if a.reorder_interval is None else ["--reorder-interval", str(a.reorder_interval)])
                + (["--moving"] if a.moving else []),
                capture_output=True, text=True, env={**os.environ, "WHITECAP_PROGRESS": "0"},
            )
            if out.returncode:
                print(out.stderr[-2000:], file=sys.stderr)
                raise SystemExit(out.returncode)
            results.append({**json.loads(out.stdout.strip().splitlines()[-1]), "load": (load0, load_average())})
    how = "jittered start, CFL-limited dt" if a.moving else "fixed dt"
    print(f"PBF dam break, 4 iterations, {how}, {os.cpu_count()} cores ({cpu_model()})"
          + ("".join(f", GPU {g}" for g in gpu_names()) if "cuda" in archs else ""))
    print(f"{'arch':5s} {'particles':>10s} {'ms/step':>9s} {'CPU ms':>8s} {'M p-it/s':>9s} {'vs SPH-PBF':>10s} "
          f"{'vs target':>9s} {'B/particle':>10s} {'peak B/p':>8s} {'res B/p':>7s} {'load':>10s}")
    for r in results:
        print(
            f"{r['arch']:5s} {r['particles']:10d} {r['ms_per_step']:9.1f} {r['cpu_ms_per_step']:8.1f} "
            f"{r['pits'] / 1e6:9.2f} "
            f"{r['pits'] / REFERENCE_PITS:9.2f}x {r['pits'] / TARGET_PITS:8.2f}x "
            f"{r['bytes_per_particle_device']:10.0f} {r['bytes_per_particle_rss']:8.0f} "
            f"{r['bytes_per_particle_resident']:7.0f} "
            f"{r['load'][0]:4.1f}→{r['load'][1]:4.1f}"
        )
    print(f"target {TARGET_PITS / 1e6:.1f} M p-it/s; reference SPlisHSPlasH PBF {REFERENCE_PITS / 1e6:.1f} M; "
          f"load = 1-minute load average before → after (the target counts only on a quiet machine)")
    for arch in archs:
        rs = [r for r in results if r["arch"] == arch]
        if len(rs) >= 2:
            small, big = rs[0], rs[-1]
            ratio = (big["ms_per_step"] / big["particles"]) / (small["ms_per_step"] / small["particles"])
            print(f"{arch}: per-particle cost at {big['particles']} / at {small['particles']}: {ratio:.2f} "
                  "(target ≤ 1.3)")
    for r in results:
        ph = ", ".join(f"{k} {v:.1f}" for k, v in sorted(r["phases_ms_per_step"].items(), key=lambda kv: -kv[1]))
        print(f"  {r['arch']} {r['particles']}: ms/step by phase: {ph}; neighbour lists of {r['list_slots']}, "
              f"{r['overflow_per_step']:.0f} pairs a step past them")


def release_freed_heap() -> None:
    """Hands memory that Python freed back to the OS (glibc's malloc_trim), so that the resident
    figure counts the solver and not the set-up's temporary arrays: after a large block is freed,
    glibc raises its mmap threshold and keeps later blocks of that size in the heap (measured: the
    --moving set-up's checkpoint and jitter left about 45 B/particle resident at 1 M)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def resident_bytes() -> int:
    """The process's resident set now (VmRSS), 0 where /proc is missing."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def load_average() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


if __name__ == "__main__":
    main()
