"""The diffuse stage's driver: the simulation frame hook and post-processing.

Two ways in, one code path (:class:`~whitecap.diffuse.generator.FoamGenerator`):

- inside ``simulate``: :func:`simulation_hook` gives the frame hook
  (:class:`whitecap.sim.driver.FrameHook`) the simulation driver calls after every frame;
  its obstacles are the solver's own;
- as post-processing: :func:`postprocess` runs over a whitecap run; a DualSPHysics
  PartVTK sequence, SPlisHSPlasH VTK or partio BGEO output or PLY/VTU/NPZ sequences
  are imported first into a run directory the later stages can read (as a bare
  sequence, :mod:`whitecap.cases.sequence`).

Output per frame: ``diffuse/diffuse_NNNNN.ply`` (x y z vx vy vz, type u8
0 spray / 1 foam / 2 bubble, lifetime, radius, id) and ``diffuse/counts.csv``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import math
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator

import numpy as np

from ..config import DEFAULT_ARCH, DEFAULT_UP, Foam, Scene, load_scene, with_options
from ..errors import InputError
from ..io import ParticleFrame, read, write, write_bytes, write_copy, write_text
from ..io.atomic import sweep_temps, write_arrays
from ..io.diffuse_types import COUNT_NAMES
from ..io.lock import run_lock
from ..io.record import relpath_problem
from ..io.run import (
    CHECKPOINT,
    COUNTS_CSV,
    FOAM_RESUME,
    RUN_JSON,
    RunInfo,
    claim_run_dir,
    frame_name,
    own_meshes,
    remove_run,
)
from ..io.writer import FrameWriter
from ..progress import console, progress
from ..sim.driver import FrameHook
from ..timing import timer
from .generator import DiffuseState, FoamGenerator, speed_squared
from .params import FoamParams, IniFile, read_ini, resolve

__all__ = ["FoamJob", "simulation_hook", "postprocess", "postprocess_params_file", "FoamGenerator", "FoamParams",
           "resolve"]


COUNTS_HEADER = ",".join(("frame", "time", *COUNT_NAMES))


def counts_line(row) -> str:
    """A row of diffuse/counts.csv: frame, time [s], then the live spray, foam and bubbles."""
    return f"{int(row[0])},{row[1]:.6f},{int(row[2])},{int(row[3])},{int(row[4])}"


def _write_diffuse(out: Path, rel: str, frame: ParticleFrame, ready: Future | None = None) -> None:
    """One frame's diffuse particles, once ``ready`` (the frame's read-back from the GPU, FoamGenerator.pending)
    is done. counts.csv up to the frame is written after it (:meth:`FoamStage.write`), so that it never lists a
    frame whose file is not written."""
    if ready is not None:
        ready.result()
    write(out / rel, frame)


class FoamStage(FrameHook):
    """Frame hook: diffuse particles for each fluid frame, with checkpointable state.

    ``obstacles`` (sim.obstacles.PosedSDF, posed per frame from run.json's records) are what the
    diffuse particles collide with; inside `simulate` they are the solver's (:meth:`on_start`)."""

    name = "diffuse"

    def __init__(self, params: FoamParams, seed: int, verbose: bool = False, obstacles: list | None = None,
                 arch: str | None = None):
        self.params = params
        self.arch = arch  # Taichi backend asked for (post-processing); None: the one running (simulate's)
        self.seed = seed
        self.obstacles = obstacles
        self.gen: FoamGenerator | None = None
        self._restored: dict | None = None  # a checkpoint's arrays (restore), set on the generator by start
        self.verbose = verbose
        self.last_frame: int | None = None  # the run's last frame index, where known
        self.max_speed = 0.0  # the fastest fluid particle seen [m/s]: to say which threshold no flow reached
        self.made_any = False  # a diffuse particle was alive at some frame (then max_speed is not needed)
        self.particle_mass: float | None = None
        self.names: dict[str, str] = {}  # where a threshold was set, e.g. {"ke_min": "f.ini: [DIFFUSE] KEMin"}
        self._unwritten: tuple | None = None  # (out, relative path, frame) made by on_frame, for write()
        self._last_file: str | None = None  # the last frame's diffuse file, relative to the run (on_frame)
        # counts.csv's lines of the generator's rows so far (``_lines_of``, that list; ``_taken`` of its rows
        # looked at): formatted once each, as a run's counts are rewritten every frame
        self._lines: list[str] = []
        self._lines_of: list | None = None
        self._taken = 0
        self._counts_from = 0  # the first frame counts.csv lists (on_start)

    @property
    def generator(self) -> FoamGenerator:
        """The generator :meth:`start` made (the frames, their files and the post-processing passes come after it)."""
        assert self.gen is not None, "FoamStage.start comes first"
        return self.gen

    def on_start(self, solver, out: Path, info: RunInfo, last_frame: int) -> None:
        if self._restored is not None and "live_file" in self._restored:  # simulate's checkpoint (see checkpoint):
            self._restored = _with_live_particles(out, self._restored)  # first, so a refusal changes nothing
        self.last_frame = last_frame
        done = max((f.index for f in info.frames), default=-1)  # the frame simulate goes on from
        if done < last_frame and info.extra.get("foam_pass") is not None:
            self._end_foam_pass(out, info, done + 1)
        # counts.csv lists the frames whose diffuse files the run lists: after a pass's frames left (and on
        # every resume after that), the rows of the frames before them, restored with simulate's state, stay out
        self._counts_from = min((i for i, _ in info.files("diffuse")), default=done + 1)
        self.start(info, solver)

    @staticmethod
    def _end_foam_pass(out: Path, info: RunInfo, index: int) -> None:
        """Inside `simulate`, before it makes frame ``index``: the frames of the `foam` pass that replaced its own
        foam leave the run (saved before any new frame is handed to the writer), said in a note. Simulate's foam
        goes on from its checkpoint, so the two are never listed side by side; a simulate with no frame to make
        leaves them as they are."""
        were = info.extra.pop("foam_pass")
        _forget_earlier_pass(info, out)
        info.save(out)
        console.print(f"note: {out}: the diffuse frames of `whitecap foam` (seed {were.get('seed')}) leave the run: "
                      f"simulate goes on with its own foam from frame {index}; `whitecap foam {out}` makes the foam "
                      "of every frame again", soft_wrap=True)

    def start(self, info: RunInfo, solver=None) -> None:
        """The generator for the run ``info`` records; with ``solver``, the obstacles are the solver's
        (its SDFs and motion laws, without loading the meshes again)."""
        if solver is not None:
            self.obstacles = solver.obstacles.posed_grids() if solver.obstacles else []
        self.particle_mass = info.particle_mass
        if self.arch is not None:
            from ..sim import runtime

            runtime.init(self.arch)  # one line when CUDA is asked for and absent
        self.gen = FoamGenerator(
            self.params, info.particle_radius, (info.domain["lower"], info.domain["upper"]), info.gravity, self.seed,
            arch=self.arch or "cpu", obstacles=self.obstacles,
        )
        self.gen.last_frame = self.last_frame
        if solver is not None:  # each frame on_frame is given is the solver's state as it stands (sim.driver's emit)
            self.gen.fluid_on_device = lambda: (solver.state.x, solver.state.v, solver.state.ids)
        if self._restored is not None:
            self._apply(self._restored)

    def on_frame(self, frame: ParticleFrame, index: int, dt: float, out: Path, info: RunInfo) -> str:
        t = frame.time if frame.time is not None else index * dt
        for g in self.obstacles or []:  # obstacles (sim.obstacles.PosedSDF): this frame's pose and the last one's
            first = index == 0
            g.at_frame(t, info.body_pose(index, g.index), 0.0 if first else dt,
                       None if first else info.body_pose(index - 1, g.index))
        if not self.made_any and frame.velocities is not None and len(frame):
            v = frame.velocities  # only while nothing was made: once something is, no warning needs it
            self.max_speed = max(self.max_speed, float(np.sqrt(speed_squared(v).max())))
        # deferred: on CUDA the frame comes back from the device while the next one is computed (its file is
        # written once it is whole: write's ``ready``)
        d = self.generator.step(frame, index, dt, defer=True)
        self.made_any = self.made_any or len(d) > 0
        rel = self._last_file = frame_name("diffuse", index)
        self._unwritten = (out, rel, d, self.generator.pending)
        if self.verbose:
            with timer("foam.say"):
                console.print(f"frame {index}: {self.status()}")
        return rel

    def write(self, writer=None) -> None:
        """Write the files of the frame :meth:`on_frame` made (its diffuse particles and the counts so
        far). Apart from on_frame, so that ``--profile`` counts writing as output, not as the foam stage.
        With ``writer`` (io.writer.FrameWriter), handed to its thread: the frame is this step's own arrays
        (the generator makes new ones each step) and the counts the text of the rows so far."""
        if self._unwritten is not None:
            out, rel, d, ready = self._unwritten
            self._unwritten = None
            csv = self._counts_csv()
            if writer is None:
                _write_diffuse(out, rel, d, ready)
                write_text(out / COUNTS_CSV, csv)
            else:  # the frame's file beside the next frame's (a lane); counts.csv, one file rewritten, after it
                writer.submit(functools.partial(_write_diffuse, out, rel, d, ready), "diffuse", lane="diffuse")
                writer.submit(functools.partial(write_text, out / COUNTS_CSV, csv), "counts")

    def _counts_csv(self) -> str:
        """counts.csv's text: the generator's rows so far from frame ``_counts_from`` on, each formatted once (a
        restored state brings a new list of rows: formatted anew)."""
        rows = self.generator.state.counts
        if rows is not self._lines_of or self._taken > len(rows):
            self._lines, self._lines_of, self._taken = [], rows, 0
        self._lines.extend(counts_line(r) for r in rows[self._taken:] if r[0] >= self._counts_from)
        self._taken = len(rows)
        return "\n".join([COUNTS_HEADER, *self._lines]) + "\n"

    def status(self) -> str:
        r = self.gen.state.counts[-1] if self.gen and self.gen.state.counts else (0, 0, 0, 0, 0)
        return f"spray {int(r[2]):,} foam {int(r[3]):,} bubbles {int(r[4]):,}"

    def checkpoint(self) -> dict[str, np.ndarray]:
        """simulate's checkpoint: the state (:meth:`state_arrays`) without the live particles, which the last
        frame's diffuse file holds exactly (_IN_FRAME_FILE), and that file's path (``live_file``, relative to the
        run) instead. The run's writer writes a checkpoint after every file handed to it before, so the file is
        on disk whenever the checkpoint is; a resume reads the particles back from it (on_start). Before this,
        the particles were copied and written into every checkpoint: at 125k fluid particles on 2 cores 34 ms a
        frame of a 921 ms frame (checkpoints every frame there), at 1 M on an H200 about 5 ms a frame of the loop
        and 10 of the writer's thread (every 20th frame), and the loop waited for the frame's read-back first."""
        if self._last_file is None:  # (no frame made yet: nothing alive; every array as it stands)
            return self.state_arrays()
        return {**self.state_arrays(live=False), "live_file": np.asarray(self._last_file)}

    def state_arrays(self, live: bool = True) -> dict[str, np.ndarray]:
        """The diffuse state, what else the next frame depends on (FoamGenerator.resume_arrays) and what the
        end-of-run warning reads. ``live``: with the live particles' arrays (their read-back waited for); without,
        without them (_IN_FRAME_FILE: the frame's diffuse file holds them), and nothing waited for."""
        if self.gen is None:
            return {}
        if live:
            self.gen.settle()
        state = {k: v for k, v in self.gen.state.to_arrays().items() if live or k not in _IN_FRAME_FILE}
        return {**state, **self.gen.resume_arrays(),
                "max_speed": np.asarray(self.max_speed, np.float64), "made_any": np.asarray(self.made_any)}

    def restore(self, data: dict[str, np.ndarray]) -> None:
        """A checkpoint's state: set on the generator now where there is one (a post-processing pass resumed,
        after its look-ahead made the plan), else by :meth:`start`."""
        if data:
            self._restored = data
            if self.gen is not None:
                self._apply(data)

    def _apply(self, data: dict) -> None:
        self.generator.restore_resume(data)  # first: sizing the live arrays keeps what they hold
        self.generator.state = DiffuseState.from_arrays(data)
        self.max_speed, self.made_any = float(data.get("max_speed", 0.0)), bool(data.get("made_any", False))

    def finish(self) -> None:
        """Warn when no diffuse particle was made, and say the peak diffuse-to-fluid ratio reached (and the
        budget it aimed for)."""
        self.warn_if_empty()
        if self.gen is not None and self.gen.state.counts:
            console.print(self.gen.peak_report())

    def warn_if_empty(self) -> None:
        rows = self.gen.state.counts if self.gen else []
        if rows and sum(r[2] + r[3] + r[4] for r in rows) == 0 and self.params.auto and \
                "ke_min" not in self.params.explicit:
            console.print(
                "[yellow]warning:[/] no diffuse particles were generated: 'auto' found no water moving faster "
                "than air entrainment needs (about 1 m/s, foam.ke_min). Set the thresholds to make some anyway."
            )
        elif rows and sum(r[2] + r[3] + r[4] for r in rows) == 0:
            console.print(
                f"[yellow]warning:[/] no diffuse particles were generated: {self._unreached()}", soft_wrap=True,
            )

    def _unreached(self) -> str:
        """Which fixed threshold no particle reached, in the units it was given, and the speed it needs."""
        p = self.params
        ke_min = p.ke_min  # kinetic energy per unit mass [J/kg] = v²/2
        if 0.5 * self.max_speed**2 < ke_min:
            need = math.sqrt(2.0 * ke_min)
            where = self.names.get("ke_min", "foam.ke_min")
            per_particle = (f" ({ke_min * self.particle_mass:.3g} J per particle of {self.particle_mass:.3g} kg)"
                            if self.particle_mass else "")
            return (f"no fluid particle reached the kinetic-energy minimum ({where} = {ke_min:.3g} J/kg"
                    f"{per_particle}), which needs a speed of {need:.3g} m/s; the fastest moved at "
                    f"{self.max_speed:.3g} m/s. Lower it to make some.")
        return ("the flow's trapped-air and wave-crest potentials never exceeded their minimums "
                f"(foam.ta_min = {p.ta_min:g}, foam.wc_min = {p.wc_min:g}), although particles reached the "
                f"kinetic-energy minimum. Lower those, or use foam.preset = \"auto\" (the default).")


def obstacle_grids(scene: Scene) -> list:
    """The scene's obstacle SDFs (cached on disk), so diffuse particles entering them are removed
    (post-processing a run; inside `simulate` the foam stage takes the solver's)."""
    if not scene.obstacle:
        return []
    from ..sim.obstacles import load_obstacles

    obstacles = load_obstacles(scene)  # None only for a scene without obstacles
    return obstacles.posed_grids() if obstacles is not None else []


def simulation_hook(scene: Scene) -> FoamStage:
    """The frame hook `simulate` uses when [foam] is enabled (its obstacles: the solver's, at on_start)."""
    p = resolve(scene.foam)
    if p.model == "foamgenerator":
        raise InputError(
            f"foam.preset: {scene.foam.preset!r} is FoamGenerator's automatic mode, whose limits come from the whole "
            "sequence; simulate with [foam] enabled = false, then run `whitecap foam RUN --preset splishsplash` "
            "(or use 'splishsplash-manual' in the simulation)"
        )
    return FoamStage(p, scene.seed)


# ============================================================================ post-processing
FOAMGENERATOR_CAPACITY = 100  # diffuse particles per fluid particle the 'splishsplash' preset makes room for


def _foamgenerator_limits(gen: FoamGenerator, reader: "_Reader", show_progress: bool):
    """FoamGenerator's pass 1: the clamping limits from the per-frame maxima over the whole input."""
    from . import splishsplash as SP

    maxima = []
    files = reader.files
    bar = progress(disable=not show_progress)
    with bar:
        task = bar.add_task("foam limits", total=len(files), info="")
        for k in range(len(files)):
            fr = reader.first() if k == 0 else reader.load(k)
            maxima.append(SP.frame_maxima(gen, fr))
            bar.update(task, advance=1)
    tau = SP.limits_from_maxima(np.array(maxima), gen.r)
    console.print(
        f"foam limits (FoamGenerator automatic mode, mean of {len(files)} per-frame maxima): trapped air "
        f"{tau[0]:.3g}–{tau[1]:.3g} m/s, wave crest {tau[2]:.3g}–{tau[3]:.3g}, "
        f"kinetic energy {tau[4]:.3g}–{tau[5]:.3g} J"
    )
    return tau


@dataclass(frozen=True)
class FoamJob:
    """How one post-processing ``foam`` runs: the options of ``whitecap foam`` and of
    :func:`whitecap.pipeline.foam`, with their defaults, defined here once (the CLI and the pipeline
    build one; :func:`postprocess` and :func:`postprocess_params_file` take it).

    ``preset`` replaces the run's [foam] preset; ``up`` is the input's up axis; ``dt`` [s] and
    ``radius`` [m] the time between frames and the particle radius where the input does not say
    them; ``seed`` replaces the run's; ``force`` replaces a run of another simulation at the
    output, whole; ``arch`` the Taichi backend (cpu, cuda, auto); ``profile`` prints the time per phase.
    """

    preset: str | None = None
    up: str = DEFAULT_UP
    dt: float | None = None
    radius: float | None = None
    seed: int | None = None
    show_progress: bool = True
    force: bool = False
    arch: str = DEFAULT_ARCH
    profile: bool = False


def postprocess(
    src: str | Path,
    out: str | Path | None = None,
    job: FoamJob | None = None,
    params: FoamParams | None = None,
    ini: str | Path | IniFile | None = None,
    case: str | Path | None = None,
    frames: list[tuple[int, Path]] | None = None,
    domain: tuple | None = None,
    look_ahead: bool = True,
    **options,
) -> RunInfo:
    """Diffuse particles over any particle sequence as ``job`` says (``options``, :class:`FoamJob`
    fields, build one or replace its fields); writes (or adds to) a run directory.

    For a whitecap run, the run's own [foam] settings and seed are used unless
    overridden, and results land in the run itself (``out`` defaults to it).
    Any other sequence is imported into the run directory ``out`` as a bare
    sequence (:func:`whitecap.cases.sequence.read_sequence`, then
    :func:`whitecap.cases.run_dir.write_case`, as ``whitecap import``; its frames
    written as the pass reads them), so that `whitecap mesh`, `view` and `render`
    can continue from there; ``frames``
    ((index, path) pairs) replaces the files found at ``src``, ``case`` is its
    DualSPHysics case XML, ``domain`` ((lower, upper) [m]) its domain: diffuse
    particles outside it are removed.
    'auto' reads frames sampled across the whole sequence first (``look_ahead``);
    without it, it keeps the simulation's running estimate, as inside ``simulate``.
    An ``out`` other than the input follows :func:`whitecap.io.run.claim_run_dir`: a run
    of another simulation there is refused unless ``job.force``, which replaces it whole.
    """
    job = with_options(FoamJob, job, options)
    src = Path(src)
    if frames is not None or not (src.is_dir() and (src / "run.json").exists()):
        return _postprocess_foreign(src, out, job, params, ini, case, frames, domain, look_ahead)
    return _postprocess_run(src, out, job, params, ini, look_ahead)


def _postprocess_run(src: Path, out, job: FoamJob, params: FoamParams | None, ini, look_ahead: bool,
                     fluid: tuple[list[tuple[int, Path]], dict] | None = None) -> RunInfo:
    """:func:`postprocess` of the whitecap run ``src``. ``fluid`` ((index, path) pairs and the reader's options):
    the run's fluid frames are still at their source, a foreign sequence imported without them
    (:func:`_postprocess_foreign`): the pass reads them from there and writes them into the run."""
    info = RunInfo.load(src)
    if not (info.files("fluid") if fluid is None else fluid[0]):
        raise InputError(f"{src}/run.json: no fluid frames listed")
    foam_cfg, run_seed, grids = _run_settings(src, info)
    out = Path(out) if out is not None else src
    p = params or resolve(foam_cfg, ini=ini, preset=job.preset, particle_mass=info.particle_mass)
    seed = run_seed if job.seed is None else job.seed
    frame_dt = _frame_dt(info, job.dt, job.radius)
    state = "same"
    if out.resolve() != src.resolve():  # copied into a run of its own: never over another simulation
        state = claim_run_dir(out, info.simulation, job.force)
    out.mkdir(parents=True, exist_ok=True)
    with run_lock(out, "foam"):
        if state == "replace":
            remove_run(out)
        return _postprocess(src, out, p, seed, frame_dt, grids, job.show_progress, look_ahead, _threshold_names(ini),
                            job.arch, fluid)


def _postprocess_foreign(src: Path, out, job: FoamJob, params, ini, case, frames, domain, look_ahead) -> RunInfo:
    """A foreign sequence: imported into ``out`` as a bare sequence, then :func:`postprocess` of that run
    (with the sequence's time step, so the foam is that of the frames as given). The import writes all but
    the frames' files; the pass reads each frame from the sequence and writes it into the run (the same
    files and run.json as ``import`` then ``foam``, each frame read once and written on the writer's thread.
    bench_foam's 98k frames: the import was 82 ms of a 30-frame pass, but on 2 cores the copies' writing then
    shares the cores with the pass, 1.00-1.03x in all; meant for a GPU host, whose cores wait on its kernels)."""
    from ..cases.run_dir import reader_options, write_case
    from ..cases.sequence import read_sequence

    seq = read_sequence(src, frames=frames, xml=case, up=job.up, dt=job.dt, radius=job.radius, domain=domain)
    if out is None:
        raise InputError(f"{src}: not a whitecap run; pass --out DIR for the results")
    # Resolved before anything is written: a setting the sequence cannot satisfy leaves no run behind.
    p = params or resolve(Foam(), ini=ini, preset=job.preset, particle_mass=seq.particle_mass)
    if job.seed is not None:
        seq.notes["seed"] = job.seed  # the run's seed, so that `foam RUN` again makes the same foam
    def foam(_imported: RunInfo) -> RunInfo:  # under the import's lock, which cleans up after bad input
        return _postprocess_run(Path(out), None, replace(job, dt=seq.frame_dt, radius=None, force=False), p, ini,
                                look_ahead, fluid=(seq.fluid, reader_options(seq)))

    return write_case(seq, out, show_progress=job.show_progress, force=job.force, then=foam)


def run_obstacles(src: Path, info: RunInfo) -> list:
    """The SDFs of the obstacles run.json lists (an imported case's tank, obstacles and moving
    bodies), posed per frame from its ``bodies``; the first fluid frame tells a wall around the
    fluid from a solid (sim.obstacles.run_obstacle_grids)."""
    if not info.obstacles:
        return []
    from ..sim.obstacles import run_obstacle_grids

    fluid = info.files("fluid")
    first = read(src / fluid[0][1]).positions if fluid else None
    return run_obstacle_grids(info, src, first)


def _run_settings(src: Path, info: RunInfo) -> tuple[Foam, int, list]:
    """A whitecap run's own [foam] section, seed and obstacles (its scene's, else those run.json
    lists, as an imported case's)."""
    foam_cfg, grids = Foam(), []
    scene_file = src / "scene.toml"
    run_scene = None
    if scene_file.is_file():
        run_scene = load_scene(scene_file)
        run_scene.base_dir = info.extra.get("scene_dir", run_scene.base_dir)
        foam_cfg = run_scene.foam
        grids = obstacle_grids(run_scene)
    if run_scene is None or not run_scene.obstacle:
        grids = run_obstacles(src, info)
    return foam_cfg, int(info.extra.get("seed", 0)), grids


def _frame_dt(info: RunInfo, dt, radius) -> float:
    """The time between frames: ``dt`` when given, else the run's; ``radius`` is only checked (the
    run's particle radius is the one used)."""
    for opt, v in (("--dt", dt), ("--radius", radius)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise InputError(f"{opt}: must be a positive number of {'seconds' if opt == '--dt' else 'metres'} "
                             f"(got {v:g})")
    return dt or 1.0 / info.frame_rate


def _threshold_names(ini) -> dict[str, str]:
    """Where a parameter file set the thresholds it gives per particle ("f.ini: [DIFFUSE] KEMin"), for messages."""
    if ini is None:
        return {}
    f = ini if isinstance(ini, IniFile) else read_ini(ini)
    return {ours: where for ours, (where, _) in f.joules.items()}


def _postprocess(src: Path, out: Path, p: FoamParams, seed: int, frame_dt: float, grids: list, show_progress: bool,
                 look_ahead: bool, names: dict[str, str], arch: str = DEFAULT_ARCH,
                 fluid: tuple[list[tuple[int, Path]], dict] | None = None) -> RunInfo:
    info = RunInfo.load(src)  # read again under the lock: what is current cannot change from here on
    files = [(i, src / rel) for i, rel in info.files("fluid")] if fluid is None else fluid[0]
    reader = _Reader(files, {} if fluid is None else fluid[1])
    with timer("foam.setup"):  # (--profile: what a pass costs before its frames, as foam.look_ahead)
        first = reader.first()
        # Results go into the run; into another folder, the fluid frames are copied along so the
        # output is a complete run directory, which records itself before any file lands in it. Frames
        # read from a foreign sequence (``fluid``) are written into the run alike.
        convert = fluid is not None or out.resolve() != src.resolve()
        if convert and fluid is None:
            info = _start_copy(info, src, out)
        if p.model == "foamgenerator":  # FoamGenerator's count per particle and frame reaches 2 foamscale Δt
            p = replace(p, max_particles=max(p.max_particles or 0, FOAMGENERATOR_CAPACITY * len(first)))
        for d in (out, out / "diffuse", out / "fluid"):  # temporary files of a writer killed mid-file (kill -9)
            sweep_temps(d)
        stage = FoamStage(p, seed, verbose=True, obstacles=grids, arch=arch)
        stage.names = names
        stage.last_frame = files[-1][0] if files else None
        stage.start(info)
        identity = pass_identity(info, p, seed, frame_dt, look_ahead, files)
        done = _resume_point(out, info, identity, files, convert)
    if done is not None and done[0] == len(files):
        console.print(f"foam: {out}: the {len(files)} diffuse frames of this pass (seed {seed}) are complete; "
                      "nothing to do", soft_wrap=True)
        info.extra["out"], info.extra["made"] = str(out), 0
        return info
    if p.model == "foamgenerator":
        with timer("foam.look_ahead"):
            tau = _foamgenerator_limits(stage.generator, reader, show_progress)
        stage.generator.state.tau = tau
        info.extra["foam_limits"] = [float(t) for t in tau]  # ta, wc, ke [J], vo: min/max pairs
    elif p.auto and look_ahead:
        with timer("foam.look_ahead"):
            _calibrate(stage, reader, info, frame_dt)
    start = 0
    if done is not None:  # after the look-ahead, which sets the plan the record's corrections go into
        start, record = done
        stage.restore(record)
        reader.cache.clear()  # the frames before ``start`` are not read again
        console.print(f"foam: resuming at frame {files[start][0]} (frames {files[0][0]}-{files[start - 1][0]} "
                      "of this pass are complete)")
    else:
        _forget_earlier_pass(info, out)
    info.extra["foam_pass"] = {"identity": identity, "seed": seed}
    _run_frames(stage, reader, info, out, frame_dt, convert, show_progress, start, identity)
    info.save(out)
    info.extra["out"], info.extra["made"] = str(out), len(files) - start  # for the caller's message; not saved
    _report(stage)
    return info


class _Reader:
    """The run's fluid frames, each checked for velocities and finite values; the first and the sampled ones are
    kept. With :meth:`ahead`, frame k + 1 is read on a thread while frame k is processed (on a GPU the kernels run
    meanwhile; on the CPU the file's bytes come in while Taichi's kernels hold the GIL)."""

    def __init__(self, files: list[tuple[int, Path]], options: dict | None = None):
        self.files = files
        self.options = options or {}  # io.read's (a foreign sequence's up axis, its solver's own)
        self.cache: dict[int, ParticleFrame] = {}
        self._pool: ThreadPoolExecutor | None = None
        self._next: tuple[int, Future] | None = None

    def load(self, k: int) -> ParticleFrame:
        """Frame k read from its file (not kept), its positions and velocities checked to be finite: on the reader's
        thread where it is read ahead (the check's 2 ms a frame at 1 M particles on 2 cores off the loop's thread;
        NumPy lets go of the GIL for it), its error raised where the frame is taken (:meth:`read`)."""
        path = self.files[k][1]
        fr = read(path, **self.options)
        if fr.velocities is None:
            raise InputError(f"{path}: missing array 'velocity'")
        fr.check_finite()
        return fr

    def read(self, k: int, keep: bool = False) -> ParticleFrame:
        if k in self.cache:
            return self.cache.pop(k) if not keep else self.cache[k]
        if self._next is not None and self._next[0] == k:
            fr = self._next[1].result()  # its error (a bad file) raised here, for this frame
            self._next = None
        else:
            fr = self.load(k)
        if keep:
            self.cache[k] = fr
        return fr

    @contextlib.contextmanager
    def ahead(self) -> Iterator["_Reader"]:
        """Within the block, :meth:`read_next` starts reading a frame on a thread."""
        with ThreadPoolExecutor(1, thread_name_prefix="whitecap-foam-reader") as pool:
            self._pool = pool
            try:
                yield self
            finally:
                self._pool, self._next = None, None

    def read_next(self, k: int) -> None:
        """Frame k, read on the thread of :meth:`ahead` (unless kept, or past the last)."""
        if self._pool is not None and k < len(self.files) and k not in self.cache:
            self._next = (k, self._pool.submit(self.load, k))

    def first(self) -> ParticleFrame:
        return self.read(0, keep=True)


def _calibrate(stage: FoamStage, reader: _Reader, info: RunInfo, frame_dt: float) -> None:
    """'auto' from the whole sequence: potentials of frames sampled evenly across it."""
    from .budget import sample_count

    nf = len(reader.files)
    picks = sorted(set(np.linspace(0, nf - 1, sample_count(nf)).round().astype(int).tolist()))
    samples = []
    for k in picks:
        fr = reader.read(k, keep=k == 0)
        fr.time = info.frame(reader.files[k][0]).time
        samples.append(fr)
    times = np.array([info.frame(i).time for i, _ in reader.files], np.float64)
    # The fluid count between samples is taken as the nearest sample's (it changes only with in- or outflow).
    n_s = np.array([len(f) for f in samples], np.float64)
    n_fluid = n_s[np.abs(times[:, None] - np.array([f.time for f in samples])[None, :]).argmin(1)]
    stage.generator.calibrate(samples, times, n_fluid, frame_dt, [i for i, _ in reader.files],
                        [reader.files[k][0] for k in picks])


def _start_copy(info: RunInfo, src: Path, out: Path) -> RunInfo:
    """The record of the run's copy at ``out`` (another folder), saved there before any file is: the run's
    constants, obstacles and frames (times, poses, particle counts), with none of the source's files nor
    what describes them (the meshes' settings, the pictures' keys, the Blender scene, the scene file's
    hash), but those ``out`` already records as its own when it is a copy of this simulation made or begun
    before (its meshes, its frames until they are replaced); then an imported case's shape meshes, which are
    files of the run, copied along. The frames' files are recorded as they land (:func:`_run_frames`), so
    that a copy stopped half-way is a run whose listed frames are complete and whose every file is
    recorded, which the same command continues into rather than refuses."""
    own = RunInfo.load(out) if (out / RUN_JSON).is_file() else None  # claimed: this simulation's, or none
    before = {f.index: f.model_dump() for f in own.frames} if own is not None else {}
    data = json.loads(info.dumps())
    for f in data["frames"]:
        mine = before.pop(f["index"], {})
        f["files"], f["made_from"] = mine.get("files", {}), mine.get("made_from", {})
        for k in ("mesh_settings", "render_key"):
            if mine.get(k) is not None:
                f[k] = mine[k]
            else:
                f.pop(k, None)
    data["frames"] += [f for f in before.values() if f.get("files")]  # frames only the copy holds: its files
    for k in ("blend", "mesh", "scene_sha256", "foam_pass"):  # the copy's own (its pass: its diffuse frames)
        if own is not None and k in own.extra:
            data["extra"][k] = own.extra[k]
        else:
            data["extra"].pop(k, None)
    copy = RunInfo.model_validate(data)
    copy.frames.sort(key=lambda e: e.index)
    copy.save(out)
    for rel in own_meshes(copy.obstacles, copy.extra):
        if relpath_problem(rel) is None and (src / rel).is_file():  # never a path out of either run
            write_bytes(out / rel, (src / rel).read_bytes())
    return copy


def pass_identity(info: RunInfo, p: FoamParams, seed: int, frame_dt: float, look_ahead: bool,
                  files: list[tuple[int, Path]]) -> str:
    """What a post-processing pass's frames are a function of, hashed (SHA-256, 16 hex digits): the run's
    simulation and frame numbers, the resolved parameters, the seed, the time between frames, whether 'auto'
    looked ahead, the Taichi arch (CPU and GPU round differently) and whitecap's version. A pass continues only
    the frames of a pass with the same identity (:func:`_resume_point`)."""
    from .. import __version__
    from ..sim import runtime

    def plain(o):  # sets (FoamParams.explicit) in a fixed order; anything else as its text
        return sorted(o) if isinstance(o, (set, frozenset)) else str(o)

    doc = {"simulation": info.simulation, "frames": [i for i, _ in files], "params": dataclasses.asdict(p),
           "seed": int(seed), "frame_dt": float(frame_dt), "look_ahead": bool(look_ahead),
           "arch": runtime.current(), "version": __version__}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=plain).encode()).hexdigest()[:16]


