"""The diffuse stage's driver: the simulation frame hook and post-processing.

Two ways in, one code path (:class:`~whitecap.diffuse.generator.FoamGenerator`):

- inside ``simulate``: :func:`simulation_hook` gives the frame hook the
  simulation driver calls after every frame;
- as post-processing: :func:`postprocess` runs over a whitecap run, a
  DualSPHysics PartVTK sequence, SPlisHSPlasH VTK or partio BGEO output or PLY/VTU/NPZ
  sequences, and writes a run directory the later stages can read.

Output per frame: ``diffuse/diffuse_NNNNN.ply`` (x y z vx vy vz, type u8
0 spray / 1 foam / 2 bubble, lifetime, radius, id) and ``diffuse/counts.csv``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from ..config import Foam, Scene, load_scene
from ..errors import InputError
from ..io import ParticleFrame, read, write, write_text
from ..io.lock import run_lock
from ..io.run import RunInfo, frame_name
from ..progress import console, progress
from ..io.diffuse_types import COUNT_NAMES
from .generator import DiffuseState, FoamGenerator
from .params import FoamParams, resolve

__all__ = ["simulation_hook", "postprocess", "FoamGenerator", "FoamParams", "resolve"]


def write_counts(out: Path, rows: list) -> None:
    lines = [",".join(("frame", "time", *COUNT_NAMES))] + [
        f"{int(r[0])},{r[1]:.6f},{int(r[2])},{int(r[3])},{int(r[4])}" for r in rows
    ]
    write_text(out / "diffuse" / "counts.csv", "\n".join(lines) + "\n")


class FoamStage:
    """Frame hook: diffuse particles for each fluid frame, with checkpointable state."""

    name = "diffuse"

    def __init__(self, params: FoamParams, seed: int, verbose: bool = False, obstacles: list | None = None):
        self.params = params
        self.seed = seed
        self.obstacles = obstacles
        self.gen: FoamGenerator | None = None
        self._pending: DiffuseState | None = None
        self.verbose = verbose

    def on_start(self, solver, out: Path, info: RunInfo) -> None:
        self.start(info)

    def start(self, info: RunInfo) -> None:
        self.gen = FoamGenerator(
            self.params, info.particle_radius, (info.domain["lower"], info.domain["upper"]), info.gravity, self.seed,
            obstacles=self.obstacles,
        )
        if self._pending is not None:
            self.gen.state = self._pending

    def on_frame(self, frame: ParticleFrame, index: int, dt: float, out: Path, info: RunInfo) -> str:
        d = self.gen.step(frame, index, dt)
        rel = frame_name("diffuse", index)
        write(out / rel, d)
        rows = self.gen.state.counts
        write_counts(out, rows)
        if self.verbose:
            console.print(f"frame {index}: {self.status()}")
        return rel

    def status(self) -> str:
        r = self.gen.state.counts[-1] if self.gen and self.gen.state.counts else (0, 0, 0, 0, 0)
        return f"spray {int(r[2]):,} foam {int(r[3]):,} bubbles {int(r[4]):,}"

    def checkpoint(self) -> dict[str, np.ndarray]:
        return self.gen.state.to_arrays() if self.gen else {}

    def restore(self, data: dict[str, np.ndarray]) -> None:
        if data:
            self._pending = DiffuseState.from_arrays(data)
            if self.gen is not None:
                self.gen.state = self._pending

    def warn_if_empty(self) -> None:
        rows = self.gen.state.counts if self.gen else []
        if rows and sum(r[2] + r[3] + r[4] for r in rows) == 0:
            console.print(
                "[yellow]warning:[/] no diffuse particles were generated: the flow never exceeded the clamping "
                "thresholds (foam.ta_min, wc_min, ke_min). Lower them or use foam.preset = \"auto\"."
            )


def obstacle_grids(scene: Scene) -> list:
    """The scene's obstacle SDFs (cached on disk), so diffuse particles entering them are removed."""
    if not scene.obstacle:
        return []
    from ..sim.obstacles import load_obstacles

    return load_obstacles(scene).grids


