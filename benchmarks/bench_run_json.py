"""run.json's cost a frame in a long run (issue 31, goal 4: I/O off the critical path at any length).

``simulate`` and ``import`` save run.json after every frame, so that a run killed anywhere resumes from
what it lists. Before, each save dumped the whole frame table anew, and the background writer first
took a deep copy of the record on the simulation's thread: both grow with the frames already in the
run, a quadratic run. Now each frame entry keeps its text until it changes (``RunInfo.dumps``).

For runs of 100, 1000 and 3000 frames (a simulation with foam and a moving body: two files, a
particle count and a pose a frame), printed in ms per frame: the old way (``deepcopy`` on the
simulation's thread, then ``json.dumps(model_dump())`` and the write on the writer's), and the new
(``dumps`` on the simulation's thread, the write on the writer's), measured in the same run, and the
ratio.

Then (``--simulate N``, 0 to skip) a whole ``simulate`` with foam of a small dam break (about 300
particles at r = 2 cm, so that the saves are not hidden behind the solver) over N frames: the median
time a frame in each sixth of the run, flat when nothing grows with the frames before it; with
``--against OTHER/src`` the same run with another checkout's package too, and the ratio of the totals.

    python benchmarks/bench_run_json.py [--frames 100 1000 3000] [--repeat 5] [--simulate 1200] [--against SRC]
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from whitecap.io.atomic import write_text
from whitecap.io.run import RUN_JSON, RunInfo


def _run(frames: int) -> RunInfo:
    info = RunInfo(particle_radius=0.004, rest_density=1000.0, particle_mass=6.4e-5, gravity=[0.0, 0.0, -9.81],
                   domain={"lower": [0.0, 0.0, 0.0], "upper": [1.6, 0.4, 0.8]}, frame_rate=120.0,
                   simulation="f" * 64)
    for i in range(frames):
        _add(info, i)
    return info


def _add(info: RunInfo, i: int) -> None:
    info.set_file(i, "fluid", f"fluid/fluid_{i:05d}.ply", i / 120)
    info.set_file(i, "diffuse", f"diffuse/diffuse_{i:05d}.ply", i / 120)
    info.frame(i).particles = 71_000 + i
    info.set_bodies(i, [{"position": [0.001 * i, 0.0, 0.0], "quaternion": [1.0, 0.0, 0.0, 0.0]}])


def _best(f, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


_SIMULATE = """
import json, sys, tempfile, time
import numpy as np
from whitecap.config import scene_from_dict
from whitecap.pipeline import simulate
from whitecap.sim import driver
n = int(sys.argv[1])
scene = scene_from_dict({
    "name": "long", "seed": 3, "domain": {"lower": [0, 0, 0], "upper": [0.6, 0.2, 0.4]},
    "solver": {"particle_radius": 0.02, "iterations": 2}, "fluid": [{"lower": [0, 0, 0], "upper": [0.2, 0.2, 0.3]}],
    "output": {"frames": n}, "foam": {"enabled": True}})
ends = []
step = driver._save_checkpoint
def stamp(*a, **k):  # called once a frame, after its files and run.json are handed over
    ends.append(time.perf_counter())
    return step(*a, **k)
driver._save_checkpoint = stamp
with tempfile.TemporaryDirectory() as out:
    t0 = time.perf_counter()
    simulate(scene, out=out, show_progress=False)
    total = time.perf_counter() - t0
d = np.diff(ends)
k = max(1, len(d) // 6)
print(json.dumps({"total": total, "blocks": [float(np.median(d[i:i + k])) for i in range(0, k * 6, k)]}))
"""


def _simulate(n: int, src: str | None) -> dict:
    env = dict(os.environ, WHITECAP_PROGRESS="0")
    if src:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [src, os.environ.get("PYTHONPATH")]))
    p = subprocess.run([sys.executable, "-c", _SIMULATE, str(n)], env=env, capture_output=True, text=True, check=True)
    return json.loads(p.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, nargs="+", default=[100, 1000, 3000])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--simulate", type=int, default=1200, help="frames of the whole-run check (0: skip it)")
    ap.add_argument("--against", help="another checkout's src folder, simulated the same way")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / RUN_JSON
        print(f"{'frames':>7}  {'old: copy':>10} {'+ save':>8} {'= ms':>7}   {'new: dumps':>10} {'+ write':>8} "
              f"{'= ms':>7}   ratio   run.json")
        for n in a.frames:
            info = _run(n)
            info.dumps()  # every entry's text kept, as after the frames before this one

            def new_frame() -> None:  # the next frame's entry recorded, as the stages do, and run.json's text made
                _add(info, len(info.frames))
                info.dumps()
                info.frames.pop()  # the same length each repeat

            old_copy = _best(lambda: copy.deepcopy(info), a.repeat)
            old_save = _best(lambda: write_text(path, json.dumps(info.model_dump(), indent=1)), a.repeat)
            new_dumps = _best(new_frame, a.repeat)
            text = info.dumps()
            assert text == json.dumps(info.model_dump(), indent=1)  # the same bytes either way
            new_write = _best(lambda: write_text(path, text), a.repeat)
            old, new = old_copy + old_save, new_dumps + new_write
            print(f"{n:>7}  {old_copy:>10.2f} {old_save:>8.2f} {old:>7.2f}   {new_dumps:>10.2f} {new_write:>8.2f} "
                  f"{new:>7.2f}   {old / new:>5.1f}x  {len(text) / 1e6:.2f} MB")
    if a.simulate:
        runs = [("this checkout", None)] + ([(a.against, a.against)] if a.against else [])
        got = {}
        for name, src in runs:
            got[name] = r = _simulate(a.simulate, src)
            sixths = " ".join(f"{1e3 * b:6.1f}" for b in r["blocks"])
            print(f"simulate, {a.simulate} frames, {name}: {r['total']:.1f} s; "
                  f"ms a frame by sixths of the run: {sixths}")
        if a.against:
            print(f"this checkout takes {got['this checkout']['total'] / got[a.against]['total']:.2f}x the time")


if __name__ == "__main__":
    main()
