"""Per-type diffuse counts of `--preset splishsplash` beside SPlisHSPlasH's FoamGenerator.

    python benchmarks/compare_foamgenerator.py --foamgenerator PATH/TO/FoamGenerator \
        [--input ../shared/data/dualsphysics_dambreak | ../shared/data/splishsplash_rigid]

A SPlisHSPlasH output folder (`whitecap import` reads it) gives FoamGenerator
its fluid frames as SPlisHSPlasH's partio export would (y up, the solver's row
order, velocity, density, id); whitecap runs on the imported fluid without
obstacles (FoamGenerator has none), the tank's inside as the domain, and again
with the case's tank and bodies. Otherwise the input is a DualSPHysics case:
converts the DualSPHysics PartFluid sequence (with its case XML) to y-up BGEO
frames 1, 2, ... as SPlisHSPlasH writes them, runs FoamGenerator with its
defaults (automatic mode; radius and time step from the case) twice, without a
bounding box (its default: spray falls for ever) and with the case's domain as
a killing box (as whitecap removes what leaves the domain), runs
`whitecap foam --preset splishsplash` on the same frames, and prints per type
the peak counts, the sums over all frames and the per-frame ratio whitecap /
FoamGenerator (the share of frames within 2x).

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
# whitecap's FoamGenerator presets: its defaults, and its defaults with the domain as a kill box
PRESETS = ("splishsplash", "splishsplash-box")


def foamgenerator_counts(log: str) -> np.ndarray:
    """(frames × 3) spray, foam, bubbles from FoamGenerator's --splittypes log."""
    vals = re.findall(r"#_(foam|spray|bubbles): (\d+)", log)
    rows = [dict(vals[i:i + 3]) for i in range(0, len(vals) - 2, 3)]
    return np.array([[int(r[t]) for t in TYPES] for r in rows])


def report(name: str, ours: np.ndarray, theirs: np.ndarray, floor: int = 100) -> None:
    print(f"\n{name}")
    for k, t in enumerate(TYPES):
        print(f"  {t:8s} peak: FoamGenerator {theirs[:, k].max():8,d}  whitecap {int(ours[:, k].max()):8,d}  "
              f"ratio {ours[:, k].max() / max(theirs[:, k].max(), 1):.2f};  whole run (sum over frames): "
              f"FoamGenerator {theirs[:, k].sum():10,d}  whitecap {int(ours[:, k].sum()):10,d}  "
              f"ratio {ours[:, k].sum() / max(theirs[:, k].sum(), 1):.2f}")
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


FG_DEFAULT = "FoamGenerator defaults (no bounding box)"
FG_BOX = "FoamGenerator defaults, --bbsize = the domain --bbtype kill"


def fg_runs(fg: str, bgeo: Path, out: Path, radius: float, dt: float, n: int, box) -> dict[str, np.ndarray]:
    """Per-frame counts (frames × 3) of FoamGenerator with its defaults, without a box, the same
    run's particles inside the domain only, and with ``box`` (the domain, y up) as a kill box."""
    from whitecap.io.bgeo import read_bgeo

    lo, hi = np.array([box[0], -box[5], box[1]]), np.array([box[3], -box[2], box[4]])  # the box, z up
    cmd = [fg, "-i", str(bgeo / "ParticleData_Fluid_#.bgeo"), "", "-r", str(radius), "-t", str(dt), "-s", "1",
           "-e", str(n), "--splittypes"]
    runs = {FG_DEFAULT: [], FG_BOX: ["--bbsize=" + ",".join(f"{v:g}" for v in box), "--bbtype=kill"]}
    counts = {}
    for name, extra in runs.items():
        d = out / str(len(counts))
        d.mkdir(parents=True)
        cmd[3] = "-o" + str(d / "foam_#.bgeo")
        done = subprocess.run(cmd + extra, capture_output=True, text=True, check=True)
        counts[name] = foamgenerator_counts(done.stdout)
        if name == FG_DEFAULT:  # its spray falls through the walls it does not know, for ever
            inside = np.zeros((n, 3), np.int64)
            for k in range(1, n + 1):
                for t, name_ in enumerate(TYPES):
                    f = d / f"foam_{k}_{name_}.bgeo"
                    if f.exists():
                        x = read_bgeo(f, up="y", require_velocity=False).positions
                        inside[k - 1, t] = int(np.all((x >= lo) & (x <= hi), axis=1).sum())
            counts[name + ", its particles inside the domain"] = inside
    return counts


def counts(run: Path) -> np.ndarray:
    return np.loadtxt(run / "diffuse" / "counts.csv", delimiter=",", skiprows=1)[:, 2:]


