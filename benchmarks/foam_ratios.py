"""Peak diffuse-to-fluid ratios, per type, with the default foam settings.

For each example scene (scenes/*.toml) and the DualSPHysics dam break, runs the
diffuse stage over the fluid frames twice: as post-processing (`whitecap foam`,
'auto' from frames sampled across the whole run) and as the simulation does it
(a running estimate, `look_ahead=False`; the same bytes `simulate` writes). Prints
the peak number of spray, foam and bubble particles per fluid particle (each at
its own peak) and of all three together.

    python benchmarks/foam_ratios.py [--runs out] [--dsph ../shared/data/dualsphysics_dambreak]

A scene's fluid frames are taken from RUNS/<name> when that holds a run of it,
else simulated there first with `whitecap simulate --no-foam` (minutes per scene).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def peaks(out: Path, n_fluid: np.ndarray) -> list[float]:
    rows = np.loadtxt(out / "diffuse" / "counts.csv", delimiter=",", skiprows=1, ndmin=2)
    r = rows[:, 2:] / n_fluid[:, None]
    return [*r.max(0).tolist(), float(r.sum(1).max())]


def fluid_counts(run: Path) -> np.ndarray:
    from whitecap import io
    from whitecap.io.run import RunInfo

    info = RunInfo.load(run)
    return np.array([len(io.read(run / rel)) for _, rel in info.files("fluid")], np.float64)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", default="out", help="folder holding (or to hold) a run per scene")
    ap.add_argument("--dsph", default=str(ROOT.parent / "shared/data/dualsphysics_dambreak"))
    ap.add_argument("--scenes", nargs="*", default=None, help="scene files (default scenes/*.toml)")
    a = ap.parse_args()
    os.environ.setdefault("WHITECAP_PROGRESS", "0")
    from whitecap.config import load_scene
    from whitecap.diffuse import postprocess, resolve
    from whitecap.io.run import RunInfo
    from whitecap.pipeline import simulate

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in a.scenes or sorted((ROOT / "scenes").glob("*.toml")):
            sc = load_scene(path)
            run = Path(a.runs) / sc.name
            if not (run / "run.json").exists() or len(RunInfo.load(run).files("fluid")) < sc.output.frames + 1:
                simulate(sc, out=run, foam=False, force=True, show_progress=False)
            n = fluid_counts(run)
            params = resolve(sc.foam)
            for mode, ahead in (("post", True), ("sim", False)):
                out = Path(tmp) / f"{sc.name}_{mode}"
                postprocess(run, out=out, params=params, look_ahead=ahead, show_progress=False)
                rows.append((sc.name, mode, int(n.max()), *peaks(out, n)))
        dsph = Path(a.dsph)
        if dsph.is_dir():
            out = Path(tmp) / "dsph"
            postprocess(str(dsph / "PartFluid_*.vtk"), out=out, show_progress=False)
            n = fluid_counts(out)
            rows.append(("DualSPHysics dam break", "post", int(n.max()), *peaks(out, n)))
    print(f"\n{'input':<24} {'mode':<5} {'fluid':>7}  {'spray':>6} {'foam':>6} {'bubbles':>7}  {'all':>5}")
    for name, mode, nf, s, f, b, t in rows:
        print(f"{name:<24} {mode:<5} {nf:>7,}  {s:>6.2f} {f:>6.2f} {b:>7.2f}  {t:>5.2f}")
    print("\npeak diffuse particles per fluid particle, each type at its own peak; 'all' at the frame of "
          "the highest total; post = whitecap foam (whole run), sim = inside simulate (running estimate)")


if __name__ == "__main__":
    main()
