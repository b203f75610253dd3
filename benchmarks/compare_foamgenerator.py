"""Per-type diffuse counts of `--preset splishsplash` beside SPlisHSPlasH's FoamGenerator.

    python benchmarks/compare_foamgenerator.py --foamgenerator PATH/TO/FoamGenerator \
        [--input ../shared/data/dualsphysics_dambreak]

Converts the DualSPHysics PartFluid sequence (with its case XML) to y-up BGEO
frames 1, 2, ... as SPlisHSPlasH writes them, runs FoamGenerator with its
defaults (automatic mode; radius and time step from the case) twice, without a
bounding box (its default: spray falls for ever) and with the case's domain as
a killing box (as whitecap removes what leaves the domain), runs
`whitecap foam --preset splishsplash` on the same frames, and prints per type
the peak counts and the per-frame ratio whitecap / FoamGenerator.

FoamGenerator is not shipped: build it from SPlisHSPlasH (Tools/FoamGenerator).
Its --splittypes log gives the counts of each frame's particles before that
frame's generation, i.e. one frame behind whitecap's; both alignments are shown.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TYPES = ("spray", "foam", "bubbles")


def foamgenerator_counts(log: str) -> np.ndarray:
    """(frames × 3) spray, foam, bubbles from FoamGenerator's --splittypes log."""
    vals = re.findall(r"#_(foam|spray|bubbles): (\d+)", log)
    rows = [dict(vals[i:i + 3]) for i in range(0, len(vals) - 2, 3)]
    return np.array([[int(r[t]) for t in TYPES] for r in rows])


def report(name: str, ours: np.ndarray, theirs: np.ndarray, floor: int = 100) -> None:
    print(f"\n{name}")
    for k, t in enumerate(TYPES):
        print(f"  {t:8s} peak: FoamGenerator {theirs[:, k].max():8,d}  whitecap {int(ours[:, k].max()):8,d}  "
              f"ratio {ours[:, k].max() / max(theirs[:, k].max(), 1):.2f}")
    for shift in (0, 1):
        a, b = ours[: len(ours) - shift], theirs[shift: shift + len(ours)]
        n = min(len(a), len(b))
        a, b = a[:n], b[:n]
        parts = []
        for k, t in enumerate(TYPES):
            m = b[:, k] >= floor
            r = a[m, k] / b[m, k]
            within = np.mean((r >= 0.5) & (r <= 2.0)) if m.any() else float("nan")
            parts.append(f"{t} median {np.median(r):.2f} [{r.min():.2f}, {r.max():.2f}], {within:.0%} of {m.sum()} "
                         f"frames within 2x" if m.any() else f"{t}: none")
        print(f"  per frame (FoamGenerator >= {floor}; whitecap {shift} frame(s) ahead): " + "; ".join(parts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--foamgenerator", required=True, help="the FoamGenerator executable")
    ap.add_argument("--input", default=str(ROOT.parent / "shared/data/dualsphysics_dambreak"))
    a = ap.parse_args()
    os.environ.setdefault("WHITECAP_PROGRESS", "0")
    sys.path.insert(0, str(ROOT))
    from tests.conftest import write_partio_bgeo  # whitecap itself never writes BGEO

    from whitecap import io
    from whitecap.diffuse import postprocess
    from whitecap.io.dualsphysics import read_case
    from whitecap.io.sequence import find_sequence

    src = Path(a.input)
    case = read_case(sorted(src.glob("*.xml"))[0])
    files = find_sequence(src / "PartFluid_*.vtk")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        (tmp / "bgeo").mkdir()
        for k, (_, p) in enumerate(files, 1):  # FoamGenerator counts frames from 1, y up
            f = io.read(p)

            def y_up(v):
                return np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)

            write_partio_bgeo(tmp / "bgeo" / f"ParticleData_Fluid_{k}.bgeo", y_up(f.positions),
                              {"velocity": y_up(f.velocities)})
        lo, hi = np.asarray(case.lower), np.asarray(case.upper)
        box = [lo[0], lo[2], -hi[1], hi[0], hi[2], -lo[1]]  # the domain, y up
        cmd = [a.foamgenerator, "-i", str(tmp / "bgeo" / "ParticleData_Fluid_#.bgeo"), "-o", str(tmp / "fg" / "foam_#.bgeo"),
               "-r", str(case.particle_radius), "-t", str(case.time_out), "-s", "1", "-e", str(len(files)), "--splittypes"]
        runs = {
            "FoamGenerator defaults (no bounding box)": cmd,
            "FoamGenerator defaults, --bbsize = the case domain --bbtype kill": cmd + [
                "--bbsize=" + ",".join(f"{v:g}" for v in box), "--bbtype=kill"],
        }
        logs = {k: subprocess.run(c, capture_output=True, text=True, check=True).stdout for k, c in runs.items()}
        postprocess(str(src / "PartFluid_*.vtk"), out=tmp / "wc", preset="splishsplash", show_progress=False)
        ours = np.loadtxt(tmp / "wc" / "diffuse" / "counts.csv", delimiter=",", skiprows=1)[:, 2:]
    print(f"{src}: {len(files)} frames, {len(f):,} fluid particles, r = {case.particle_radius} m, "
          f"frame time {case.time_out} s")
    for name, log in logs.items():
        report(f"whitecap --preset splishsplash vs {name}", ours, foamgenerator_counts(log))


if __name__ == "__main__":
    main()