def simulation_hook(scene: Scene) -> FoamStage:
    """The frame hook `simulate` uses when [foam] is enabled."""
    return FoamStage(resolve(scene.foam), scene.seed, obstacles=obstacle_grids(scene))


# ============================================================================ post-processing
def _input_frames(src: Path) -> tuple[list[tuple[int, Path]], RunInfo | None, dict]:
    """Frames of the input plus what is known about the run (radius, dt, domain...)."""
    from ..io.sequence import find_sequence

    if src.is_dir() and (src / "run.json").exists():
        info = RunInfo.load(src)
        files = [(i, src / rel) for i, rel in info.files("fluid")]
        if not files:
            raise InputError(f"{src}/run.json: no fluid frames listed")
        return files, info, {}
    if not src.exists() and not any(c in str(src) for c in "*?["):
        raise InputError(f"{src}: no such file or directory")
    files = find_sequence(src)
    known: dict = {}
    folder = src if src.is_dir() else src.parent
    xmls = sorted(folder.glob("*.xml")) if folder.is_dir() else []
    if xmls:
        from ..io.dualsphysics import read_case

        case = read_case(xmls[0])
        known.update(radius=case.particle_radius, mass=case.mass, dt=case.time_out, rest_density=case.rho0,
                     gravity=case.gravity, lower=case.lower, upper=case.upper, case=str(xmls[0]))
    return files, None, known


def _first_particles(files: list[tuple[int, Path]], first: ParticleFrame, up: str) -> np.ndarray | None:
    """Positions of the first frame that has particles (None when every frame is empty)."""
    for k, (_, path) in enumerate(files):
        fr = first if k == 0 else read(path, up=up)
        if len(fr):
            fr.check_finite()
            return fr.positions
    return None


def postprocess(
    src: str | Path,
    out: str | Path | None = None,
    params: FoamParams | None = None,
    ini: str | Path | None = None,
    preset: str | None = None,
    up: str = "z",
    dt: float | None = None,
    radius: float | None = None,
    seed: int | None = None,
    case: str | Path | None = None,
    show_progress: bool = True,
) -> RunInfo:
    """Diffuse particles over any particle sequence; writes (or adds to) a run directory.

    For a whitecap run, the run's own [foam] settings and seed are used unless
    overridden, and results land in the run itself (``out`` defaults to it).
    For other sequences the fluid frames are converted into ``out/fluid`` so
    that `whitecap mesh`, `view` and `render` can continue from there.
    """
    src = Path(src)
    files, info, known = _input_frames(src)
    if case is not None:
        from ..io.dualsphysics import read_case

        c = read_case(case)
        known.update(radius=c.particle_radius, mass=c.mass, dt=c.time_out, rest_density=c.rho0, gravity=c.gravity,
                     lower=c.lower, upper=c.upper)
    foam_cfg = Foam()
    run_seed = 0
    grids: list = []
    if info is not None:
        scene_file = src / "scene.toml"
        if scene_file.is_file():
            run_scene = load_scene(scene_file)
            run_scene.base_dir = info.extra.get("scene_dir", run_scene.base_dir)
            foam_cfg = run_scene.foam
            grids = obstacle_grids(run_scene)
        run_seed = int(info.extra.get("seed", 0))
        out = Path(out) if out is not None else src
    elif out is None:
        raise InputError(f"{src}: not a whitecap run; pass --out DIR for the results")
    out = Path(out)
    p = params or resolve(foam_cfg, ini=ini, preset=preset)
    seed = run_seed if seed is None else seed

    frame_dt = dt or (1.0 / info.frame_rate if info else known.get("dt"))
    if not frame_dt or frame_dt <= 0:
        raise InputError(f"{src}: the time between frames is unknown; pass --dt SECONDS")
    r = radius or (info.particle_radius if info else known.get("radius"))
    if not r or r <= 0:
        raise InputError(f"{src}: the particle radius is unknown; pass --radius METRES (half the spacing)")

    src_is_run = info is not None
    out.mkdir(parents=True, exist_ok=True)
    with run_lock(out, "foam"):
        return _postprocess(src, out, files, info, known, p, seed, frame_dt, r, up, grids, show_progress)


