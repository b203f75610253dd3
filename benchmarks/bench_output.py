"""Output and checkpoint share of ``simulate`` (issue 31, goal 4), with the background writer on and off.

The H = 2a dam break of bench_simulate_foam.py (bench_solver's column at 120 fps), foam off unless
``--foam``, at a few particle radii. Per size, each configuration runs in its own process (one Taichi
runtime per process), after a one-frame warm-up in that process so that kernel compilation is not
counted as output:

- ``inline, every frame``: frames, run.json and checkpoints written in the loop, a checkpoint every
  frame (whitecap before the background writer);
- ``writer, every frame``: the background writer, a checkpoint every frame;
- ``writer, interval N``: the background writer with ``output.checkpoint_interval``'s default
  (0: automatic, by the arch; see sim/driver.py ``AUTO_CHECKPOINT_INTERVAL``) or ``--interval``.

Printed per configuration, in ms a frame and as a share of the run's wall time: ``step`` (the
solver), ``output`` (gathering a frame and handing it over; all of the writing when inline),
``output.wait`` (blocked on the writer: a full queue, the final flush; inside ``output`` and ``checkpoint``),
``checkpoint`` (gathering
the state; writing it too when inline) and, overlapped in the writer thread, ``writer.*``. Then the
ratios against the inline run of the same size, measured in the same invocation.

    python benchmarks/bench_output.py [--radius 0.006 0.004] [--frames 20] [--arch cpu] [--foam]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGET_CHECKPOINT_SHARE = 0.05


def _scene(radius: float, frames: int, interval: int | None, foam: bool):
    sys.path.insert(0, os.path.dirname(__file__))
    from bench_simulate_foam import _scene as dam_break

    from whitecap.config import scene_from_dict

    sc = dam_break(radius, frames)
    d = json.loads(sc.model_dump_json())
    d.pop("base_dir", None)
    if interval is not None:
        d["output"]["checkpoint_interval"] = interval
    d["foam"]["enabled"] = foam
    return scene_from_dict(d)


def run_one(radius: float, frames: int, arch: str, writer: bool, interval: int | None, foam: bool) -> dict:
    from whitecap import timing
    from whitecap.pipeline import simulate
    from whitecap.sim import driver

    driver.BACKGROUND_WRITER = writer
    with tempfile.TemporaryDirectory() as tmp:
        simulate(_scene(radius, 1, interval, foam), out=tmp + "/warm", arch=arch, foam=foam, show_progress=False)
        sc = _scene(radius, frames, interval, foam)
        t0 = time.perf_counter()
        info = simulate(sc, out=tmp + "/run", arch=arch, foam=foam, show_progress=False)
        wall = time.perf_counter() - t0
        from whitecap.io import read

        n = len(read(Path(tmp, "run", info.frames[0].files["fluid"])))
        size = sum(p.stat().st_size for p in Path(tmp, "run").rglob("*") if p.is_file())
    return {"timers": {k: v[0] for k, v in timing.TIMERS.items()}, "wall": wall, "n": n, "bytes": size,
            "interval": driver.checkpoint_interval(sc)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--radius", type=float, nargs="+", default=[0.006, 0.004])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--foam", action="store_true", help="with the foam stage (its files are written in the loop)")
    ap.add_argument("--interval", type=int, help="checkpoint interval of the third run (default: the scene default)")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    a = ap.parse_args()
    os.environ.setdefault("WHITECAP_PROGRESS", "0")
    if a.one:
        radius, writer, interval = a.one.split(",")
        r = run_one(float(radius), a.frames, a.arch, writer == "on", int(interval) if interval else None, a.foam)
        print("RESULT " + json.dumps(r))
        return
    configs = [("inline, every frame", "off", "1"), ("writer, every frame", "on", "1"),
               ("writer, interval {}", "on", str(a.interval or ""))]
    f = a.frames
    for radius in a.radius:
        res = {}
        for label, writer, interval in configs:
            cmd = [sys.executable, __file__, "--frames", str(f), "--arch", a.arch, "--one",
                   f"{radius},{writer},{interval}"] + (["--foam"] if a.foam else [])
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            r = json.loads([ln for ln in out.splitlines() if ln.startswith("RESULT ")][-1][7:])
            res[label.format(r["interval"])] = r
        first = next(iter(res.values()))
        print(f"== r = {1e3 * radius:g} mm: {first['n']:,} particles, {f} frames, arch {a.arch}, "
              f"foam {'on' if a.foam else 'off'}, {first['bytes'] / 1e6:.0f} MB written")
        for label, r in res.items():
            t, wall = r["timers"], r["wall"]
            ck = t.get("checkpoint", 0.0)
            crit = t.get("output", 0.0)  # its waits (output.wait) included
            print(f"  {label}: {wall:.2f} s ({1e3 * wall / f:.0f} ms a frame); checkpoint share "
                  f"{100 * ck / wall:.1f}% (target < {100 * TARGET_CHECKPOINT_SHARE:.0f}%), output share "
                  f"{100 * crit / wall:.1f}%")
            for k in ("step", "diffuse", "output", "output.wait", "checkpoint"):
                if k in t:
                    print(f"    {k:20s} {1e3 * t[k] / f:8.1f} ms/frame {100 * t[k] / wall:5.1f}%")
            for k in sorted(t):
                if k.startswith("writer."):
                    print(f"    {k:20s} {1e3 * t[k] / f:8.1f} ms/frame (background)")
        base = first
        for label, r in list(res.items())[1:]:
            bt, t = base["timers"], r["timers"]
            bo = bt.get("output", 0) + bt.get("checkpoint", 0)
            o = t.get("output", 0) + t.get("checkpoint", 0)
            print(f"  {label} / inline: output+checkpoint on the loop {o / bo:.2f}x, "
                  f"checkpoint {t.get('checkpoint', 0) / max(bt.get('checkpoint', 0), 1e-9):.2f}x, "
                  f"wall {r['wall'] / base['wall']:.2f}x")


if __name__ == "__main__":
    main()
