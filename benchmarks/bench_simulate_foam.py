"""Share of the diffuse phase in ``simulate`` (issue 31): the H = 2a dam break of
bench_solver.py's ``scene_for`` (COLUMN_HEIGHT, here at r = 4 mm), 30 frames at 120 fps,
with foam on and off, ``simulate(..., profile=True)``.

Prints the wall time of each top-level phase (step, diffuse, output, checkpoint) per frame and
its share of the run, the foam phase's own split (potentials, advect, generate, compact),
and the ratio to issue 31's reference figures on 2 CPU cores (diffuse 356 ms a frame,
37% of the run, against 578 ms a frame of solver). Target: the diffuse phase at most 15%.

    python benchmarks/bench_simulate_foam.py [--radius 0.004] [--frames 30] [--arch cpu] [--foam-only]
        [--against OLD/src]

Each configuration runs in its own process (one Taichi runtime per process). ``--against`` runs the
foam-on case once more with another checkout's package (e.g. ``git archive 80c2fce | tar -x -C OLD``)
and prints the diffuse share of both, measured in the same run, and their ratio. ``--pin`` runs it once
more with the read-back's host arrays page-locked or not, whichever sim/runtime.py PIN_READBACK does not
(on since 2026-11-28), to tell what the diffuse particles' copy into pageable memory costs the loop;
``--arrays`` once more with the fluid and
diffuse frames read back array by array and packed by the writer, as before they were made as their
files' records (c268cca, 68bb59a). ``--repeat N`` runs the whole list N times, one configuration after the
other, and prints each round's foam-on / foam-off ratios and their medians (a GPU's figures drift from run to
run). ``--kernels`` runs foam on and off once more each with Taichi's kernel profiler on, and prints each kernel's
device time a frame: where foam-on's frames go on the device, which the host's timers (waits included) cannot say.
Where the run has a background writer (on a GPU), each configuration also lists the loop's waits for it over 1 ms,
by what was being handed over (a checkpoint that holds the writer up shows as the next frame's waits; the run's last
files as the flush).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import kernel_profile  # noqa: E402

REFERENCE_DIFFUSE_MS = 356.0  # issue 31, 2 CPU cores, foam phase per frame
REFERENCE_SOLVER_MS = 578.0  # issue 31, solver per frame
REFERENCE_SHARE = 0.37
TARGET_SHARE = 0.15
PHASE = "diffuse"  # the foam stage's timer in sim/driver.py (its hook name)
WARM_FRAMES = 24  # of the warm-up run: long enough for the dam break to splash (the advection's kernels compile then)


def _scene(radius: float, frames: int):
    sys.path.insert(0, os.path.dirname(__file__))
    from bench_solver import COLUMN_HEIGHT

    from whitecap.config import scene_from_dict

    a = COLUMN_HEIGHT / 2  # scene_for's column: a wide, a/2 deep, 2a tall, in a 4a × a/2 × 2.5a tank
    return scene_from_dict(
        {
            "domain": {"upper": [4 * a, a / 2, 2.5 * a]},
            "solver": {"particle_radius": radius, "iterations": 4, "frame_rate": 120},
            "fluid": [{"lower": [0, 0, 0], "upper": [a, a / 2, 2 * a]}],
            "output": {"frames": frames},
        }
    )


def run_one(radius: float, frames: int, arch: str, foam: bool, other_pin: bool = False, arrays: bool = False,
            kernels: bool = False) -> dict:
    from whitecap import timing
    from whitecap.pipeline import simulate
    from whitecap.sim import runtime

    if other_pin:
        runtime.PIN_READBACK = not runtime.PIN_READBACK
    if kernels:  # Taichi's kernel profiler, the solver's phases kernel by kernel (not as graphs)
        kernel_profile.enable()
    if arrays:  # every frame read back array by array and packed by the writer, as before c268cca
        from whitecap.sim import records

        records.WORDS_MAX = 0

    waits = _record_waits()
    sc = _scene(radius, frames)
    with tempfile.TemporaryDirectory() as tmp:
        # Warm-up: the same run at twice the radius (an eighth of the particles, the same kernels), so that the
        # timed run compiles nothing. Without it, the first configuration on a machine paid Taichi's compilation
        # (the offline cache empty): on an H100, 1.7 s a frame over a 6-frame run against 0.34 warm.
        warm = min(frames, WARM_FRAMES)
        simulate(_scene(2 * radius, warm), out=tmp + "/warm", frames=warm, arch=arch, foam=foam, show_progress=False)
        timing.reset()
        waits.clear()  # (the warm-up's)
        if kernels:
            kernel_profile.clear()
        t0 = time.perf_counter()
        info = simulate(sc, out=tmp + "/run", frames=frames, arch=arch, foam=foam, profile=True, show_progress=False)
        wall = time.perf_counter() - t0
        n = int(info.extra.get("n_particles", 0) or 0) if hasattr(info, "extra") else 0
    t = {k: v[0] for k, v in timing.TIMERS.items()}
    out = {"timers": t, "n": n, "wall": wall, "waits": [w for w in waits if w[1] >= WAIT_SHOWN]}
    if kernels:
        out["kernel_ms"], out["kernels"] = kernel_profile.times()
    return out


WAIT_SHOWN = 1e-3  # [s] the loop's waits for the background writer listed one by one (shorter ones: handing over)


def _record_waits() -> list:
    """[(what was being handed over, or 'flush'; seconds)] for each of the timed run's calls into the background
    writer (io.writer.FrameWriter; on a GPU), appended as they return: where ``output.wait`` goes (a checkpoint
    that holds the writer up shows as the waits of the frame after it; the run's last files as the flush)."""
    from whitecap.io import writer as W

    waits: list = []
    submit, flush = W.FrameWriter.submit, W.FrameWriter.flush

    def timed_submit(self, job, label="output", lane=None):
        t0 = time.perf_counter()
        try:
            return submit(self, job, label, lane)
        finally:
            waits.append((label, time.perf_counter() - t0))

    def timed_flush(self):
        t0 = time.perf_counter()
        try:
            return flush(self)
        finally:
            waits.append(("flush", time.perf_counter() - t0))

    W.FrameWriter.submit, W.FrameWriter.flush = timed_submit, timed_flush
    return waits


def _say_waits(waits: list, frames: int) -> None:
    """One line on the loop's waits for the writer (_record_waits): how many, by what was handed over, the longest."""
    if not waits:
        return
    by: dict = {}
    for label, sec in waits:
        by[label] = by.get(label, 0.0) + sec
    longest = sorted(waits, key=lambda w: -w[1])[:5]
    print(f"    the loop's waits for the writer over {1e3 * WAIT_SHOWN:.0f} ms: {len(waits)}, "
          f"{1e3 * sum(by.values()) / frames:.1f} ms a frame; by what was handed over "
          + ", ".join(f"{k} {1e3 * v:.0f}" for k, v in sorted(by.items(), key=lambda kv: -kv[1]))
          + " ms; longest " + ", ".join(f"{1e3 * s:.0f} ({k})" for k, s in longest) + " ms")


def _top(t: dict) -> dict:
    """The simulation loop's top-level phases (not the nested ``x.y``, nor the writer thread's)."""
    from whitecap.timing import top_level

    return {k: t[k] for k in top_level(t)}


def _loop(t: dict) -> float:
    """The simulation loop's time: its top-level phases' sum (a phase's waits for the writer, output.wait, inside
    it)."""
    return sum(_top(t).values())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--radius", type=float, default=0.004)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--foam-only", action="store_true", help="skip the run with foam off")
    ap.add_argument("--against", help="another checkout's src folder: its foam-on run, for the before/after ratio")
    ap.add_argument("--pin", action="store_true", help="one more foam-on run, the read-back's host arrays pinned "
                    "where sim/runtime.py PIN_READBACK leaves them pageable, and the other way round")
    ap.add_argument("--arrays", action="store_true", help="one more foam-on run, the fluid and diffuse frames read "
                    "back array by array and packed by the writer (not made as their files' records on the device)")
    ap.add_argument("--repeat", type=int, default=1, help="run the list this many times, one after the other")
    ap.add_argument("--kernels", action="store_true", help="foam on and off once more each, with each kernel's "
                    "device time (Taichi's kernel profiler)")
    ap.add_argument("--one", choices=["on", "off"], help=argparse.SUPPRESS)
    ap.add_argument("--other-pin", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--by-array", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--profiled", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    os.environ.setdefault("WHITECAP_PROGRESS", "0")
    if a.one:
        r = run_one(a.radius, a.frames, a.arch, a.one == "on", a.other_pin, a.by_array, a.profiled)
        print("RESULT " + json.dumps(r))
        return
    results = {}
    runs = [(m, m, None, []) for m in (("on",) if a.foam_only else ("on", "off"))]
    if a.against:
        runs.append(("on, against", "on", os.path.abspath(a.against), []))
    if a.pin:
        from whitecap.sim import runtime

        runs.append((f"on, {'pageable' if runtime.PIN_READBACK else 'pinned'} read-back", "on", None, ["--other-pin"]))
    if a.arrays:
        runs.append(("on, read back array by array", "on", None, ["--by-array"]))
    rounds: list[dict] = []
    for name, mode, src, extra in runs * a.repeat + ([("on, kernels", "on", None, ["--profiled"]),
                                                       ("off, kernels", "off", None, ["--profiled"])]
                                                      if a.kernels else []):
        cmd = [
            sys.executable, __file__, "--radius", str(a.radius), "--frames", str(a.frames), "--arch", a.arch,
            "--one", mode, *extra,
        ]
        here = os.path.dirname(os.path.abspath(__file__))
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [src, here, os.environ.get("PYTHONPATH")]))) \
            if src else None
        out = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env).stdout
        results[name] = json.loads([ln for ln in out.splitlines() if ln.startswith("RESULT ")][-1][7:])
        if name == runs[0][0]:
            rounds.append({})
        if "kernels" not in name:
            rounds[-1][name] = _loop(results[name]["timers"])
    for mode, r in results.items():
        if "kernels" in mode:
            continue
        t = r["timers"]
        top = _top(t)
        total = _loop(t)
        f = a.frames
        print(f"== foam {mode}: {total:.2f} s for {f} frames ({1e3 * total / f:.0f} ms a frame; the run's wall time "
              f"{r['wall']:.2f} s)")
        for k, v in sorted(top.items(), key=lambda kv: -kv[1]):
            print(f"  {k:12s} {1e3 * v / f:8.1f} ms/frame {100 * v / total:5.1f}%")
        for k, v in sorted(t.items()):
            if k.startswith(("foam.", "output.", "writer.")):
                print(f"    {k:24s} {1e3 * v / f:8.1f} ms/frame")
        _say_waits(r.get("waits", []), f)
        if PHASE in top:
            share = top[PHASE] / total
            ms = 1e3 * top[PHASE] / f
            print(f"  diffuse share {100 * share:.1f}% (target <= {100 * TARGET_SHARE:.0f}%; issue 31's reference "
                  f"{100 * REFERENCE_SHARE:.0f}%): {ms:.0f} ms a frame, {ms / REFERENCE_DIFFUSE_MS:.2f}x the reference "
                  f"{REFERENCE_DIFFUSE_MS:.0f} ms; solver {1e3 * top.get('step', 0) / f:.0f} ms a frame "
                  f"(reference {REFERENCE_SOLVER_MS:.0f})")
    if "on, against" in results:
        share = {
            k: results[k]["timers"].get(PHASE, 0.0) / _loop(results[k]["timers"])
            for k in ("on", "on, against")
        }
        phase = results["on"]["timers"].get(PHASE, 0.0) / results["on, against"]["timers"].get(PHASE, 1.0)
        print(f"diffuse share {100 * share['on']:.1f}% against {100 * share['on, against']:.1f}% with {a.against} "
              f"({share['on'] / share['on, against']:.2f}x); diffuse phase {phase:.2f}x its time")
    if "off" in results:
        off = _loop(results["off"]["timers"])
        for name in (k for k in results if k.startswith("on") and "against" not in k and "kernels" not in k):
            on = _loop(results[name]["timers"])
            print(f"foam {name} / foam off wall time: {on / off:.2f}x  (frame rate with foam: {off / on:.2f}x of "
                  "without)")
    if len(rounds) > 1 and all("off" in r for r in rounds):
        for name in (k for k in rounds[0] if k.startswith("on") and "against" not in k):
            rates = [r["off"] / r[name] for r in rounds]
            ms = [1e3 * r[name] / a.frames for r in rounds]
            print(f"foam {name}: frame rate with foam over without, round by round "
                  f"{', '.join(f'{x:.2f}' for x in rates)}x, median {statistics.median(rates):.2f}x "
                  f"({', '.join(f'{x:.0f}' for x in ms)} ms a frame)")
        offs = [1e3 * r["off"] / a.frames for r in rounds]
        print(f"foam off: {', '.join(f'{x:.0f}' for x in offs)} ms a frame")
    for mode in ("on, kernels", "off, kernels"):
        if mode in results:
            r = results[mode]
            f = a.frames
            print(f"== foam {mode.split(',')[0]}, each kernel's device time (Taichi's kernel profiler; its timing "
                  f"slows the run): {r['kernel_ms'] / f:.1f} ms a frame on the device in all, the loop "
                  f"{1e3 * _loop(r['timers']) / f:.0f} ms a frame; the solver's phases kernel by kernel, not as "
                  "graphs)")
            kernel_profile.show(r["kernels"], f)
    if "on, kernels" in results and "off, kernels" in results:
        on, off = results["on, kernels"], results["off, kernels"]
        f = a.frames
        dev = (on["kernel_ms"] - off["kernel_ms"]) / f
        loop = 1e3 * (_loop(on["timers"]) - _loop(off["timers"])) / f
        print(f"foam on adds {dev:.1f} ms a frame of kernels on the device and {loop:.1f} ms a frame to the loop: what "
              f"the loop adds beyond its kernels ({loop - dev:.1f} ms) is the host's work and the device left idle")


if __name__ == "__main__":
    main()
