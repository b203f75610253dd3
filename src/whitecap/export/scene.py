"""``whitecap export RUN --to usd|abc``: a whole run as one animated scene for other tools.

The scene is the one the renderer builds (no Blender needed to describe it):

- the fluid surface per frame with normals and the velocities the meshing
  stage interpolated onto its vertices (splashsurf's SPH interpolation of the
  particle velocities, ``velocity`` in ``mesh/fluid_NNNNN.ply``); a run
  without surfaces exports its fluid particles as points instead, and says so;
- the diffuse particles, one point set per type (names from
  :mod:`whitecap.io.diffuse_types`), with ids, velocities and sphere diameters
  drawn per particle from the render radius range of its type
  (:func:`whitecap.render.scene.diffuse_radius`), at a quantile of that range
  fixed by the particle's id, so a particle keeps its size from frame to frame;
- the obstacles' render meshes with their rest placement and, when they
  move, ``run.json``'s pose per frame (together :func:`whitecap.geometry.obstacle_matrix`);
- the camera as the renderer places it (:func:`whitecap.render.stage.camera_keys`,
  framing at the final resolution's aspect).

The writers are the io registry's scene formats, registered by this package (``usd``:
:mod:`whitecap.export.usd`, ``abc``: :mod:`whitecap.export.alembic`). Output goes to ``RUN/export/<to>/scene.<to>``.
As for the ParaView series (:mod:`whitecap.export.series`), ``export.json`` there
lists whitecap's files (the USD frame layers too), extended before anything is
written; an export removes only listed files it did not write again. With ``--out``
outside the run, the run is only read (a shared lock) and may be read-only.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..config import Render, with_options
from ..errors import InputError
from ..geometry import obstacle_transform
from ..io import read, read_mesh, write_scene
from ..io.cache import CacheCamera, CacheObstacle, FrameGeometry, PointSet, SceneCache
from ..io.diffuse_types import TYPE_NAMES
from ..io.lock import export_locks
from ..io.record import OBSTACLE_COLOR
from ..io.run import RunInfo
from ..progress import progress
from ..render import stage
from ..render.scene import diffuse_radius
from . import SCENE_TARGETS, ExportJob
from .series import export_target, record_planned, replace_previous

#: Bumped when what a frame layer holds changes, so that a rerun rewrites old frame layers.
CACHE_VERSION = 1
#: Colour of an obstacle whose entry names none (the renderer's default stone).


# ---------------------------------------------------------------------------- one frame (pure)
def id_uniform(ids: np.ndarray, salt: int) -> np.ndarray:
    """A number in [0, 1) per id, the same for an id at every frame (SplitMix64 finaliser of id + salt)."""
    with np.errstate(over="ignore"):
        z = ids.astype(np.uint64) + np.uint64(salt) * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


#: Salt of the per-particle size draw (any fixed number; a particle keeps its size quantile when it changes type).
WIDTH_SALT = 1


def point_widths(ids: np.ndarray, radius: tuple[float, float]) -> np.ndarray:
    """Sphere diameters [m]: a radius in [min, max] per particle, at a quantile fixed by its id."""
    lo, hi = radius
    return 2.0 * (lo + (hi - lo) * id_uniform(ids, WIDTH_SALT))


def frame_geometry(run_dir: Path, files: dict, index: int, has_mesh: bool, point_sets: tuple[str, ...],
                   radii: dict[str, tuple[float, float]]) -> FrameGeometry:
    """The fluid surface and point sets of one frame, from the files ``files`` (kind -> path in the run)."""
    mesh = None
    if has_mesh and "mesh" in files:
        mesh = read_mesh(run_dir / files["mesh"])
        mesh.check_finite()
    points: dict[str, PointSet] = {}
    if "fluid" in point_sets and "fluid" in files:
        f = read(run_dir / files["fluid"])
        f.check_finite()
        points["fluid"] = PointSet(f.positions, f.velocities, f.ids, np.full(len(f), 2 * radii["fluid"][0]))
    if "diffuse" in files and any(n in TYPE_NAMES for n in point_sets):
        d = read(run_dir / files["diffuse"])
        d.check_finite()
        types = d.arrays.get("type", np.zeros(len(d), np.uint8))
        for code, name in enumerate(TYPE_NAMES):
            sel = types == code
            ids = d.ids[sel]
            points[name] = PointSet(d.positions[sel], None if d.velocities is None else d.velocities[sel], ids,
                                    point_widths(ids, radii[name]))
    return FrameGeometry(index=index, mesh=mesh, points=points)


def _fingerprint(run_dir: Path, simulation: str, files: dict, kinds: tuple[str, ...], radii: dict) -> str:
    """What a frame's geometry depends on: its source files (path, size, modification time) and the radii."""
    src = []
    for kind in kinds:
        if kind in files:
            st = (run_dir / files[kind]).stat()
            src.append([kind, files[kind], st.st_size, st.st_mtime_ns])
    return json.dumps({"v": CACHE_VERSION, "simulation": simulation, "files": src,
                       "radii": {k: list(v) for k, v in sorted(radii.items())}}, sort_keys=True)


