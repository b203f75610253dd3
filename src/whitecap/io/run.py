"""The run directory contract that every stage reads and writes.

    RUN/
      scene.toml                 resolved scene
      run.json                   metadata + per-frame file table (this module)
      fluid/fluid_NNNNN.ply      fluid particles (x y z vx vy vz density id)
      diffuse/diffuse_NNNNN.ply  diffuse particles (adds type lifetime radius)
      mesh/fluid_NNNNN.ply       reconstructed surfaces
      render/frame_NNNNN.png, render/movie.mp4, render/scene.blend

``run.json`` holds the format version, particle radius, rest density,
particle mass, gravity, domain box, frame rate, the simulation's identity
and, per frame, its index, simulated time, the files written for it keyed by
kind, (``made_from``) the identity of the simulation each file was made
from, and, in runs with moving obstacles, (``bodies``) each obstacle's pose
at that frame: position [m] and quaternion (w, x, y, z) of the rigid motion
from its rest placement (``geometry.obstacle_matrix`` composes the two). The
``obstacles`` entries name each body's collision ``mesh`` and ``render_mesh``.
The fields, their types and their defaults are the records of ``io/record.py``
(:class:`RunInfo` is its run record with the reading, writing and look-ups).

The identity (:func:`simulation_identity`) is a hash of the resolved scene
TOML, seed included; ``output.frames`` is left out so that extending a run
keeps it. A file recorded from another simulation is stale: loading drops its
entry, so every stage sees it as missing and makes it again. File entries
must be relative paths inside the run.
"""

from __future__ import annotations

import bisect
import contextlib
import hashlib
import json
import os
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .atomic import write_text
from .record import FORMAT_VERSION, HAVE_PYDANTIC, Frame, Pose, RunRecord, relpath_problem

RUN_JSON = "run.json"
#: where RunInfo.dumps puts the frame table's text into the rest of run.json's
_FRAMES_MARK = "\0frames\0"
#: scene keys (or whole sections) that do not change the simulated frames, left out of the identity
#: (checkpoints are where a resume starts: the frames after one are the same bytes whatever the interval)
IDENTITY_IGNORES = ("output.frames", "output.checkpoint_interval", "cluster")


def simulation_identity(scene_toml: str) -> str:
    """The identity of a simulation: SHA-256 (16 hex digits) of its resolved scene TOML, seed included."""
    data = tomllib.loads(scene_toml)
    for key in IDENTITY_IGNORES:
        *parents, leaf = key.split(".")
        d = data
        for k in parents:
            d = d.get(k, {})
        d.pop(leaf, None)
    text = json.dumps(data, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def source_identity(paths: list[Path], up: str, extra: object = None) -> str:
    """Identity of a foreign sequence (a run converted from another solver's files): the files'
    absolute names, sizes and modification times, the up axis, and ``extra`` (JSON) when given."""
    stats = [(str(Path(p).resolve()), Path(p).stat().st_size, Path(p).stat().st_mtime_ns) for p in paths]
    key = [up, stats] if extra is None else [up, stats, extra]
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]


def check_relpath(rel: Any, where: str) -> str:
    """``rel`` if it is a relative path that stays inside the run, else an InputError naming ``where``."""
    problem = relpath_problem(rel)
    if problem:
        raise InputError(f"{where}: {problem}")
    return rel


