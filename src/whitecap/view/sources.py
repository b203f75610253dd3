"""Where frames come from: a written run, a numbered particle sequence, or a live solver.

Every source gives :class:`Frame` objects: fluid arrays and, when present,
diffuse particles (positions, type, radius).
"""

from __future__ import annotations

import glob
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import FORMATS, read
from ..io.run import RUN_JSON, RunInfo


@dataclass
class Frame:
    index: int
    time: float
    positions: np.ndarray
    velocities: np.ndarray | None = None
    density: np.ndarray | None = None
    diffuse_positions: np.ndarray | None = None
    diffuse_type: np.ndarray | None = None
    diffuse_radius: np.ndarray | None = None

    def as_dict(self) -> dict:
        return {"positions": self.positions, "velocities": self.velocities, "density": self.density}

    def counts(self) -> dict[str, int]:
        from .colors import DIFFUSE_NAMES

        c = {"fluid": len(self.positions)}
        if self.diffuse_type is not None:
            for t, name in enumerate(DIFFUSE_NAMES):
                c[name] = int((self.diffuse_type == t).sum())
        return c


@dataclass
class Bounds:
    lower: np.ndarray
    upper: np.ndarray


# ----------------------------------------------------------------------------- sequences
_NUM = re.compile(r"^(.*?)(\d+)$")


def find_sequence(path: str | Path) -> list[Path]:
    """Numbered particle files of one sequence, in frame order.

    ``path`` is a directory (the largest group of files sharing a name stem
    ``PREFIX<digits>.<ext>`` with a registered extension), one file of the
    sequence, or a glob pattern. Hand-written because the shared sequence
    reader (io/sequence.py) is not on this branch yet.
    """
    p = Path(path)
    if any(ch in str(path) for ch in "*?["):
        files = [Path(f) for f in glob.glob(str(path)) if Path(f).is_file()]
        if not files:
            raise InputError(f"{path}: no files match this pattern")
        return _numeric_sort(files)
    if p.is_file():
        m = _NUM.match(_stem(p)[0])
        if not m:
            return [p]
        pre, ext = m.group(1), _stem(p)[1]
        return _numeric_sort([q for q in p.parent.iterdir() if _key(q) == (pre, ext)])
    if p.is_dir():
        exts = tuple(e for f in FORMATS.values() if f.reader for e in f.extensions)
        groups: dict[tuple[str, str], list[Path]] = {}
        for q in p.iterdir():
            if q.is_file() and q.name.lower().endswith(exts) and _key(q):
                groups.setdefault(_key(q), []).append(q)
        if not groups:
            raise InputError(f"{p}: no numbered particle files ({', '.join(exts)}) and no {RUN_JSON}")
        return _numeric_sort(max(groups.values(), key=len))
    raise InputError(f"{p}: no such run directory or particle sequence")


def _stem(p: Path) -> tuple[str, str]:
    name = p.name
    for f in FORMATS.values():
        for e in f.extensions:
            if name.lower().endswith(e):
                return name[: -len(e)], e
    return p.stem, p.suffix


def _key(p: Path):
    stem, ext = _stem(p)
    m = _NUM.match(stem)
    return (m.group(1), ext) if m else None


def _numeric_sort(files: list[Path]) -> list[Path]:
    def num(q: Path) -> int:
        m = _NUM.match(_stem(q)[0])
        return int(m.group(2)) if m else -1

    return sorted(files, key=num)