# ---------------------------------------------------------------------------- the run
def build_cache(run_dir: Path, info: RunInfo, cfg: Render) -> SceneCache:
    """The run as a :class:`SceneCache`: frames, point sets, obstacles and camera."""
    has_mesh = bool(info.files("mesh"))
    has_diffuse = bool(info.files("diffuse"))
    kinds = ("mesh", "diffuse") if has_mesh else ("fluid", "diffuse")
    frames = [(f.index, float(info.time(f.index))) for f in info.frames if any(k in f.files for k in kinds)]
    if not frames:
        raise InputError(f"{run_dir / 'run.json'}: no mesh, fluid or diffuse frames to export")
    point_sets = (() if has_mesh else ("fluid",)) + (TYPE_NAMES if has_diffuse else ())
    r = info.particle_radius
    radii = {name: diffuse_radius(cfg, t, r) for t, name in enumerate(TYPE_NAMES) if name in point_sets}
    if "fluid" in point_sets:
        radii["fluid"] = (r, r)
    table = {f.index: dict(f.files) for f in info.frames}
    notes = []
    if not has_mesh:
        notes.append(f"{run_dir}: no surface meshes: exported points only (fluid and diffuse particles); "
                     f"run `whitecap mesh {run_dir}` for a fluid surface")

    def load(index: int) -> FrameGeometry:
        return frame_geometry(run_dir, table.get(index, {}), index, has_mesh, point_sets, radii)

    def fingerprint(index: int) -> str:
        return _fingerprint(run_dir, info.simulation, table.get(index, {}), kinds, radii)

    obstacles, boxes = [], []
    for k, entry in enumerate(info.obstacles):
        m = stage.obstacle_render_mesh(entry, info, run_dir)
        if m is None:
            notes.append(f"{run_dir / 'run.json'}: obstacles[{k}]: render mesh not found, left out")
            continue
        placement = obstacle_transform(entry)
        found = {i: info.body_pose(i, k) for i, _ in frames}
        poses = {}
        if any(p is not None for p in found.values()):  # a frame without a pose is at rest
            poses = {i: (list(p.position), list(p.quaternion)) if p is not None else ([0.0] * 3, [1.0, 0.0, 0.0, 0.0])
                     for i, p in found.items()}
        red, green, blue = entry.color or OBSTACLE_COLOR  # a colour is 3 numbers (record.Vec3)
        obstacles.append(CacheObstacle(f"obstacle_{k}", np.asarray(m.vertices), np.asarray(m.faces),
                                       (red, green, blue), placement, poses))
        rest = np.asarray(m.vertices) @ placement[:3, :3].T + placement[:3, 3]
        boxes.append(np.array([rest.min(0), rest.max(0)]))
    cache = SceneCache(frame_rate=info.frame_rate, frames=frames, has_mesh=has_mesh, point_sets=point_sets,
                       load=load, fingerprint=fingerprint, obstacles=obstacles, radii=radii, notes=notes)
    cache.camera = _camera(run_dir, info, cfg, frames, boxes, has_mesh)
    return cache


def _camera(run_dir: Path, info: RunInfo, cfg: Render, frames, boxes, has_mesh: bool) -> CacheCamera:
    """The renderer's camera: keyed over the meshed frames (as `whitecap render` renders them)."""
    keyed = [i for i, _ in info.files("mesh")] if has_mesh else [i for i, _ in frames]
    first, last = min(keyed), max(keyed)
    aspect = stage.image_aspect(cfg)
    keys, target = stage.camera_keys(cfg, info, stage.scene_bounds(run_dir, info, boxes), first, last, aspect)
    at = {i: keys[min(max(i, first), last)] for i, _ in frames}  # frames outside the keyed range hold
    moving = len({tuple(p) for p in at.values()}) > 1
    positions = at if moving else {None: next(iter(at.values()))}
    matrices = {i: stage.look_at_matrix(p, target) for i, p in positions.items()}
    focus = None
    if cfg.fstop is not None:
        point = np.asarray(cfg.focus_target or target, float)
        # Blender focuses on the plane through the focus point facing the camera.
        focus = {i: float(np.dot(point - m[:3, 3], -m[:3, 2])) for i, m in matrices.items()}
    return CacheCamera(matrices=matrices, lens=cfg.lens, sensor=stage.SENSOR_WIDTH, aspect=aspect,
                       clip=stage.camera_clip(keys[first], target), fstop=cfg.fstop, focus=focus)


def export_scene(run: str | Path, job: ExportJob | None = None, out: str | Path | None = None,
                 **options) -> dict[str, Path | str]:
    """Write ``run`` as one scene file (``RUN/export/<to>/scene.<to>`` unless ``out`` names a
    directory) as ``job`` says (``options``, its field names, build one or replace its fields;
    its ``to`` must be usd or abc). Returns {target: path}, plus {"note": ...} when the export
    left something out. ``jobs`` is checked as for the series (one process writes a scene)."""
    job = with_options(ExportJob, job, options)
    to, show_progress = job.to, job.show_progress
    run, out = export_target(run, to, SCENE_TARGETS, out, job.jobs, sub=to)
    with export_locks(run, out, "export"):
        from ..render.driver import render_settings

        info = RunInfo.load(run)
        cfg = render_settings(run)
        stage.image_size(cfg, False, run / "scene.toml")  # the camera's aspect comes from it
        cache = build_cache(run, info, cfg)
        path = out / f"scene.{to}"
        if to == "usd":
            from .usd import files

            written = {str(f.relative_to(out)) for f in files(path, cache)}
        else:
            written = {path.name}
        out.mkdir(parents=True, exist_ok=True)
        record_planned(out, info.simulation, written)
        with progress(disable=None if show_progress else True) as bar:
            task = bar.add_task(f"export {to}", total=len(cache.frames) + (to == "abc"), info="")
            write_scene(path, cache, fmt=to, advance=lambda label: bar.update(task, advance=1, info=label))
        replace_previous(out, info.simulation, written)
    result: dict[str, Path | str] = {to: path}
    if cache.notes:
        result["note"] = "; ".join(cache.notes)
    return result
