"""Benchmark of `whitecap mesh` (issue 5).

    PYTHONPATH=src python benchmarks/bench_mesh.py [--particles 100000] [--frames 20] [--repeat 3]
    PYTHONPATH=src python benchmarks/bench_mesh.py --cluster local [--frames 20] [--repeat 3]

Prints
  1. time per frame for one 100k-particle frame (the whole per-frame function:
     read PLY, splashsurf, canonical ordering, write PLY),
  2. the overhead of that function over a bare ``pysplashsurf.reconstruction_pipeline``
     call on the same particles with the same settings (target <= 10 %),
  3. wall time for N frames with --jobs 1 against --jobs 2 (pool start included).

With ``--cluster local`` (issue 17) it prints instead frames/s of the local
process pool and of a local Dask cluster (``pip install 'whitecap[cluster]'``)
with 1 and 2 workers, the same frames, interleaved repeats (median), and the
Dask path's overhead per frame (target < 10 % on 2 cores). The cluster is
started once before timing, as a running cluster is; its start-up is printed
apart. The machine's load (/proc/loadavg) is printed: timings on a shared
machine move with it.

Frames are synthetic: a jittered lattice of fluid (spacing 2r) with a
travelling wave on its surface and a few flying droplets, so the surface has
the sheets and splashes of a real frame. Reference run: the figures in the
README's mesh section / the issue-5 report were measured with these defaults.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from whitecap import io as wio, timing
from whitecap.io.frame import ParticleFrame
from whitecap.surface.driver import plan, run_mesh
from whitecap.surface.reconstruct import MeshParams, mesh_frame, single_threaded_splashsurf

R = 0.01  # simulation particle radius r [m]


def synthetic_frame(n_target: int, k: int, seed: int = 0) -> ParticleFrame:
    """About ``n_target`` particles: a wavy pool of depth ~0.25 m plus droplets; ``k`` shifts the wave phase."""
    rng = np.random.default_rng(seed + k)
    s = 2 * R
    depth = 0.25
    # footprint so that the pool holds ~95 % of n_target particles
    area = 0.95 * n_target * s**3 / depth
    lx = np.sqrt(2 * area)
    ly = area / lx
    xs, ys, zs = np.arange(0, lx, s), np.arange(0, ly, s), np.arange(0, depth + 0.1, s)
    g = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), -1).reshape(-1, 3)
    phase = 2 * np.pi * k / 20
    height = depth + 0.06 * np.sin(2 * np.pi * g[:, 0] / lx * 2 - phase) * np.cos(np.pi * g[:, 1] / ly)
    pool = g[g[:, 2] <= height]
    n_drop = max(0, n_target - len(pool))
    drops = np.column_stack([rng.uniform(0, lx, n_drop), rng.uniform(0, ly, n_drop),
                             rng.uniform(depth + 0.1, depth + 0.3, n_drop)])
    pos = np.concatenate([pool + rng.normal(0, 0.1 * s, pool.shape), drops])
    vel = np.zeros_like(pos)
    vel[:, 0] = np.cos(2 * np.pi * pos[:, 0] / lx * 2 - phase)
    vel[:, 2] = 0.5 * np.sin(2 * np.pi * pos[:, 0] / lx * 2 - phase)
    return ParticleFrame(positions=pos, velocities=vel, density=np.full(len(pos), 1000.0))


def best_of(f, repeat: int) -> tuple[float, list[float]]:
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), ts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=100_000)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cluster", choices=["local"], help="compare the process pool with a local Dask cluster")
    a = ap.parse_args()
    if a.cluster:
        return bench_cluster(a)
    import pysplashsurf

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        seq = tmp / "seq"
        for k in range(a.frames):
            wio.write(seq / f"fluid_{k:05d}.ply", synthetic_frame(a.particles, k))
        src = seq / "fluid_00000.ply"
        frame = wio.read(src)
        params = MeshParams(particle_radius=R).check()
        print(f"machine: {os.cpu_count()} cores; frame: {len(frame)} particles, r = {R} m, "
              f"surface radius {params.surface_radius} m, smoothing {params.smoothing_length}, cube {params.cube_size}")

        # 1 + 2: per-frame function against the bare pysplashsurf call (interleaved, median of repeats)
        pos64 = frame.positions.astype(np.float64)
        vel64 = frame.velocities.astype(np.float64)

        def bare():
            pysplashsurf.reconstruction_pipeline(pos64, attributes_to_interpolate={"velocity": vel64},
                                                 **params.splashsurf_kwargs())

        single_threaded_splashsurf()  # as mesh_frame does: both timings on rayon's one thread
        bare()  # warm-up (thread pool, page cache)
        stats = mesh_frame(src, tmp / "warm.ply", params)
        t_bare, t_func, t_extra = [], [], []
        for _ in range(a.repeat):  # interleaved, so both see the same machine load
            t_bare.append(best_of(bare, 1)[0])
            timing.reset()
            t_func.append(best_of(lambda: mesh_frame(src, tmp / "out.ply", params), 1)[0])
            # time the per-frame function spends outside the splashsurf call
            t_extra.append(t_func[-1] - timing.TIMERS["mesh.splashsurf"][0])
        tb, tf, te = statistics.median(t_bare), statistics.median(t_func), statistics.median(t_extra)
        print(f"mesh: {stats['vertices']} vertices, {stats['faces']} triangles")
        print(f"bare pysplashsurf call      : {tb:7.3f} s median, {min(t_bare):.3f} s best "
              f"(runs {', '.join(f'{t:.3f}' for t in t_bare)})")
        print(f"whitecap mesh_frame         : {tf:7.3f} s median, {min(t_func):.3f} s best "
              f"(runs {', '.join(f'{t:.3f}' for t in t_func)})")
        print(f"  of which outside splashsurf (read, snap, canonical order, write): {te:.3f} s median")
        print(f"overhead over bare call     : {100 * (tf / tb - 1):+6.1f} % (medians), "
              f"{100 * (min(t_func) / min(t_bare) - 1):+6.1f} % (best runs), "
              f"{100 * te / tb:+6.1f} % (time outside splashsurf / bare call); target <= 10 %")
        print(timing.report("mesh_frame phases (last repeat)"))

        # 3: N frames, --jobs 1 against --jobs 2 (pool start and run.json-free sequence input)
        walls = {}
        for jobs in (1, 2):
            job = plan(seq, out=tmp / f"jobs{jobs}", radius=R)
            t0 = time.perf_counter()
            run_mesh(job, jobs=jobs, force=True, show_progress=False)
            walls[jobs] = time.perf_counter() - t0
            print(f"{a.frames} frames, --jobs {jobs}: {walls[jobs]:7.2f} s wall  "
                  f"({walls[jobs] / a.frames:.3f} s/frame)")
        name = "fluid_{:05d}.ply".format
        same = all((tmp / "jobs1" / name(k)).read_bytes() == (tmp / "jobs2" / name(k)).read_bytes()
                   for k in range(a.frames))
        print(f"speed-up --jobs 2 / --jobs 1: {walls[1] / walls[2]:.2f}x; outputs byte-identical: {same}")


def loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "unknown"


def bench_cluster(a) -> None:
    """frames/s: process pool against a local Dask cluster, 1 and 2 workers; Dask overhead per frame."""
    import distributed

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        seq = tmp / "seq"
        for k in range(a.frames):
            wio.write(seq / f"fluid_{k:05d}.ply", synthetic_frame(a.particles, k))
        print(f"machine: {len(os.sched_getaffinity(0))} cores, load {loadavg()} (1, 5, 15 min); "
              f"{a.frames} frames of {a.particles} particles; median of {a.repeat} interleaved repeats")
        rows = []
        for workers in (1, 2):
            t0 = time.perf_counter()
            cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                               dashboard_address=None, silence_logs=40)
            start = time.perf_counter() - t0
            pool, dask = [], []
            try:
                for _ in range(a.repeat):  # interleaved: both see the same load
                    for times, cl in ((pool, None), (dask, cluster.scheduler_address)):
                        job = plan(seq, out=tmp / f"w{workers}{'d' if cl else 'p'}", radius=R)
                        t0 = time.perf_counter()
                        run_mesh(job, jobs=workers, force=True, show_progress=False, cluster=cl)
                        times.append(time.perf_counter() - t0)
            finally:
                cluster.close()
            tp, td = statistics.median(pool), statistics.median(dask)
            name = "fluid_{:05d}.ply".format
            same = all((tmp / f"w{workers}p" / name(k)).read_bytes() == (tmp / f"w{workers}d" / name(k)).read_bytes()
                       for k in range(a.frames))
            over = (td - tp) / a.frames
            rows.append((workers, tp, td))
            print(f"{workers} worker{'s' if workers > 1 else ' '}: process pool {a.frames / tp:6.2f} frames/s, "
                  f"Dask {a.frames / td:6.2f} frames/s; Dask overhead {1000 * over:+7.1f} ms per frame "
                  f"({100 * (td / tp - 1):+5.1f} %); cluster start {start:.1f} s (not counted); "
                  f"byte-identical: {same}")
        print(f"load after: {loadavg()}")


if __name__ == "__main__":
    main()
