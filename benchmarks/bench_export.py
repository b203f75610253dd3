"""Benchmark of `whitecap export --to usd` and `--to abc` (issue 19).

    PYTHONPATH=src python benchmarks/bench_export.py [--particles 100000] [--frames 6] [--diffuse 20000]

Builds a synthetic run (the wavy pool of ``bench_mesh.py``: about 100k fluid
particles per frame, meshed with ``whitecap mesh``; ``--diffuse`` diffuse
particles of random type per frame; one static obstacle) in a temporary
directory, then prints the export time per frame:

  1. USD, first export (every frame layer written),
  2. USD, rerun with nothing changed (frame layers reused; the stage rewritten),
  3. Alembic (USD into a temporary directory, Blender's import and Alembic
     export in a child process; its start, about 1-2 s, is in the figure),

with the surface size, the output size per frame, and the machine load
(/proc/loadavg) before and after. A few minutes on 2 cores, most of it meshing.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_mesh import R, loadavg, synthetic_frame  # noqa: E402

from whitecap import io as wio  # noqa: E402
from whitecap.io.frame import ParticleFrame  # noqa: E402
from whitecap.io.mesh import read_mesh  # noqa: E402
from whitecap.io.run import RunInfo, frame_name  # noqa: E402
from whitecap.pipeline import export, mesh  # noqa: E402

FPS = 30.0


def make_run(run: Path, particles: int, frames: int, diffuse: int) -> None:
    """A run directory following the contract: fluid and diffuse PLYs recorded in run.json, then meshed."""
    import trimesh

    rng = np.random.default_rng(0)
    first = synthetic_frame(particles, 0)
    lo, hi = first.positions.min(0) - 0.05, first.positions.max(0) + 0.35
    info = RunInfo(particle_radius=R, rest_density=1000.0, particle_mass=1000.0 * (2 * R) ** 3,
                   gravity=[0.0, 0.0, -9.81], domain={"lower": lo.tolist(), "upper": hi.tolist()}, frame_rate=FPS,
                   simulation="bench-export", extra={"scene_dir": str(run), "source": "benchmark"})
    run.mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=4, radius=0.05).export(run / "ball.obj")
    info.obstacles = [{"mesh": "ball.obj", "translate": ((lo + hi) / 2).tolist()}]
    for k in range(frames):
        f = synthetic_frame(particles, k)
        f.ids = np.arange(len(f), dtype=np.uint32)
        wio.write(run / frame_name("fluid", k), f)
        info.set_file(k, "fluid", frame_name("fluid", k), time=k / FPS)
        pick = rng.integers(0, len(f), diffuse)
        d = ParticleFrame(positions=f.positions[pick] + rng.normal(0, R, (diffuse, 3)),
                          velocities=rng.normal(0, 1, (diffuse, 3)), ids=np.arange(diffuse, dtype=np.uint32) + 10**6,
                          arrays={"type": rng.integers(0, 3, diffuse).astype(np.uint8),
                                  "lifetime": rng.uniform(0, 2, diffuse).astype(np.float32),
                                  "radius": np.full(diffuse, R / 2, np.float32)})
        wio.write(run / frame_name("diffuse", k), d)
        info.set_file(k, "diffuse", frame_name("diffuse", k))
    info.save(run)
    mesh(run, show_progress=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=100_000)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--diffuse", type=int, default=20_000)
    ap.add_argument("--keep", help="build the run in this directory (reused when it exists) instead of a temporary one")
    a = ap.parse_args()
    os.environ.setdefault("WHITECAP_PROGRESS", "0")
    print(f"load before: {loadavg()}")
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(a.keep) if a.keep else Path(tmp) / "run"
        t0 = time.perf_counter()
        if not (run / "run.json").is_file():
            make_run(run, a.particles, a.frames, a.diffuse)
        m = read_mesh(run / "mesh/fluid_00000.ply")
        n_fluid = len(wio.read(run / "fluid/fluid_00000.ply"))
        print(f"run: {a.frames} frames of {n_fluid} fluid particles, surface {len(m.vertices)} vertices / "
              f"{len(m.faces)} triangles, {a.diffuse} diffuse particles (built and meshed in "
              f"{time.perf_counter() - t0:.1f} s)")
        import pxr.Usd  # noqa: F401  (imports outside the timings: a per-frame figure, not a start-up one)
        import trimesh  # noqa: F401

        for label, to in (("USD, first export", "usd"), ("USD, rerun (frames reused)", "usd"), ("Alembic", "abc")):
            t = time.perf_counter()
            path = export(run, to=to, show_progress=False)[to]
            dt = time.perf_counter() - t
            size = sum(p.stat().st_size for p in path.parent.rglob("*") if p.is_file())
            print(f"{label:28s} {dt:7.2f} s total  {dt / a.frames:6.3f} s/frame  "
                  f"{size / a.frames / 2**20:6.1f} MiB/frame  (load {loadavg()})")
    print(f"load after: {loadavg()}")


if __name__ == "__main__":
    main()