def _field(loc: tuple) -> str:
    """A field's location as run.json's readers write it: ``frames[1].bodies[0].quaternion``."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _one_line(exc: Any, p: Path) -> InputError:
    """The first error of a pydantic ValidationError as one line naming run.json and the field."""
    err = exc.errors()[0]
    field = _field(err["loc"])
    if err["type"] == "missing":
        return InputError(f"{p}: missing field '{field}'")
    if err["type"] == "value_error":
        return InputError(f"{p}: field '{field}': {err['ctx']['error']}")
    return InputError(f"{p}: field '{field}': {err['msg'].lower()}, got {err['input']!r}")


#: The six faces of the domain box, named by axis and side: "x-" is the face at domain.lower[0].
WALLS = ("x-", "x+", "y-", "y+", "z-", "z+")


def frame_name(kind: str, index: int, ext: str = "ply") -> str:
    """Relative file name of a frame: ``fluid/fluid_00012.ply``."""
    return f"{kind}/{kind}_{index:05d}.{ext}"


class RunInfo(RunRecord):
    """run.json (the fields: io/record.py's :class:`RunRecord`), read, looked up and written."""

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
        if not isinstance(data, dict):
            raise InputError(f"{p}: expected a JSON object, got {type(data).__name__}")
        if HAVE_PYDANTIC:
            from pydantic import ValidationError

            try:
                info = cls.model_validate(data)
            except ValidationError as exc:
                raise _one_line(exc, p) from None
        else:  # Blender's Python (the add-on): read as it is
            info = cls.model_validate(data)
        if info.version > FORMAT_VERSION:
            raise InputError(f"{p}: version {info.version} is newer than this whitecap ({FORMAT_VERSION})")
        info.frames.sort(key=lambda e: e.index)  # kept in index order (see _entry)
        for f in info.frames:  # entries made from another simulation are stale: forget them
            f.made_from = dict(f.made_from)  # written back even where the file had none
            for kind in [k for k in f.files if f.made_from.get(k, "") != info.simulation]:
                del f.files[kind]
                f.made_from.pop(kind, None)
        return info

    def save(self, run_dir: str | Path) -> None:
        write_text(Path(run_dir) / RUN_JSON, self.dumps())

    def dumps(self) -> str:
        """run.json's text, byte for byte ``json.dumps(self.model_dump(), indent=1)``.

        Stages save the run after every frame; dumping every entry anew made that quadratic (at 3000
        frames 120 ms a frame, and a deep copy of 60 ms for the background writer). Here each frame
        entry keeps its text (``Frame._text``) until it changes, so a save costs the new entries' text
        and a join. An entry's fields are changed by assignment or through the methods below, which
        say so (``Frame.changed``)."""
        head = self.model_dump(exclude={"frames"})
        top = {k: (_FRAMES_MARK if k == "frames" else head[k]) for k in type(self).model_fields
               if k == "frames" or k in head}
        texts = []
        for f in self.frames:
            kept: dict = f.__pydantic_private__  # type: ignore[assignment]  # Frame._text, without __getattr__
            if kept["_text"] is None:  # an entry nested two deep: its lines indented by two more spaces
                kept["_text"] = json.dumps(f.model_dump(), indent=1).replace("\n", "\n  ")
            texts.append(kept["_text"])
        frames = "[\n  " + ",\n  ".join(texts) + "\n ]" if texts else "[]"
        text, mark = json.dumps(top, indent=1), json.dumps(_FRAMES_MARK)
        at = text.index(mark)  # the first such string: only numbers come before "frames"
        return text[:at] + frames + text[at + len(mark):]

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
    def _entry(self, index: int) -> Frame | None:
        """The frame entry with this index, or None. The entries are kept sorted by index and are
        usually contiguous, so this is a direct look-up, else a binary search: stages ask for a
        frame's entry (its time, a body's pose) once per frame, and a scan made that O(frames²)."""
        fr = self.frames
        if not fr:
            return None
        k = index - fr[0].index
        if 0 <= k < len(fr) and fr[k].index == index:
            return fr[k]
        k = bisect.bisect_left(fr, index, key=lambda e: e.index)
        return fr[k] if k < len(fr) and fr[k].index == index else None

    def frame(self, index: int) -> Frame:
        """The frame entry with this index, made (at time index / frame rate, no files) if missing."""
        f = self._entry(index)
        if f is not None:
            return f
        f = Frame(index=index, time=index / self.frame_rate, files={}, made_from={})
        if not self.frames or self.frames[-1].index < index:
            self.frames.append(f)  # the usual case, a run's next frame: no sort of the whole table
        else:
            bisect.insort(self.frames, f, key=lambda e: e.index)
        return f

    def time(self, index: int) -> float:
        """Frame ``index``'s simulated time [s]: as recorded, else index / frame rate."""
        f = self._entry(index)
        return f.time if f is not None and f.time is not None else index / self.frame_rate

    def set_file(self, index: int, kind: str, relpath: str, time: float | None = None) -> None:
        """Record a file of this frame, made from the current simulation."""
        f = self.frame(index)
        f.files[kind] = check_relpath(relpath, f"run.json: frame {index}: {kind}")
        f.made_from[kind] = self.simulation
        f.changed()
        if time is not None:
            f.time = float(time)

    def set_bodies(self, index: int, bodies: list[Pose | dict]) -> None:
        """Record the pose of every obstacle at this frame (:class:`Pose`, or its dict), in scene
        order: the rigid motion from its rest placement."""
        self.frame(index).bodies = bodies  # type: ignore[assignment]  # validated on assignment: dicts become Poses

    def body_pose(self, index: int, k: int) -> Pose | None:
        """Obstacle ``k``'s pose at frame ``index`` (None: static, or not recorded: at rest)."""
        f = self._entry(index)
        b = (f.bodies or []) if f is not None else []
        return b[k] if k < len(b) else None

    def files(self, kind: str) -> list[tuple[int, str]]:
        """(index, relative path) of every frame that has a file of this kind."""
        return [(f.index, f.files[kind]) for f in self.frames if kind in f.files]

    def truncate(self, last_index: int) -> None:
        """Forget frames after ``last_index`` (used when resuming)."""
        self.frames = [f for f in self.frames if f.index <= last_index]


def obstacle_path(src: str, info: "RunInfo", run_dir: str | Path | None) -> Path | None:
    """Where an obstacle's mesh file (a ``mesh`` or ``render_mesh`` of run.json's ``obstacles``)
    is: absolute as given; a relative path in the scene's directory (``extra.scene_dir``,
    whitecap's own runs), else in the run directory (imported cases: cases/run_dir.py), else the
    working directory. None when not found. The one resolver the renderer and the diffuse stage use."""
    p = Path(src)
    if p.is_absolute():
        return p if p.is_file() else None
    bases = [Path(info.extra["scene_dir"])] if info.extra.get("scene_dir") else []
    bases += [Path(run_dir)] if run_dir is not None else []
    return next((b / p for b in bases + [Path(".")] if (b / p).is_file()), None)


# ============================================================================ what a run owns
#: The resume state of ``simulate`` (sim/driver.py), at the top of the run.
CHECKPOINT = "checkpoint.npz"
#: The resolved scene ``simulate`` writes; whitecap's own only while its SHA-256 is the one run.json records.
SCENE_FILE = "scene.toml"
#: Files at the top of a run that whitecap writes under these names and nothing else does.
#: The foam stage's live counts by frame (diffuse/driver.py), a file of the run beside its frames.
COUNTS_CSV = "diffuse/counts.csv"
#: Where a `foam` post-processing pass resumes from: its state after its last complete frame (diffuse/driver.py).
FOAM_RESUME = "diffuse/resume.npz"
OWN_TOP_FILES = (CHECKPOINT, "profile.json", "render/movie.mp4", COUNTS_CSV, FOAM_RESUME)
#: The writer lock's file (io/lock.py; named here too, since io/run.py sits below it).
_LOCK_FILE = ".whitecap.lock"


def _raw(run_dir: Path) -> dict | None:
    """run.json as stored (stale entries included: they name files whitecap wrote too), or None
    when there is none; a malformed one is refused, so nothing is ever removed on a guess."""
    p = run_dir / RUN_JSON
    if not p.is_file():
        return None
    try:
        data = json.loads(p.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: malformed JSON ({exc}); whitecap will not write into or clear this "
                         "directory: move it away or choose another --out") from None
    if not isinstance(data, dict):
        raise InputError(f"{p}: expected a JSON object, got {type(data).__name__}")
    return data


def scene_sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _scene_file_owned(run_dir: Path, data: dict | None) -> bool:
    """Is RUN/scene.toml the file whitecap wrote (its hash is in run.json)? A run from before the
    hash was recorded: whitecap's when it still describes the run's own simulation."""
    p = run_dir / SCENE_FILE
    if data is None or not p.is_file():
        return False
    recorded = (data.get("extra") or {}).get("scene_sha256")
    if recorded is not None:
        return hashlib.sha256(p.read_bytes()).hexdigest() == recorded
    try:
        return bool(data.get("simulation")) and simulation_identity(p.read_bytes().decode()) == data["simulation"]
    except (ValueError, tomllib.TOMLDecodeError):
        return False


def owned_files(run_dir: str | Path) -> list[Path]:
    """Every file in ``run_dir`` that whitecap recorded as its own: the files of every frame that
    run.json lists (of any simulation), the obstacle meshes an import wrote into the run, the
    Blender scene, the checkpoint, the stage profile, the scene file while unedited, and run.json
    itself (last). Only these are ever removed (:func:`remove_run`)."""
    run_dir = Path(run_dir)
    data = _raw(run_dir)
    if data is None:
        return []
    rels: list[str] = []
    for f in data.get("frames") or []:
        if isinstance(f, dict) and isinstance(f.get("files"), dict):
            rels += list(f["files"].values())
    extra = data.get("extra")
    if not isinstance(extra, dict):
        extra = {}
    rels += own_meshes(data.get("obstacles") or [], extra)
    blend = extra.get("blend")
    if isinstance(blend, dict) and isinstance(blend.get("file"), str):
        rels.append(blend["file"])
    rels += list(OWN_TOP_FILES)
    files, seen = [], set()
    for rel in rels:
        try:
            check_relpath(rel, "")
        except InputError:
            continue  # never follow a path out of the run
        p = run_dir / rel
        if rel not in seen and p.is_file():
            seen.add(rel)
            files.append(p)
    if _scene_file_owned(run_dir, data):
        files.append(run_dir / SCENE_FILE)
    return files + [run_dir / RUN_JSON]


def own_meshes(obstacles: list, extra: dict) -> list[str]:
    """The obstacle meshes that are files of the run itself (relative paths as run.json gives them): an
    imported case's shapes (cases/run_dir.py), in a run without ``extra.scene_dir``. A simulated run's
    are the scene's, in the scene's directory. ``obstacles``: run.json's entries, as dicts or records."""
    if "scene_dir" in extra:
        return []
    rels = []
    for o in obstacles:
        for k in ("mesh", "render_mesh"):
            v = o.get(k) if isinstance(o, dict) else getattr(o, k, None)
            if isinstance(v, str) and v not in rels:
                rels.append(v)
    return rels


def remove_run(run_dir: str | Path) -> list[Path]:
    """Remove what whitecap recorded as its own in ``run_dir`` (:func:`owned_files`), run.json last
    so that an interrupted removal leaves a run that a second one finishes; then the folders this
    emptied. A user's file, recorded nowhere, stays where it is. Returns the files removed."""
    run_dir = Path(run_dir)
    files = owned_files(run_dir)
    for p in files:
        p.unlink(missing_ok=True)
    for d in sorted({p.parent for p in files if p.parent != run_dir}, key=lambda d: -len(d.parts)):
        with contextlib.suppress(OSError):
            d.rmdir()  # only when empty
    return files


def _foreign(run_dir: Path) -> list[str]:
    """Entries of a directory without run.json that whitecap did not write: anything but the lock
    file, an atomic write's temporary file, and empty folders."""
    from .atomic import _TEMP_NAME

    found = []
    for top, dirs, names in os.walk(run_dir):  # stops at the third: --out may name a big folder
        dirs.sort()
        for name in sorted(names):
            if (name == _LOCK_FILE and Path(top) == run_dir) or _TEMP_NAME.match(name):
                continue
            found.append(str((Path(top) / name).relative_to(run_dir)))
            if len(found) >= 3:
                return found
    return found


def claim_run_dir(out: str | Path, identity: str, force: bool = False) -> str:
    """May a stage that makes a run of ``identity`` write into ``out``? The one rule that
    ``simulate``, ``import`` and ``foam --out`` share:

    - ``"new"``: ``out`` does not exist, is empty, or holds only whitecap's lock file;
    - ``"same"``: ``out`` is a run of this very simulation (continue it);
    - ``"replace"``: a run of another simulation, with ``force`` (the caller removes it with
      :func:`remove_run` once its own set-up has succeeded).

    Refused in one line: a run of another simulation without ``force``, and, whatever ``force``
    says, a directory holding files whitecap did not write (no run.json) or a file in the way.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: is a file, not a run directory")
    if not out.exists():
        return "new"
    data = _raw(out)
    if data is None:
        foreign = _foreign(out)
        if foreign:
            raise InputError(f"{out}: holds files whitecap did not write ({', '.join(foreign)}); whitecap writes "
                             "only into a new or empty directory or a run of its own: choose another --out")
        return "new"
    if data.get("simulation") == identity:
        return "same"
    if not force:
        what = (data.get("extra") or {}).get("source") or (data.get("extra") or {}).get("name") or "a whitecap scene"
        raise InputError(f"{out}: holds another simulation (made from {what}); pass --force to replace "
                         "it whole, or choose another --out")
    return "replace"


def check_scene_file(out: str | Path) -> None:
    """Refuse to write the resolved scene over a RUN/scene.toml that whitecap did not write (the
    user's own scene, or one edited since): comments and edits would be lost."""
    out = Path(out)
    p = out / SCENE_FILE
    if p.exists() and not _scene_file_owned(out, _raw(out)):
        raise InputError(f"{p}: not the scene whitecap wrote here (your own file, or edited since); whitecap "
                         "writes the resolved scene to this name: move the file, or choose another --out")


# ============================================================================ the domain of a foreign run
#: Margin around the flow on its four sides: a share of its extent along that axis, plus some
#: particle radii. Spray leaves the water ballistically and can land beyond where any fluid went
#: (over a tank's rim, off a free jet); the foam stage removes diffuse particles that leave the
#: domain, and the domain is only that bound (no grid is sized by it), so it errs on the side of room.
FLOW_MARGIN = 0.5
FLOW_MARGIN_RADII = 4.0
#: Room above the flow (or the case's shapes), as a share of their height, plus FLOW_MARGIN_RADII r.
FLOW_HEADROOM = 1.0
#: How run.json's ``extra.domain_rule`` names this rule. The floor is the lowest particle's bottom
#: (or the lowest shape): water rests on it, and the renderer puts its ground there.
DOMAIN_RULE = (f"the box of the fluid over all frames and the case's shapes, grown by {FLOW_MARGIN:g}x its "
               f"extent + {FLOW_MARGIN_RADII:g} r on the four sides and {FLOW_HEADROOM:g}x its height + "
               f"{FLOW_MARGIN_RADII:g} r above, its floor at the lowest particle's bottom")


def sequence_bounds(paths: list[Path], **read_kw) -> tuple[np.ndarray, np.ndarray] | None:
    """The box holding every particle of every frame (None when all frames are empty): the flow's
    reach, which a single frame does not show (a dam break travels far beyond its first frame). Each
    frame's positions and velocities are checked finite on the way (ParticleFrame.check_finite), as an
    import checks them, so that a bad frame is named before anything is made of the sequence."""
    from .registry import read

    box: tuple[np.ndarray, np.ndarray] | None = None
    for path in paths:
        fr = read(path, **read_kw)
        fr.check_finite()
        pos = fr.positions
        if len(pos):
            # column by column: NumPy's reduction along the rows of an (n, 3) array walks 3 values a row
            # (4 ms a 98k frame for min(0) against 0.1 for the three columns)
            a = np.array([pos[:, k].min() for k in range(3)], np.float64)
            b = np.array([pos[:, k].max() for k in range(3)], np.float64)
            box = (a, b) if box is None else (np.minimum(box[0], a), np.maximum(box[1], b))
    return box


def flow_domain(bounds: tuple[np.ndarray, np.ndarray], r: float) -> dict[str, list[float]]:
    """The domain of a run made from another solver's frames (``import`` and ``foam`` alike):
    :data:`DOMAIN_RULE` applied to ``bounds`` (:func:`sequence_bounds`, with any shapes' box)."""
    lo, hi = np.array(bounds[0], np.float64), np.array(bounds[1], np.float64)
    e = hi - lo
    margin = FLOW_MARGIN * e[:2] + FLOW_MARGIN_RADII * r
    lo[:2], hi[:2] = lo[:2] - margin, hi[:2] + margin
    lo[2], hi[2] = lo[2] - r, hi[2] + FLOW_HEADROOM * e[2] + FLOW_MARGIN_RADII * r
    return {"lower": [float(x) for x in lo], "upper": [float(x) for x in hi]}


def domain_text(domain: dict[str, list[float]]) -> str:
    """``(x, y, z) .. (x, y, z)``: a domain box for a message."""
    return " .. ".join("(" + ", ".join(f"{v:.4g}" for v in domain[k]) + ")" for k in ("lower", "upper"))


def refuse_inside_other_run(out: str | Path, own: str | Path | None, what: str) -> None:
    """A one-line error when the folder ``out`` (a stage's output outside its own run) lies in a
    whitecap run directory other than ``own``: its files would sit among another simulation's."""
    out = Path(out).resolve()
    own_r = Path(own).resolve() if own is not None else None
    for d in (out, *out.parents):
        if d == own_r:
            return
        if (d / RUN_JSON).is_file():
            raise InputError(f"{out}: lies in the run directory {d} of another simulation; {what} would mix its "
                             "files with that run's: choose a folder outside it")
