"""Memory per fluid particle with foam on and off (issue 31, goal 2): ``simulate`` of the dam break of
bench_simulate_foam.py (r = 4 mm by default), each configuration in its own process.

Prints, per configuration: the fluid particle count; resident memory (VmRSS) after the first frame
and at the end, and the peak (VmHWM), in bytes per fluid particle; the growth of VmRSS from the
middle frame to the end per frame; with foam on, the bytes of the Taichi arrays the foam stage keeps
(FoamGenerator.nbytes) per fluid particle; on CUDA, the GPU memory in use (nvidia-smi) at the same points.

    python benchmarks/bench_memory.py [--radius 0.004 0.006] [--frames 30] [--arch cpu|cuda]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile


def _rss() -> tuple[int, int]:
    got = {}
    with open("/proc/self/status") as f:
        for line in f:
            k, _, v = line.partition(":")
            if k in ("VmRSS", "VmHWM"):
                got[k] = int(v.split()[0]) * 1024
    return got["VmRSS"], got["VmHWM"]


def _gpu_used() -> int | None:
    """GPU memory in use on the first GPU [bytes] (nvidia-smi), None where there is none."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
                             capture_output=True, text=True, timeout=20).stdout
        return int(out.split()[0]) * 2**20
    except (OSError, ValueError, IndexError, subprocess.SubprocessError):
        return None


def run_one(radius: float, frames: int, arch: str, foam: bool) -> dict:
    sys.path.insert(0, os.path.dirname(__file__))
    from bench_simulate_foam import _scene

    from whitecap.diffuse import generator as G
    from whitecap.pipeline import simulate
    from whitecap.sim import driver as D

    samples = []  # per frame: (rss, gpu)
    gens, solvers = [], []
    cuda = arch == "cuda"
    init, build = G.FoamGenerator.__init__, D.build_solver

    def kept_init(self, *a, **kw):
        init(self, *a, **kw)
        gens.append(self)

    def kept_build(*a, **kw):  # samples after each frame's solver steps (and the last frame's foam, on the next)
        solver = build(*a, **kw)
        solvers.append(solver)
        advance = solver.advance_frame

        def advance_frame(*b, **kb):
            out = advance(*b, **kb)
            samples.append((_rss()[0], _gpu_used() if cuda else None))
            return out

        solver.advance_frame = advance_frame
        return solver

    G.FoamGenerator.__init__ = kept_init
    D.build_solver = kept_build
    with tempfile.TemporaryDirectory() as tmp:
        simulate(_scene(radius, frames), out=tmp + "/run", frames=frames, arch=arch, foam=foam,
                        show_progress=False)
    rss, hwm = _rss()
    n = int(solvers[0].n) if solvers else 0
    return {"n": n, "samples": samples, "rss": rss, "hwm": hwm, "gpu": _gpu_used() if cuda else None,
            "foam_nbytes": gens[0].nbytes() if gens else None, "frames": frames}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--radius", type=float, nargs="+", default=[0.004])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--one", nargs=2, help=argparse.SUPPRESS)  # radius, on|off
    a = ap.parse_args()
    os.environ.setdefault("WHITECAP_PROGRESS", "0")
    if a.one:
        print("RESULT " + json.dumps(run_one(float(a.one[0]), a.frames, a.arch, a.one[1] == "on")))
        return
    for r in a.radius:
        res = {}
        for mode in ("off", "on"):
            cmd = [sys.executable, __file__, "--frames", str(a.frames), "--arch", a.arch, "--one", str(r), mode]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            res[mode] = json.loads([ln for ln in out.splitlines() if ln.startswith("RESULT ")][-1][7:])
        n = max(res["on"]["n"], res["off"]["n"], 1)
        print(f"== r = {1e3 * r:g} mm, {n:,} fluid particles, {a.frames} frames, arch {a.arch}")
        for mode in ("off", "on"):
            x = res[mode]
            s = x["samples"]
            line = f"  foam {mode:3s}: VmRSS {x['rss'] / n:7.0f} B/particle at the end, peak {x['hwm'] / n:7.0f}"
            if len(s) >= 4:
                mid = len(s) // 2
                growth = (s[-1][0] - s[mid][0]) / (len(s) - 1 - mid)
                line += (f"; after frame 1 {s[0][0] / n:7.0f}; growth from frame {mid + 1} to {len(s)}: "
                         f"{growth / 1e3:+.1f} kB a frame ({growth / n:+.2f} B/particle a frame)")
            print(line)
            if x["foam_nbytes"] is not None:
                print(f"    foam stage's Taichi arrays: {x['foam_nbytes'] / n:.0f} B/particle "
                      f"({x['foam_nbytes'] / 2**20:.1f} MiB)")
            if x["gpu"] is not None:
                g = [t[1] for t in s if t[1] is not None]
                grow = f", from {g[0] / 2**20:.0f} MiB after frame 1 to {g[-1] / 2**20:.0f} MiB" if g else ""
                print(f"    GPU memory in use (nvidia-smi, the whole GPU): {x['gpu'] / n:.0f} B/particle{grow}")
                if len(g) >= 4:  # flat once the largest frame has been seen: where it last rose, and by how much after
                    mid = len(g) // 2
                    rose = max((k for k in range(1, len(g)) if g[k] > g[k - 1]), default=0)
                    print(f"    GPU memory from frame {mid + 1} to {len(g)}: "
                          f"{(g[-1] - g[mid]) / 2**20 / (len(g) - 1 - mid):+.1f} MiB a frame; last rose at frame "
                          f"{rose + 1} (by {(g[rose] - g[rose - 1]) / 2**20 if rose else 0:.0f} MiB)")
        d = res["on"]["rss"] - res["off"]["rss"]
        print(f"  foam on - off: {d / n:+.0f} B/particle of VmRSS")


if __name__ == "__main__":
    main()