#: The state's arrays that the frame's diffuse file holds exactly (float32 x, v, lifetime; uint32 ids): the
#: resume record (FOAM_RESUME) leaves them out, so that it stays a few kilobytes a frame
_IN_FRAME_FILE = ("positions", "velocities", "lifetime", "ids")


def _live_particles(path: Path, counts) -> dict[str, np.ndarray]:
    """The live particles a diffuse file holds (_IN_FRAME_FILE), checked against the state's last count row
    (spray, foam, bubbles alive); InputError naming the file where it is unreadable or holds other particles."""
    try:
        last = read(path)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: unreadable ({exc})") from None
    rows = np.asarray(counts, np.float64).reshape(-1, 5)
    live = int(rows[-1][2:].sum()) if len(rows) else 0
    if len(last) != live or "lifetime" not in last.arrays or last.velocities is None or last.ids is None:
        lifetime = "" if "lifetime" in last.arrays else " without a lifetime"
        raise InputError(f"{path}: holds {len(last)} diffuse particles{lifetime}, where the state counted {live}")
    return {"positions": last.positions, "velocities": last.velocities, "lifetime": last.arrays["lifetime"],
            "ids": last.ids}


def _with_live_particles(out: Path, data: dict) -> dict:
    """simulate's checkpoint of the stage (FoamStage.checkpoint) with the live particles read back from the
    diffuse file it names (a path inside the run: never read from anywhere else)."""
    rel = str(data["live_file"])
    problem = relpath_problem(rel)
    if problem is not None:
        raise InputError(f"{out / CHECKPOINT}: field '{FoamStage.name}/live_file': {problem}; start over with "
                         "`whitecap simulate --force`")
    path = out / rel
    try:
        live = _live_particles(path, data["counts"])
    except InputError as exc:
        raise InputError(f"{exc}: the checkpoint's diffuse particles are gone; start over with "
                         "`whitecap simulate --force`") from None
    return {**{k: v for k, v in data.items() if k != "live_file"}, **live}