def _source_identity(files: list[tuple[int, Path]], up: str) -> str:
    """Identity of a foreign sequence: its files' names, sizes and modification times."""
    stats = [(str(path.resolve()), path.stat().st_size, path.stat().st_mtime_ns) for _, path in files]
    return hashlib.sha256(json.dumps([up, stats]).encode()).hexdigest()[:16]


def _postprocess(src: Path, out: Path, files: list, info: RunInfo | None, known: dict, p: FoamParams, seed: int,
                 frame_dt: float, r: float, up: str, grids: list, show_progress: bool) -> RunInfo:
    src_is_run = info is not None
    if src_is_run:  # read again under the lock: what is current cannot change from here on
        info = RunInfo.load(src)
        files = [(i, src / rel) for i, rel in info.files("fluid")]
    first = read(files[0][1], **({"up": up} if info is None else {}))
    if first.velocities is None:
        raise InputError(f"{files[0][1]}: missing array 'velocity'")
    if info is None:
        if "lower" in known and "upper" in known:
            lo, hi = known["lower"], known["upper"]
        else:  # the first frame with particles, grown by half its extent
            pts = _first_particles(files, first, up)
            if pts is None:
                raise InputError(f"{src}: all {len(files)} frames are empty (no particles), so there is nothing to "
                                 "make diffuse particles from")
            lo = (pts.min(0) - 0.5 * np.ptp(pts, 0) - 4 * r).tolist()
            hi = (pts.max(0) + 0.5 * np.ptp(pts, 0) + 4 * r).tolist()
        info = RunInfo(
            particle_radius=float(r), rest_density=float(known.get("rest_density", 1000.0)),
            particle_mass=float(known.get("mass", 1000.0 * (2 * r) ** 3)), gravity=list(known.get("gravity", [0, 0, -9.81])),
            domain={"lower": list(map(float, lo)), "upper": list(map(float, hi))}, frame_rate=1.0 / frame_dt,
            extra={"source": str(src), "seed": seed, **({"case": known["case"]} if "case" in known else {})},
        )
        info.simulation = _source_identity(files, up)
    # Results for a whitecap run go into that run; anywhere else the fluid
    # frames are copied along so the output is a complete run directory.
    convert = out.resolve() != src.resolve()
    stage = FoamStage(p, seed, verbose=True, obstacles=grids)
    stage.start(info)
    bar = progress(disable=not show_progress)
    with bar:
        task = bar.add_task("foam", total=len(files), info="")
        for index, path in files:
            fr = first if path == files[0][1] else read(path, **({"up": up} if not src_is_run else {}))
            if fr.velocities is None:
                raise InputError(f"{path}: missing array 'velocity'")
            fr.check_finite()
            fr.time = info.frame(index)["time"] if src_is_run else index * frame_dt
            if convert:
                rel = frame_name("fluid", index)
                write(out / rel, fr)
                info.set_file(index, "fluid", rel, fr.time)
            rel = stage.on_frame(fr, index, frame_dt, out, info)
            info.set_file(index, "diffuse", rel, fr.time)
            c = stage.gen.state.counts[-1]
            bar.update(task, advance=1, info=f"{len(fr):,} fluid  spray {c[2]:,}  foam {c[3]:,}  bubbles {c[4]:,}")
    info.save(out)
    stage.warn_if_empty()
    tot = np.array([r_[2:] for r_ in stage.gen.state.counts]).sum(0) if stage.gen.state.counts else np.zeros(3)
    console.print("diffuse particles over the run: " + ", ".join(f"{t} {int(v):,}" for t, v in zip(COUNT_NAMES, tot)))
    return info
