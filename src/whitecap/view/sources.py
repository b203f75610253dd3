"""Where frames come from: a written run, a numbered particle sequence, or a live solver.

Every source gives :class:`Frame` objects: fluid arrays and, when present,
diffuse particles (positions, type, radius).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config import DEFAULT_ARCH, DEFAULT_UP, Scene
from ..errors import InputError
from ..io import read
from ..io.record import Obstacle
from ..io.run import RUN_JSON, RunInfo
from ..io.sequence import find_sequence

if TYPE_CHECKING:  # types only: a live source imports the solver and the foam stage when it starts
    from ..diffuse.driver import FoamStage
    from ..diffuse.generator import FoamGenerator


@dataclass
class DeviceFluid:
    """A live solver's particle arrays where they live (CPU or GPU memory): the
    viewer colours and draws them with one kernel, without a copy to numpy."""

    x: Any  # positions, vec3 ndarray [m] (Taichi's ndarrays are typed Any)
    v: Any  # velocities, vec3 ndarray [m/s]
    rho: Any  # density, f32 ndarray [kg/m³]; current only when asked for
    n: int

    def host(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = self.n  # the live particles: the arrays hold the solver's capacity (emitters)
        return self.x.to_numpy()[:n], self.v.to_numpy()[:n], self.rho.to_numpy()[:n]


@dataclass
class Frame:
    index: int
    time: float
    positions: np.ndarray | None  # None for a live frame until as_dict() copies it from `device`
    velocities: np.ndarray | None = None
    density: np.ndarray | None = None
    diffuse_positions: np.ndarray | None = None
    diffuse_type: np.ndarray | None = None
    diffuse_radius: np.ndarray | None = None
    device: DeviceFluid | None = None
    bodies: list | None = None  # per obstacle, its pose (io.record.Pose; None: all at rest)

    def as_dict(self) -> dict:
        if self.positions is None and self.device is not None:
            self.positions, self.velocities, self.density = self.device.host()
        return {"positions": self.positions, "velocities": self.velocities, "density": self.density}

    @property
    def n_fluid(self) -> int:
        if self.device is not None:
            return self.device.n
        assert self.positions is not None  # a frame is live (device) or has its positions
        return len(self.positions)

    def counts(self) -> dict[str, int]:
        from ..io.diffuse_types import TYPE_NAMES

        c = {"fluid": self.n_fluid}
        if self.diffuse_type is not None:
            for t, name in enumerate(TYPE_NAMES):
                c[name] = int((self.diffuse_type == t).sum())
        return c


@dataclass
class Bounds:
    lower: np.ndarray
    upper: np.ndarray


# ----------------------------------------------------------------------------- playback
class PlaybackSource:
    """Frames read from disk on demand (with a small cache)."""

    live = False

    def __init__(self, path: str | Path, up: str = DEFAULT_UP):
        self.path = Path(path)
        self.up = up
        self.info: RunInfo | None = None
        self.diffuse: dict[int, Path] = {}
        if (self.path / RUN_JSON).is_file():
            self.info = RunInfo.load(self.path)
            fl = self.info.files("fluid")
            if not fl:
                raise InputError(f"{self.path / RUN_JSON}: no fluid frames listed")
            self.indices = [i for i, _ in fl]
            self.files = [self.path / rel for _, rel in fl]
            self.diffuse = {i: self.path / rel for i, rel in self.info.files("diffuse")}
            self.times = {f.index: self.info.time(f.index) for f in self.info.frames}
            self.bodies = {f.index: f.bodies for f in self.info.frames if f.bodies}
            d = self.info.domain
            bounds: Bounds | None = Bounds(np.asarray(d["lower"], float), np.asarray(d["upper"], float))
            radius: float | None = float(self.info.particle_radius)
        else:
            if not self.path.exists() and not any(c in str(path) for c in "*?["):
                raise InputError(f"{self.path}: no such run directory or particle sequence")
            seq = find_sequence(self.path)
            self.indices = [i for i, _ in seq]
            self.files = [q for _, q in seq]
            self.times = {}
            self.bodies = {}
            bounds = radius = None
        self._cache: dict[int, Frame] = {}
        first = self.frame(0)
        if bounds is None or radius is None:
            # Frame the first frame that has particles; a sequence of empty frames
            # shows an empty unit box.
            first = next((f for f in map(self.frame, range(len(self))) if f.n_fluid), first)
        positions = first.positions  # a frame read from disk has its positions
        assert positions is not None
        if bounds is None:
            if first.n_fluid:
                lo, hi = positions.min(axis=0), positions.max(axis=0)
            else:
                lo, hi = np.zeros(3), np.ones(3)
            bounds = Bounds(lo.astype(float), hi.astype(float))
        if radius is None:
            # Spacing estimate: the cube root of the volume per particle, halved.
            ext = np.maximum(bounds.upper - bounds.lower, 1e-6)
            radius = 0.5 * float(np.prod(ext) / max(len(positions), 1)) ** (1 / 3)
        self.bounds, self.radius = bounds, radius

    def __len__(self) -> int:
        return len(self.files)

    def frame(self, k: int) -> Frame:
        k = int(np.clip(k, 0, len(self.files) - 1))
        if k in self._cache:
            return self._cache[k]
        opts = {"up": self.up} if self.up != "z" else {}
        pf = read(self.files[k], **opts)
        pf.check_finite()  # NaN would be drawn at random places or break the colour map
        idx = self.indices[k]
        t = pf.time if pf.time is not None else self.times.get(idx, float(idx))
        fr = Frame(idx, float(t), pf.positions, pf.velocities, pf.density)
        fr.bodies = self.bodies.get(idx)
        dpath = self.diffuse.get(idx)
        if dpath is not None and dpath.is_file():
            dfr = read(dpath)
            dfr.check_finite()
            for name in ("type", "radius"):
                if name not in dfr.arrays:
                    raise InputError(f"{dpath}: missing array '{name}'")
            fr.diffuse_positions = dfr.positions
            fr.diffuse_type = np.asarray(dfr.arrays["type"], np.uint8)
            fr.diffuse_radius = np.asarray(dfr.arrays["radius"], np.float32)
        if len(self._cache) > 8:
            self._cache.pop(next(iter(self._cache)))
        self._cache[k] = fr
        return fr

    def obstacles(self) -> list[Obstacle]:
        return list(self.info.obstacles) if self.info else []

    def obstacle_base(self) -> list[Path]:
        """Where relative obstacle mesh paths are looked for: the scene's directory as the run
        recorded it, then the run directory."""
        scene_dir = self.info.extra.get("scene_dir") if self.info else None
        return ([Path(scene_dir)] if scene_dir else []) + [self.path]


# ----------------------------------------------------------------------------- live
@dataclass
class LiveSource:
    """A solver advanced frame by frame while the viewer shows it."""

    scene: Scene
    arch: str = DEFAULT_ARCH
    live: bool = True
    hook: FoamStage | None = None
    _initial: dict = field(default_factory=dict)

    def __post_init__(self):
        from ..sim.driver import build_solver

        self.solver = build_solver(self.scene, self.arch)
        self._initial = self.solver.checkpoint()
        self.index = 0
        self.steps = 0
        lo, hi = np.asarray(self.scene.domain.lower, float), np.asarray(self.scene.domain.upper, float)
        self.bounds = Bounds(lo, hi)
        self.radius = float(self.scene.solver.particle_radius)
        self._diffuse = None
        self._diffuse_index = -1
        self._foam_hook()

    def _foam_hook(self) -> None:
        """Diffuse particles from the diffuse stage's generator, when the scene has [foam] on."""
        from ..diffuse import simulation_hook
        from ..sim.driver import run_info_for

        if self.scene.foam.enabled:
            self.hook = simulation_hook(self.scene)
            self.hook.start(run_info_for(self.scene, self.solver), self.solver)  # the solver's obstacles

    @property
    def foam_params(self):
        """The live foam generator's parameters (a dataclass), or None."""
        gen = getattr(self.hook, "gen", None)
        return gen.p if gen is not None else None

    def _generator(self) -> FoamGenerator:
        """The live foam generator (the scene has [foam] on, and it has not failed)."""
        assert self.hook is not None and self.hook.gen is not None
        return self.hook.gen

    def set_foam_params(self, **kw) -> None:
        self._generator().with_params(**kw)

    def __len__(self) -> int:
        return self.index + 1

    def advance(self) -> int:
        """One output frame, or ``[view] steps_per_draw`` solver steps of it, so the
        window redraws while a frame is still being computed; returns the steps taken."""
        k = self.scene.view.steps_per_draw
        if not k:
            nsub = self.solver.advance_frame(self.index + 1)
            self.index += 1
            self.steps += nsub
            return nsub
        if getattr(self, "_left", 0) == 0:
            self._nsub = self.solver.substeps_for_frame()
            self._left = self._nsub
        dt = 1.0 / self.scene.solver.frame_rate / self._nsub
        n = min(k, self._left)
        for _ in range(n):
            self.solver.step(dt)
        self._left -= n
        self.steps += n
        if self._left == 0:
            self.index += 1
        return n

    def reset(self) -> None:
        self.solver.restore(self._initial)
        self.index = 0
        self._left = 0
        if self.hook is not None:
            from ..diffuse import DiffuseState

            self._generator().state = DiffuseState.empty()

    def current(self, with_density: bool = False) -> Frame:
        """The solver's state as a frame; its arrays stay on the device (see DeviceFluid)."""
        s = self.solver
        step_foam = self.hook is not None and self._diffuse_index != self.index
        if with_density and not step_foam:
            s.update_density()
        fr = Frame(self.index, float(s.time), None, device=DeviceFluid(s.state.x, s.state.v, s.state.rho, s.n))
        moving = next((c for c in s.colliders if getattr(c, "moving", False)), None)
        if moving is not None:  # moving bodies at their current pose
            fr.bodies = moving.body_records()
        if step_foam:  # once per output frame: the foam generator works on host arrays
            a = s.arrays(with_density=True)
            fr.positions, fr.velocities, fr.density = a["positions"], a["velocities"], a["density"]
            self._step_foam(fr, a)
        if self._diffuse is not None:
            fr.diffuse_positions, fr.diffuse_type, fr.diffuse_radius = self._diffuse
        return fr

    def _step_foam(self, fr: Frame, a: dict) -> None:
        try:
            from ..io import ParticleFrame

            pf = ParticleFrame(a["positions"], a["velocities"], a["ids"], a["density"], time=fr.time)
            dt = 1.0 / self.scene.solver.frame_rate
            assert self.hook is not None  # stepped only with a foam stage
            for g in self.hook.obstacles or []:  # obstacles (sim.obstacles.PosedSDF) at this pose, from the last
                g.at_frame(fr.time, fr.bodies[g.index] if fr.bodies else None, dt if self.index > 0 else 0.0)
            d = self._generator().step(pf, self.index, dt)
            self._diffuse = (d.positions, np.asarray(d.arrays["type"], np.uint8),
                             np.asarray(d.arrays["radius"], np.float32))
            self._diffuse_index = self.index
        except Exception as exc:  # the viewer carries on without diffuse particles
            import logging

            logging.getLogger("whitecap.view").warning("foam generator failed (%s); diffuse particles off", exc)
            self.hook, self._diffuse = None, None

    def obstacles(self) -> list[Obstacle]:
        return [Obstacle.model_validate(o.model_dump()) for o in self.scene.obstacle]  # as run.json lists them

    def obstacle_base(self) -> list[Path]:
        return [Path(self.scene.base_dir)]