def _keep_live_in_checkpoint(out: Path, removing: set[str]) -> None:
    """Before the diffuse files ``removing`` (relative to ``out``) leave the run: where simulate's checkpoint
    takes its live particles from one of them, they are written into the checkpoint itself (atomically, before
    the file goes), so that simulate still goes on from it. An unreadable checkpoint or file is left as it is
    (a resume from it then says which file)."""
    path = out / CHECKPOINT
    key = f"{FoamStage.name}/live_file"
    if not removing or not path.is_file():
        return
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
        if key not in data or str(data[key]) not in removing:
            return
        live = _live_particles(out / str(data[key]), data[f"{FoamStage.name}/counts"])
    except (OSError, ValueError, KeyError, InputError):
        return
    del data[key]
    write_arrays(path, {**data, **{f"{FoamStage.name}/{k}": v for k, v in live.items()}})


def _resume_record(stage: "FoamStage", index: int, identity: str) -> dict[str, np.ndarray]:
    """The pass's state after frame ``index`` without the live particles (their frame's file holds them):
    owned copies, for the writer's thread."""
    data = {k: np.array(v, copy=True) for k, v in stage.state_arrays(live=False).items()}
    data.update(frame=np.asarray(index, np.int64), identity=np.asarray(identity))
    return data


def _resume_point(out: Path, info: RunInfo, identity: str, files: list[tuple[int, Path]],
                  convert: bool) -> tuple[int, dict] | None:
    """Where a pass with this identity, stopped (Ctrl-C, kill -9, a full disk), left off: (the position in
    ``files`` of the first frame to make, the state to go on from), or None to start over. It continues only
    when run.json says the listed diffuse frames are this identity's, the record (FOAM_RESUME, written after
    its frame's run.json) is too, every frame up to the record's is listed and on disk (with its fluid copy, into
    another folder), and the record's frame's file holds as many particles as it counted."""
    path = out / FOAM_RESUME
    if (info.extra.get("foam_pass") or {}).get("identity") != identity or not path.is_file():
        return None
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
        if str(data.pop("identity")) != identity:
            return None
        index = int(data.pop("frame"))
        order = [i for i, _ in files]
        pos = order.index(index) if index in order else -1
        listed = {f.index: f.files for f in info.frames}
        kinds = ("diffuse", "fluid") if convert else ("diffuse",)
        if pos < 0 or any(k not in listed.get(i, {}) or not (out / listed[i][k]).is_file()
                          for i in order[:pos + 1] for k in kinds):
            return None
        data.update(_live_particles(out / listed[index]["diffuse"], data["counts"]))
    except (OSError, ValueError, KeyError, IndexError, InputError):
        return None  # an unreadable or partial record, or a file of other particles: the pass starts over
    return pos + 1, data


