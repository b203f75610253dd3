"""Render benchmark: Cycles on the CPU.

A synthetic run with a ~100k-triangle fluid mesh and 20k diffuse particles
per frame, on the default stage: a glass tank around the domain (the run's
walls are solid), Blender's physical sky with its sun, the tiled ground.
Prints seconds per preview frame (320×240, [render].preview_samples), scene update
included, and the time of one final-quality frame (1920×1080,
[render].samples). Target: preview ≤ 3 s per frame. Prints the load
average too: the figures are only comparable on a quiet machine.

    python benchmarks/bench_render.py [--frames 4] [--final]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

TARGET_PREVIEW_S = 3.0


def make_run(root: Path, frames: int) -> Path:
    import trimesh
    from plyfile import PlyData, PlyElement

    from whitecap import io
    from whitecap.io.run import RunInfo

    run = root / "run"
    info = RunInfo(particle_radius=0.01, rest_density=1000.0, particle_mass=0.008, gravity=[0, 0, -9.81],
                   domain={"lower": [0, 0, 0], "upper": [1.0, 0.6, 0.6]}, frame_rate=30.0)
    base = trimesh.creation.uv_sphere(radius=0.2, count=[160, 160])
    rng = np.random.default_rng(0)
    for i in range(frames):
        m = base.copy()
        m.apply_translation([0.3 + 0.05 * i, 0.3, 0.2])
        names = ("x", "y", "z", "nx", "ny", "nz", "vx", "vy", "vz")
        v = np.empty(len(m.vertices), dtype=[(k, "f4") for k in names])
        vals = np.hstack([m.vertices, m.vertex_normals, np.tile([1.5, 0, 0], (len(m.vertices), 1))])
        for k, a in zip(names, vals.T):
            v[k] = a
        f = np.empty(len(m.faces), dtype=[("vertex_indices", "i4", (3,))])
        f["vertex_indices"] = m.faces
        (run / "mesh").mkdir(parents=True, exist_ok=True)
        ply = PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(f, "face")])
        ply.write(str(run / f"mesh/fluid_{i:05d}.ply"))
        info.set_file(i, "mesh", f"mesh/fluid_{i:05d}.ply")
        n = 20000
        d = io.ParticleFrame(rng.random((n, 3)) * [0.8, 0.5, 0.4] + [0.1, 0.05, 0.05], np.zeros((n, 3)),
                             np.arange(n) + n * i, arrays={"type": rng.integers(0, 3, n).astype(np.uint8),
                                                            "lifetime": np.ones(n, np.float32),
                                                            "radius": np.full(n, 0.005, np.float32)})
        io.write(run / f"diffuse/diffuse_{i:05d}.ply", d)
        info.set_file(i, "diffuse", f"diffuse/diffuse_{i:05d}.ply")
    info.save(run)
    return run, len(base.faces)


def child_cpu() -> float:
    """CPU seconds used so far by finished child processes (the render workers)."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--final", action="store_true", help="also time one final-quality frame")
    a = ap.parse_args()
    from whitecap.render import RenderJob, render_run

    with tempfile.TemporaryDirectory() as tmp:
        run, tris = make_run(Path(tmp), a.frames)
        t0 = time.perf_counter()
        render_run(run, RenderJob(quality="preview", frames="0:1", movie=False, show_progress=False))
        first = time.perf_counter() - t0  # process start + scene build + one frame
        t0, c0 = time.perf_counter(), child_cpu()
        render_run(run, RenderJob(quality="preview", frames=f"1:{a.frames}", movie=False, show_progress=False))
        rest, cpu = time.perf_counter() - t0, child_cpu() - c0
        per = rest / (a.frames - 1)
        res = {"triangles": tris, "diffuse": 20000, "preview_first_s": first, "preview_s_per_frame": per,
               "preview_cpu_s_per_frame": cpu / (a.frames - 1)}
        from whitecap.io.run import RunInfo
        from whitecap.render.driver import render_settings
        from whitecap.render.stage import container_kind

        cfg = render_settings(run)
        stage = f"container {container_kind(cfg, RunInfo.load(run))}, " + (
            f"environment {cfg.environment}" if cfg.environment else f"sky {cfg.sky_type}")
        load = os.getloadavg()
        res.update(stage=stage, load=load, cores=os.cpu_count())
        print(f"fluid mesh {tris} triangles, 20000 diffuse particles, Cycles CPU, {stage}")
        print(f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f} on {os.cpu_count()} cores")
        print(f"preview 320x240 {cfg.preview_samples} spp: {per:.2f} s/frame over {a.frames - 1} frames "
              f"(incl. one scene build per call: {first:.2f} s for the first) — target {TARGET_PREVIEW_S} s: "
              f"{per / TARGET_PREVIEW_S:.2f}x of budget")
        print(f"  CPU time {cpu / (a.frames - 1):.2f} s per frame (worker start and scene build included), "
              f"{cpu / (a.frames - 1) / os.cpu_count():.2f} s per frame spread over {os.cpu_count()} idle cores")
        if a.final:
            t0 = time.perf_counter()
            render_run(run, RenderJob(quality="final", frames="0:1", force=True, movie=False, show_progress=False))
            res["final_s"] = time.perf_counter() - t0
            print(f"final 1920x1080: {res['final_s']:.1f} s for one frame (scene build included)")
        print(json.dumps(res))


if __name__ == "__main__":
    main()