# ----------------------------------------------------------------------------- playback
class PlaybackSource:
    """Frames read from disk on demand (with a small cache)."""

    live = False

    def __init__(self, path: str | Path, up: str = "z"):
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
            self.times = {f["index"]: f.get("time", f["index"] / self.info.frame_rate) for f in self.info.frames}
            self.radius = float(self.info.particle_radius)
            d = self.info.domain or {}
            self.bounds = Bounds(np.asarray(d["lower"], float), np.asarray(d["upper"], float)) if "lower" in d else None
        else:
            self.files = find_sequence(self.path)
            self.indices = list(range(len(self.files)))
            self.times = {}
            self.bounds = None
            self.radius = None
        self._cache: dict[int, Frame] = {}
        first = self.frame(0)
        if self.bounds is None:
            lo, hi = first.positions.min(axis=0), first.positions.max(axis=0)
            self.bounds = Bounds(lo.astype(float), hi.astype(float))
        if self.radius is None:
            # Spacing estimate: the cube root of the volume per particle, halved.
            ext = np.maximum(self.bounds.upper - self.bounds.lower, 1e-6)
            self.radius = 0.5 * float(np.prod(ext) / max(len(first.positions), 1)) ** (1 / 3)

    def __len__(self) -> int:
        return len(self.files)

    def frame(self, k: int) -> Frame:
        k = int(np.clip(k, 0, len(self.files) - 1))
        if k in self._cache:
            return self._cache[k]
        opts = {"up": self.up} if self.up != "z" else {}
        pf = read(self.files[k], **opts)
        idx = self.indices[k]
        t = pf.time if pf.time is not None else self.times.get(idx, float(idx))
        fr = Frame(idx, float(t), pf.positions, pf.velocities, pf.density)
        dpath = self.diffuse.get(idx)
        if dpath is not None and dpath.is_file():
            dfr = read(dpath)
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

    def obstacles(self) -> list[dict]:
        return list(self.info.obstacles) if self.info else []

    def obstacle_base(self) -> Path:
        """Where relative obstacle mesh paths start: the scene's directory when the run recorded it."""
        scene_dir = (self.info.extra.get("scene_dir") if self.info else None) or self.path
        return Path(scene_dir)


# ----------------------------------------------------------------------------- live
@dataclass
class LiveSource:
    """A solver advanced frame by frame while the viewer shows it."""

    scene: object
    arch: str = "cpu"
    live: bool = True
    hook: object | None = None
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
        self._foam_hook()

    def _foam_hook(self) -> None:
        """Use the foam stage's live hook when it exists (optional)."""
        try:
            from .. import foam

            make = getattr(foam, "simulation_hook", None)
            if make is not None and self.scene.foam.enabled:
                self.hook = make(self.scene)
        except Exception:  # the foam stage is optional for viewing
            self.hook = None

    def __len__(self) -> int:
        return self.index + 1

    def advance(self) -> int:
        """One output frame; returns the substeps taken."""
        nsub = self.solver.advance_frame(self.index + 1)
        self.index += 1
        self.steps += nsub
        return nsub

    def reset(self) -> None:
        self.solver.restore(self._initial)
        self.index = 0
        self._diffuse = None

    def current(self, with_density: bool = False) -> Frame:
        a = self.solver.arrays(with_density=with_density)
        fr = Frame(self.index, float(self.solver.time), a["positions"], a["velocities"], a["density"])
        if self.hook is not None:
            self._run_hook(fr, a)
        return fr

    def _run_hook(self, fr: Frame, a: dict) -> None:
        try:
            from ..io import ParticleFrame

            if self.index == 0 and hasattr(self.hook, "on_start"):
                self.hook.on_start(self.solver, None, None)
            pf = ParticleFrame(a["positions"], a["velocities"], a["ids"], a["density"], time=fr.time)
            res = self.hook.on_frame(pf, self.index, 1.0 / self.scene.solver.frame_rate, None, None)
            d = getattr(self.hook, "diffuse", None) or (res if isinstance(res, object) and hasattr(res, "arrays") else None)
            if d is not None and hasattr(d, "arrays"):
                fr.diffuse_positions = d.positions
                fr.diffuse_type = np.asarray(d.arrays["type"], np.uint8)
                fr.diffuse_radius = np.asarray(d.arrays["radius"], np.float32)
        except Exception:
            self.hook = None  # the hook's interface may differ; the viewer carries on without diffuse

    def obstacles(self) -> list[dict]:
        return [o.model_dump() for o in self.scene.obstacle]

    def obstacle_base(self) -> Path:
        return Path(self.scene.base_dir)
