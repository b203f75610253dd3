"""Obstacle cost: the solver benchmark's dam break with and without a 50k-face obstacle.

Same particle count and settings (4 iterations, fixed dt); the obstacle is a
finely tessellated torus (50,000 faces) placed in the path of the wave. Prints ms per step
of both and the overhead (target ≤ 15 %). The SDF is built once (cached).
Then the same for a dynamic body (a 5,120-face sphere of 500 kg/m³, two-way
coupled) against the scene without it (target ≤ 20 %, issue 15).

    python benchmarks/bench_obstacles.py [--particles 120000] [--steps 20]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

TARGET_OVERHEAD = 0.15
TARGET_DYNAMIC_OVERHEAD = 0.20


def one(n: int, steps: int, mesh: str | None, dynamic: bool = False) -> dict:
    sys.path.insert(0, os.path.dirname(__file__))
    from bench_solver import scene_for

    from whitecap.config import Obstacle
    from whitecap.sim.driver import build_solver

    sc = scene_for(n)
    if mesh:
        a = sc.domain.upper[0] / 4
        extra = {"dynamic": True, "density": 500.0} if dynamic else {}
        # in the column's foot: contact from the start
        sc.obstacle = [Obstacle(mesh=mesh, translate=[1.0 * a, a / 4, 0.03], **extra)]
    t0 = time.perf_counter()
    s = build_solver(sc)
    setup = time.perf_counter() - t0
    dt = 1.0 / sc.solver.frame_rate / sc.solver.substeps
    for _ in range(5):
        s.step(dt)
    import taichi as ti

    ti.sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        s.step(dt)
    ti.sync()
    return {"particles": s.n, "ms_per_step": 1e3 * (time.perf_counter() - t0) / steps, "setup_s": setup}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--particles", type=int, default=120_000)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--one", help=argparse.SUPPRESS)
    ap.add_argument("--dynamic", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one is not None:
        print(json.dumps(one(a.particles, a.steps, a.one or None, a.dynamic)))
        return
    import trimesh

    with tempfile.TemporaryDirectory() as tmp:
        os.environ["WHITECAP_CACHE"] = tmp
        m = trimesh.creation.torus(major_radius=0.07, minor_radius=0.03, major_sections=250, minor_sections=100)
        path = os.path.join(tmp, "obstacle.ply")
        m.export(path)
        ball = os.path.join(tmp, "ball.ply")
        trimesh.creation.icosphere(subdivisions=4, radius=0.05).export(ball)  # 5,120 faces
        res = {}
        for key, mesh, dyn in (("without", "", False), ("with", path, False), ("with (cached SDF)", path, False),
                               ("dynamic body", ball, True)):
            out = subprocess.run([sys.executable, __file__, "--particles", str(a.particles), "--steps", str(a.steps),
                                  "--one", mesh] + (["--dynamic"] if dyn else []), capture_output=True, text=True,
                                 env={**os.environ})
            if out.returncode:
                print(out.stderr[-2000:], file=sys.stderr)
                raise SystemExit(1)
            res[key] = json.loads(out.stdout.strip().splitlines()[-1])
    w, o = res["without"], res["with (cached SDF)"]
    print(f"dam break, {w['particles']:,} particles without / {o['particles']:,} with the obstacle "
          f"({len(m.faces):,} faces)")
    for k, r in res.items():
        print(f"  {k:18s} {r['ms_per_step']:8.1f} ms/step   setup {r['setup_s']:.2f} s")
    # Per particle, since the obstacle displaces some of the initial fluid.
    over = (o["ms_per_step"] / o["particles"]) / (w["ms_per_step"] / w["particles"]) - 1
    print(f"obstacle overhead per step and particle: {100 * over:+.1f} % (target ≤ {100 * TARGET_OVERHEAD:.0f} %)")
    d = res["dynamic body"]
    over = (d["ms_per_step"] / d["particles"]) / (w["ms_per_step"] / w["particles"]) - 1
    print(f"dynamic body (5,120 faces) overhead per step and particle: {100 * over:+.1f} % "
          f"(target ≤ {100 * TARGET_DYNAMIC_OVERHEAD:.0f} %)")


if __name__ == "__main__":
    main()
