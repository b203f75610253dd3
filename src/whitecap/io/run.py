"""The run directory contract that every stage reads and writes.

    RUN/
      scene.toml                 resolved scene
      run.json                   metadata + per-frame file table (this module)
      fluid/fluid_NNNNN.ply      fluid particles (x y z vx vy vz density id)
      diffuse/diffuse_NNNNN.ply  diffuse particles (adds type lifetime radius)
      mesh/fluid_NNNNN.ply       reconstructed surfaces
      render/frame_NNNNN.png, render/movie.mp4, render/scene.blend

``run.json`` holds the format version, particle radius, rest density,
particle mass, gravity, domain box, frame rate and, per frame, its index,
simulated time and the files written for it, keyed by kind.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..errors import InputError
from .atomic import write_text

FORMAT_VERSION = 1
RUN_JSON = "run.json"

#: The six faces of the domain box, named by axis and side: "x-" is the face at domain.lower[0].
WALLS = ("x-", "x+", "y-", "y+", "z-", "z+")


def frame_name(kind: str, index: int, ext: str = "ply") -> str:
    """Relative file name of a frame: ``fluid/fluid_00012.ply``."""
    return f"{kind}/{kind}_{index:05d}.{ext}"


@dataclass
class RunInfo:
    particle_radius: float
    rest_density: float
    particle_mass: float
    gravity: list[float]
    domain: dict[str, list[float]]
    frame_rate: float
    frames: list[dict[str, Any]] = field(default_factory=list)
    obstacles: list[dict[str, Any]] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)
    format: str = "whitecap-run"
    version: int = FORMAT_VERSION
    up: str = "z"

    # ------------------------------------------------------------------ io
    @classmethod
    def load(cls, run_dir: str | Path) -> "RunInfo":
        p = Path(run_dir) / RUN_JSON
        if not p.is_file():
            raise InputError(f"{p}: not found (is {run_dir} a whitecap run directory?)")
        try:
            data = json.loads(p.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(f"{p}: malformed JSON: {exc}") from None
        known = {f for f in cls.__dataclass_fields__}
        missing = [k for k in ("particle_radius", "rest_density", "particle_mass", "frame_rate") if k not in data]
        if missing:
            raise InputError(f"{p}: missing field '{missing[0]}'")
        if data.get("version", 0) > FORMAT_VERSION:
            raise InputError(f"{p}: version {data['version']} is newer than this whitecap ({FORMAT_VERSION})")
        return cls(**{k: v for k, v in data.items() if k in known})

    def save(self, run_dir: str | Path) -> None:
        write_text(Path(run_dir) / RUN_JSON, json.dumps(asdict(self), indent=1))

    # ------------------------------------------------------------------ walls
    def solid_walls(self) -> list[str]:
        """The domain box faces that held the fluid in (names from :data:`WALLS`).

        ``extra.solid_walls`` when the run says; otherwise all six for a run
        that whitecap simulated (the solver confines particles to the box) and
        none for a converted foreign sequence (``extra.source``), whose box is
        only a bound.
        """
        walls = self.extra.get("solid_walls")
        if walls is None:
            walls = [] if "source" in self.extra else list(WALLS)
        return [w for w in WALLS if w in walls]

    # ------------------------------------------------------------------ frames
    def frame(self, index: int) -> dict[str, Any]:
        for f in self.frames:
            if f["index"] == index:
                return f
        f = {"index": index, "time": index / self.frame_rate, "files": {}}
        self.frames.append(f)
        self.frames.sort(key=lambda e: e["index"])
        return f

    def set_file(self, index: int, kind: str, relpath: str, time: float | None = None) -> None:
        f = self.frame(index)
        f["files"][kind] = relpath
        if time is not None:
            f["time"] = float(time)

    def files(self, kind: str) -> list[tuple[int, str]]:
        """(index, relative path) of every frame that has a file of this kind."""
        return [(f["index"], f["files"][kind]) for f in self.frames if kind in f["files"]]

    def truncate(self, last_index: int) -> None:
        """Forget frames after ``last_index`` (used when resuming)."""
        self.frames = [f for f in self.frames if f["index"] <= last_index]
