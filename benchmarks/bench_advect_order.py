"""An experiment for a GPU lease: does the diffuse particles' advection run faster with the particles in the fluid
grid's cell order?

The live diffuse particles are stored in the order compaction leaves them (survivors in their order, then the new
ones in candidate order), which after a few frames is close to random in space: each advect_diffuse query meets the
fluid's cells at random. On 2 CPU cores, where the fluid's arrays fit in the cache, the same particles sorted by cell
advected in about the same time (2026-11-28, benchmarks/RESULTS.md). On a GPU, a warp whose 32 queries are scattered
shares neither cache lines nor loop lengths, so a sort each frame (a counting sort, as the fluid's grid makes) might
pay for itself there. This benchmark times the kernel both ways, on the live particles of a `whitecap foam` pass
over bench_foam.py's sloshing sequence, at its last frame:

    python benchmarks/bench_advect_order.py [--particles 1000000] [--frames 8] [--arch cuda] [--repeats 5]

It prints the diffuse count, how ordered the stored particles are, each order's best time of ``--repeats`` (the
kernel alone, waited for), their ratio, and checks that both orders move every particle the same way.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_foam import write_sloshing  # noqa: E402


def _time_both(gen, args, dt: float, repeats: int) -> dict:
    """advect_diffuse on copies of the live particles, as stored and sorted by the fluid grid's cell, best of
    ``repeats`` each (each launch from the same copies, waited for)."""
    import taichi as ti

    from whitecap.diffuse import kernels as K
    from whitecap.sim.grid import grid_spec

    p, nd = gen.p, gen._nd
    live = gen._live[gen._cur]
    x, v = live["x"].to_numpy()[:nd], live["v"].to_numpy()[:nd]
    life, kind = live["life"].to_numpy()[:nd], live["kind"].to_numpy()[:nd]
    # the cells of the foam stage's fluid grid (FoamGenerator._fluid_grid's spec), numbered as grid.cell_key numbers
    # them: the order its queries meet the fluid in
    spec = grid_spec(gen.lo, gen.hi, gen.h / 2)
    dims = np.asarray(spec.dims, np.int64)
    cell = np.clip(np.floor((x - np.asarray(spec.lower)) / spec.cell), 0, dims - 1).astype(np.int64)
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")

    def run(rows: np.ndarray) -> tuple[float, list]:
        ax, av = ti.Vector.ndarray(3, ti.f32, nd), ti.Vector.ndarray(3, ti.f32, nd)
        al, keep, kd = ti.ndarray(ti.f32, nd), ti.ndarray(ti.i32, nd), ti.ndarray(ti.i32, nd)
        best = np.inf
        for _ in range(repeats):
            ax.from_numpy(np.ascontiguousarray(x[rows]))
            av.from_numpy(np.ascontiguousarray(v[rows]))
            al.from_numpy(np.ascontiguousarray(life[rows]))
            kd.from_numpy(np.ascontiguousarray(kind[rows]))
            ti.sync()
            t = time.perf_counter()
            K.advect_diffuse(nd, ax, av, al, *args, gen.g, p.buoyancy, p.drag, dt, p.spray_below, p.bubble_above,
                             ti.math.vec3(*gen.lo), ti.math.vec3(*gen.hi), keep, kd, 0, 0)
            ti.sync()
            best = min(best, time.perf_counter() - t)
        return best, [a.to_numpy()[:nd] for a in (ax, av, keep, kd)]

    stored, out_s = run(np.arange(nd))
    sorted_, out_o = run(order)
    inverse = np.empty(nd, np.int64)
    inverse[order] = np.arange(nd)
    same = all(np.array_equal(a, b[inverse]) for a, b in zip(out_s, out_o))
    return {"n": nd, "ascending": float(np.mean(np.diff(key) >= 0)), "jump": float(np.median(np.abs(np.diff(key)))),
            "stored": stored, "sorted": sorted_, "same": same}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--particles", type=int, default=1_000_000)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    os.environ.setdefault("WHITECAP_PROGRESS", "0")
    from whitecap.config import Foam
    from whitecap.diffuse import generator as G, postprocess, resolve
    from whitecap.io.run import flow_domain, sequence_bounds

    got: dict = {}
    advect = G.FoamGenerator._advect

    def measured(self, args, dt, index):  # at the last frame, before its own advection
        if index == a.frames - 1 and self._nd:
            got.update(_time_both(self, args, dt, a.repeats))
        return advect(self, args, dt, index)

    G.FoamGenerator._advect = measured
    with tempfile.TemporaryDirectory() as tmp:
        r, files = write_sloshing(Path(tmp) / "fluid", a.particles, a.frames)
        box = flow_domain(sequence_bounds(files), r)
        with contextlib.redirect_stderr(io.StringIO()):  # (the pass's own lines: each frame's counts)
            postprocess(Path(tmp) / "fluid", out=Path(tmp) / "foam", params=resolve(Foam(preset="auto")), dt=1 / 30,
                        radius=r, show_progress=False, arch=a.arch, domain=(box["lower"], box["upper"]))
    if not got:
        print("no diffuse particles at the last frame: nothing to time")
        return
    print(f"{got['n']:,} diffuse particles at frame {a.frames - 1}; stored order: {100 * got['ascending']:.0f} % of "
          f"neighbours ascending in cell, median jump {got['jump']:.0f} cells")
    print(f"advect_diffuse, best of {a.repeats}: as stored {1e3 * got['stored']:.2f} ms, sorted by cell "
          f"{1e3 * got['sorted']:.2f} ms: sorted {got['stored'] / got['sorted']:.2f}x as fast "
          f"({'the same' if got['same'] else 'DIFFERENT'} particles moved the same way in both orders)")


if __name__ == "__main__":
    main()