def _forget_earlier_pass(info: RunInfo, out: Path) -> None:
    """Before a pass writes its first frame, the diffuse frames of an earlier one (other settings, another seed,
    or simulate's own foam) leave run.json, then the run, with their counts.csv. A pass makes every frame anew
    from the first: one stopped half-way would otherwise list its frames beside the earlier pass's, a sequence
    made two ways that jumps where they meet (a stage never mixes frames). Only ``out``'s own files go."""
    old = [(f, f.files.pop("diffuse")) for f in info.frames if "diffuse" in f.files]
    for f, _ in old:
        f.made_from.pop("diffuse", None)
        f.changed()
    if old:
        info.save(out)  # first: run.json never lists a file that is gone
        _keep_live_in_checkpoint(out, {rel for _, rel in old})
    for _, rel in old:
        (out / rel).unlink(missing_ok=True)
    (out / COUNTS_CSV).unlink(missing_ok=True)
    (out / FOAM_RESUME).unlink(missing_ok=True)


def _run_frames(stage: FoamStage, reader: _Reader, info: RunInfo, out: Path, frame_dt: float, convert: bool,
                show_progress: bool, start: int, identity: str) -> None:
    """The frames from position ``start`` on through the generator; the fluid copied along into ``out`` when it
    is another folder. Each frame's files, then run.json listing them, then the pass's resume record
    (FOAM_RESUME) are handed to the writer in that order."""
    bar = progress(disable=not show_progress)
    with bar, FrameWriter(name="whitecap-foam-writer") as writer, reader.ahead():
        task = bar.add_task("foam", total=len(reader.files), completed=start, info="")
        for k in range(start, len(reader.files)):
            index = reader.files[k][0]
            with timer("foam.read"):  # what is left of reading the frame once the last one is computed
                fr = reader.read(k)
            reader.read_next(k + 1)  # on the reader's thread while this frame is processed
            fr.time = info.frame(index).time
            rel = stage.on_frame(fr, index, frame_dt, out, info)
            if convert:  # after the step: a frame that fails there leaves no file of its own behind
                fluid = frame_name("fluid", index)  # a copy of the file where it is already as written (PLY, z up)
                writer.submit(functools.partial(write_copy, out / fluid, fr, reader.files[k][1], **reader.options),
                              "fluid", lane="fluid")
                info.set_file(index, "fluid", fluid, fr.time)
            stage.write(writer)
            info.set_file(index, "diffuse", rel, fr.time)
            with timer("foam.records"):  # run.json's text, the resume record, the progress bar
                text, record = info.dumps(), _resume_record(stage, index, identity)
                c = stage.generator.state.counts[-1]
                bar.update(task, advance=1, info=f"{len(fr):,} fluid  spray {c[2]:,}  foam {c[3]:,}  bubbles {c[4]:,}")
            writer.submit(functools.partial(write_text, out / RUN_JSON, text), "run.json")
            writer.submit(functools.partial(write_arrays, out / FOAM_RESUME, record), "resume")


