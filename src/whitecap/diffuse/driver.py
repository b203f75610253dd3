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

from pathlib import Path

import numpy as np

from ..config import Foam, Scene, load_scene
from ..errors import InputError
from ..io import ParticleFrame, read, write, write_text
from ..io.run import RunInfo, frame_name
from ..progress import console, progress
from .generator import TYPES, DiffuseState, FoamGenerator
from .params import FoamParams, resolve

__all__ = ["simulation_hook", "postprocess", "FoamGenerator", "FoamParams", "resolve"]


def write_counts(out: Path, rows: list) -> None:
    lines = ["frame,time,spray,foam,bubbles"] + [
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

    def finish(self) -> None:
        """Say the peak diffuse-to-fluid ratio reached (and the budget it aimed for)."""
        if self.gen is not None and self.gen.state.counts:
            console.print(self.gen.peak_report())

    def warn_if_empty(self) -> None:
        rows = self.gen.state.counts if self.gen else []
        if rows and sum(r[2] + r[3] + r[4] for r in rows) == 0 and self.params.auto:
            console.print(
                "[yellow]warning:[/] no diffuse particles were generated: 'auto' found no water moving faster "
                "than air entrainment needs (about 1 m/s, foam.ke_min). Set the thresholds to make some anyway."
            )
        elif rows and sum(r[2] + r[3] + r[4] for r in rows) == 0:
            console.print(
                "[yellow]warning:[/] no diffuse particles were generated: the flow never exceeded the clamping "
                "thresholds (foam.ta_min, wc_min, ke_min). Lower them or use foam.preset = \"auto\" (the default)."
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
def _input_frames(src: Path, up: str) -> tuple[list[tuple[int, Path]], RunInfo | None, dict]:
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
    look_ahead: bool = True,
) -> RunInfo:
    """Diffuse particles over any particle sequence; writes (or adds to) a run directory.

    For a whitecap run, the run's own [foam] settings and seed are used unless
    overridden, and results land in the run itself (``out`` defaults to it).
    For other sequences the fluid frames are converted into ``out/fluid`` so
    that `whitecap mesh`, `view` and `render` can continue from there.
    'auto' reads frames sampled across the whole sequence first (``look_ahead``);
    without it, it keeps the simulation's running estimate, as inside ``simulate``.
    """
    src = Path(src)
    files, info, known = _input_frames(src, up)
    if case is not None:
        known.update(_case_values(case))
    foam_cfg, run_seed, grids, out = _run_settings(src, info, out)
    p = params or resolve(foam_cfg, ini=ini, preset=preset)
    seed = run_seed if seed is None else seed
    frame_dt, r = _frame_dt_and_radius(src, info, known, dt, radius)
    reader = _Reader(files, up if info is None else None)
    src_is_run = info is not None
    if info is None:
        info = _foreign_run_info(reader.first(), known, r, frame_dt, src, seed)
    out.mkdir(parents=True, exist_ok=True)
    stage = FoamStage(p, seed, verbose=True, obstacles=grids)
    stage.start(info)
    if p.auto and look_ahead:
        _calibrate(stage, reader, info, frame_dt, src_is_run)
    # Results for a whitecap run go into that run; anywhere else the fluid
    # frames are copied along so the output is a complete run directory.
    convert = out.resolve() != src.resolve()
    _run_frames(stage, reader, info, out, frame_dt, src_is_run, convert, show_progress)
    info.save(out)
    _report(stage)
    return info


def _case_values(case: str | Path) -> dict:
    from ..io.dualsphysics import read_case

    c = read_case(case)
    return dict(radius=c.particle_radius, mass=c.mass, dt=c.time_out, rest_density=c.rho0, gravity=c.gravity,
                lower=c.lower, upper=c.upper)


def _run_settings(src: Path, info: RunInfo | None, out) -> tuple[Foam, int, list, Path]:
    """A whitecap run's own [foam] section, seed and obstacles; where the results go."""
    foam_cfg, run_seed, grids = Foam(), 0, []
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
    return foam_cfg, run_seed, grids, Path(out)


def _frame_dt_and_radius(src: Path, info: RunInfo | None, known: dict, dt, radius) -> tuple[float, float]:
    frame_dt = dt or (1.0 / info.frame_rate if info else known.get("dt"))
    if not frame_dt or frame_dt <= 0:
        raise InputError(f"{src}: the time between frames is unknown; pass --dt SECONDS")
    r = radius or (info.particle_radius if info else known.get("radius"))
    if not r or r <= 0:
        raise InputError(f"{src}: the particle radius is unknown; pass --radius METRES (half the spacing)")
    return frame_dt, r


class _Reader:
    """The input's frames, each checked for velocities; the first and the sampled ones are kept."""

    def __init__(self, files: list[tuple[int, Path]], up: str | None):
        self.files = files
        self.kw = {"up": up} if up is not None else {}
        self.cache: dict[int, ParticleFrame] = {}

    def read(self, k: int, keep: bool = False) -> ParticleFrame:
        if k in self.cache:
            return self.cache.pop(k) if not keep else self.cache[k]
        path = self.files[k][1]
        fr = read(path, **self.kw)
        if fr.velocities is None:
            raise InputError(f"{path}: missing array 'velocity'")
        fr.check_finite()
        if keep:
            self.cache[k] = fr
        return fr

    def first(self) -> ParticleFrame:
        return self.read(0, keep=True)


def _foreign_run_info(first: ParticleFrame, known: dict, r: float, frame_dt: float, src: Path, seed: int) -> RunInfo:
    """A run.json for a sequence from another solver: the domain from its case file or the first frame."""
    lo = known.get("lower") or (first.positions.min(0) - 0.5 * np.ptp(first.positions, 0) - 4 * r).tolist()
    hi = known.get("upper") or (first.positions.max(0) + 0.5 * np.ptp(first.positions, 0) + 4 * r).tolist()
    return RunInfo(
        particle_radius=float(r), rest_density=float(known.get("rest_density", 1000.0)),
        particle_mass=float(known.get("mass", 1000.0 * (2 * r) ** 3)), gravity=list(known.get("gravity", [0, 0, -9.81])),
        domain={"lower": list(map(float, lo)), "upper": list(map(float, hi))}, frame_rate=1.0 / frame_dt,
        extra={"source": str(src), "seed": seed, **({"case": known["case"]} if "case" in known else {})},
    )


def _frame_time(info: RunInfo, index: int, frame_dt: float, src_is_run: bool) -> float:
    return info.frame(index)["time"] if src_is_run else index * frame_dt


def _calibrate(stage: FoamStage, reader: _Reader, info: RunInfo, frame_dt: float, src_is_run: bool) -> None:
    """'auto' from the whole sequence: potentials of frames sampled evenly across it."""
    from .budget import sample_count

    nf = len(reader.files)
    picks = sorted(set(np.linspace(0, nf - 1, sample_count(nf)).round().astype(int).tolist()))
    samples = []
    for k in picks:
        fr = reader.read(k, keep=k == 0)
        fr.time = _frame_time(info, reader.files[k][0], frame_dt, src_is_run)
        samples.append(fr)
    times = np.array([_frame_time(info, i, frame_dt, src_is_run) for i, _ in reader.files], np.float64)
    # The fluid count between samples is taken as the nearest sample's (it changes only with in- or outflow).
    n_s = np.array([len(f) for f in samples], np.float64)
    n_fluid = n_s[np.abs(times[:, None] - np.array([f.time for f in samples])[None, :]).argmin(1)]
    stage.gen.calibrate(samples, times, n_fluid, frame_dt, [i for i, _ in reader.files])


def _run_frames(stage: FoamStage, reader: _Reader, info: RunInfo, out: Path, frame_dt: float, src_is_run: bool,
                convert: bool, show_progress: bool) -> None:
    """Every frame through the generator; the fluid copied along into ``out`` when it is another folder."""
    bar = progress(disable=not show_progress)
    with bar:
        task = bar.add_task("foam", total=len(reader.files), info="")
        for k, (index, _) in enumerate(reader.files):
            fr = reader.read(k)
            fr.time = _frame_time(info, index, frame_dt, src_is_run)
            if convert:
                rel = frame_name("fluid", index)
                write(out / rel, fr)
                info.set_file(index, "fluid", rel, fr.time)
            rel = stage.on_frame(fr, index, frame_dt, out, info)
            info.set_file(index, "diffuse", rel, fr.time)
            c = stage.gen.state.counts[-1]
            bar.update(task, advance=1, info=f"{len(fr):,} fluid  spray {c[2]:,}  foam {c[3]:,}  bubbles {c[4]:,}")


def _report(stage: FoamStage) -> None:
    stage.warn_if_empty()
    stage.finish()
    counts = stage.gen.state.counts
    tot = np.array([r_[2:] for r_ in counts]).sum(0) if counts else np.zeros(3)
    console.print("diffuse particles over the run: " + ", ".join(f"{t} {int(v):,}" for t, v in zip(TYPES, tot)))