def dualsphysics(a, tmp: Path, write_partio_bgeo) -> tuple[str, dict, dict]:
    """The DualSPHysics PartFluid sequence: converted to y-up BGEO; whitecap reads it as it is."""
    from whitecap import io
    from whitecap.cases.dualsphysics_xml import read_xml
    from whitecap.diffuse import postprocess
    from whitecap.io.sequence import find_sequence

    src = Path(a.input)
    case = read_xml(sorted(src.glob("*.xml"))[0])
    files = find_sequence(src / "PartFluid_*.vtk")
    for k, (_, p) in enumerate(files, 1):  # FoamGenerator counts frames from 1, y up
        f = io.read(p)

        def y_up(v):
            return np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)

        write_partio_bgeo(tmp / "bgeo" / f"ParticleData_Fluid_{k}.bgeo", y_up(f.positions),
                          {"velocity": y_up(f.velocities)})
    lo, hi = np.asarray(case.lower), np.asarray(case.upper)
    box = [lo[0], lo[2], -hi[1], hi[0], hi[2], -lo[1]]  # the domain, y up
    fg = fg_runs(a.foamgenerator, tmp / "bgeo", tmp / "fg", case.particle_radius, case.time_out, len(files), box)
    for preset in PRESETS:
        postprocess(str(src / "PartFluid_*.vtk"), out=tmp / preset, preset=preset, show_progress=False)
    head = (f"{src}: {len(files)} frames, {len(f):,} fluid particles, r = {case.particle_radius} m, "
            f"frame time {case.time_out} s")
    return head, fg, {p: counts(tmp / p) for p in PRESETS}


def splishsplash(a, tmp: Path, write_partio_bgeo) -> tuple[str, dict, dict]:
    """A SPlisHSPlasH output folder: FoamGenerator gets its fluid frames as SPlisHSPlasH's partio
    exporter writes them (y up, the solver's row order, velocity, density and id); whitecap imports
    the case (`whitecap import`) and runs on its fluid without obstacles, the tank's inside as the
    domain (FoamGenerator knows no obstacles), and, for reference, with the tank and bodies."""
    from whitecap import io
    from whitecap.cases.splishsplash import _axes, read_output
    from whitecap.diffuse import postprocess
    from whitecap.io.run import RunInfo
    from whitecap.pipeline import import_case

    src = Path(a.input)
    case = read_output(src)
    to_y = _axes(case.up)  # rows: z-up vectors -> the solver's y-up ones (v_z @ M)
    for k, p in case.fluid:  # SPlisHSPlasH numbers frames from 1, as FoamGenerator reads them
        f = io.read(p, up=case.up)  # the file's own row order (SPlisHSPlasH z-sorts its particles)
        write_partio_bgeo(tmp / "bgeo" / f"ParticleData_Fluid_{k}.bgeo", f.positions @ to_y,
                          {"velocity": f.velocities @ to_y, "density": f.density, "id": f.ids.astype(np.int32)})
    tank = next(s for s in case.shapes if s.role == "container")
    lo, hi = tank.vertices.min(axis=0), tank.vertices.max(axis=0)  # z up
    box = np.concatenate([(lo @ to_y), (hi @ to_y)])
    box = [*np.minimum(box[:3], box[3:]), *np.maximum(box[:3], box[3:])]
    fg = fg_runs(a.foamgenerator, tmp / "bgeo", tmp / "fg", case.particle_radius, case.frame_dt,
                 case.fluid[-1][0], box)
    run = tmp / "run"
    import_case(src, run, show_progress=False)
    fluid = [(i, run / rel) for i, rel in RunInfo.load(run).files("fluid")]
    for preset in PRESETS:
        postprocess(run / "fluid", frames=fluid, out=tmp / preset, preset=preset, dt=case.frame_dt,
                    radius=case.particle_radius, domain=(lo, hi), show_progress=False)
    postprocess(run, out=tmp / "wc_obstacles", preset="splishsplash", show_progress=False)
    head = (f"{src}: {len(case.fluid)} frames, {len(f):,} fluid particles, r = {case.particle_radius} m, "
            f"frame time {case.frame_dt} s; whitecap runs on the imported fluid without obstacles, the tank's "
            "inside as the domain")
    ours = {p: counts(tmp / p) for p in PRESETS}
    ours["splishsplash with the tank and the sphere"] = counts(tmp / "wc_obstacles")
    return head, fg, ours


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--foamgenerator", required=True, help="the FoamGenerator executable")
    ap.add_argument("--input", default=str(ROOT.parent / "shared/data/dualsphysics_dambreak"),
                    help="a DualSPHysics case folder (PartFluid_*.vtk and the case XML) "
                         "or a SPlisHSPlasH output folder")
    a = ap.parse_args()
    os.environ.setdefault("WHITECAP_PROGRESS", "0")
    sys.path.insert(0, str(ROOT))
    from tests.conftest import write_partio_bgeo  # whitecap itself never writes BGEO
    from whitecap.cases.splishsplash import is_case

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        (tmp / "bgeo").mkdir()
        build = splishsplash if is_case(a.input) else dualsphysics
        head, fg, ours = build(a, tmp, write_partio_bgeo)
    print(head)
    for label, c in ours.items():
        for name, theirs in fg.items():
            if (name == FG_BOX) == label.startswith("splishsplash-box"):  # each preset beside its FoamGenerator run
                report(f"whitecap --preset {label} vs {name}", c, theirs)


if __name__ == "__main__":
    main()