def _report(stage: FoamStage) -> None:
    stage.finish()
    counts = stage.generator.state.counts
    tot = np.array([r_[2:] for r_ in counts]).sum(0) if counts else np.zeros(3)
    console.print("diffuse particles over the run: " + ", ".join(f"{t} {int(v):,}" for t, v in zip(COUNT_NAMES, tot)))


def postprocess_params_file(
    ini: str | Path,
    src: str | Path | None = None,
    out: str | Path | None = None,
    case: str | Path | None = None,
    job: FoamJob | None = None,
    **options,
) -> RunInfo:
    """`whitecap foam [INPUT] --params FILE`: what a parameter file describes, then :func:`postprocess`
    as ``job`` says (``options``, :class:`FoamJob` fields, build one or replace its fields).

    A VisualSPHysics foam .ini (the file DualSPHysics users have) also names the
    job: input frames (InputDataPath, InputFilesPrefix, ZeroPadding and
    [TIMESTEPS]), output folder (OutputDataPath), case XML (XmlFile) and a
    custom domain. Arguments given here replace the file's.
    """
    from ..io.sequence import find_sequence

    run = with_options(FoamJob, job, options)
    f = read_ini(ini)
    spec = f.job
    if spec is None:
        if src is None:
            raise InputError(f"{f.path}: no [PATHS] InputDataPath; give the INPUT sequence as well")
        return postprocess(src, out=out, job=run, ini=f, case=case)
    if spec.exclusion_zone:
        raise InputError(f"{f.path}: [PATHS] ExclusionZoneFile = {spec.exclusion_zone}: exclusion zones are not "
                         "supported; leave it empty (a [DOMAIN] CustomDomain box is)")
    frames = None
    if src is None:
        if spec.input_dir is None:
            raise InputError(f"{f.path}: [PATHS] InputDataPath: missing; set it or give the INPUT sequence")
        if not spec.input_dir.is_dir():
            raise InputError(f"{f.path}: [PATHS] InputDataPath = {spec.input_dir}: no such directory")
        src = spec.input_dir
        if spec.first is not None:
            frames = _job_frames(f.path, spec)
        else:
            pattern = spec.input_dir / f"{spec.prefix}{'[0-9]' * spec.zero_padding}*.vtk"
            frames = [(i, q) for i, q in find_sequence(pattern) if spec.last is None or i <= spec.last]
    elif spec.first is not None or spec.last is not None:
        src_p = Path(src)
        if not (src_p.is_dir() and (src_p / "run.json").exists()):
            lo, hi = spec.first or 0, spec.last if spec.last is not None else float("inf")
            frames = [(i, q) for i, q in find_sequence(src_p) if lo <= i <= hi]
            if not frames:
                raise InputError(f"{f.path}: [TIMESTEPS]: no frame of {src} lies in {lo}..{hi}")
    if out is None:
        if spec.out is None:
            raise InputError(f"{f.path}: [PATHS] OutputDataPath: missing; set it or pass --out")
        out = spec.out
    if case is None and spec.xml is not None:
        if not spec.xml.is_file():
            raise InputError(f"{f.path}: [PATHS] XmlFile = {spec.xml}: file not found")
        case = spec.xml
    notes = [f"[OUTPUT] {', '.join(spec.outputs)}"] if spec.outputs else []
    if spec.out_prefix:
        notes.append(f"[PATHS] FilesOutputPrefix = {spec.out_prefix}")
    if notes:
        console.print(f"note: {f.path}: {'; '.join(notes)}: whitecap writes {out}/diffuse/diffuse_NNNNN.ply "
                      f"(`whitecap export {out} --to vtk` for VTK)", soft_wrap=True)
    return postprocess(src, out=out, job=run, ini=f, case=case, frames=frames, domain=spec.domain)


def _job_frames(path: Path, job) -> list[tuple[int, Path]]:
    """Frames StartingTimeStep..EndingTimeStep; like the VisualSPHysics simulator, the run ends
    at the first missing file (said once), and the first one must exist."""
    first = job.frame_path(job.first)
    if not first.is_file():
        raise InputError(f"{path}: [TIMESTEPS] StartingTimeStep = {job.first}: {first} not found")
    frames = []
    i = job.first
    while job.last is None or i <= job.last:
        q = job.frame_path(i)
        if not q.is_file():
            if job.last is not None:
                console.print(f"[yellow]warning:[/] {path}: [TIMESTEPS] EndingTimeStep = {job.last} but {q.name} "
                              f"is missing; frames {job.first}..{i - 1} are used", soft_wrap=True)
            break
        frames.append((i, q))
        i += 1
    return frames
