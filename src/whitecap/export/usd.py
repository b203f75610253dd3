"""USD: a whole run as one stage, through Pixar's ``usd-core`` (module ``pxr``).

Layout (for ``scene.usd``)::

    scene.usd                   the stage: World, camera, obstacles, clip metadata
    scene.manifest.usda         the attributes that come from the per-frame layers
    scene_frames/frame_NNNNN_<hash>.usdc   one frame's fluid and particles

The stage's metadata: metersPerUnit 1, upAxis Z, timeCodesPerSecond =
framesPerSecond = the run's frame rate; time code = frame index.

Prims::

    /World                      Xform (default prim; carries the value clips)
      fluid                     Mesh: points, faceVertexCounts, faceVertexIndices,
                                normals (vertex), velocities, extent; time-sampled
      fluid_particles           Points (runs without a surface instead of fluid)
      diffuse/spray|foam|bubble Points: points, widths, ids, velocities, extent
      obstacles/obstacle_K      Mesh (render mesh in its own coordinates); xformOp:transform
                                = its rest placement, and for a moving body before it
                                xformOp:translate and xformOp:orient per frame (run.json's pose)
      camera                    Camera: xformOp:transform, focalLength, apertures,
                                clippingRange (and fStop, focusDistance)

Per-frame layers (value clips). The fluid's topology changes every frame,
so nothing is shared between frames, and a 100k-vertex surface is about
7 MB per frame: a single file would hold the whole run in memory until it is
saved (a few GB for a long run). Each frame is therefore written as its own
small layer, a pure function of that frame's files, and the stage names them
as value clips (``clips`` on /World, clip k active from its frame on, holding
its samples until the next frame: motion blur within a frame comes from the
velocities). A frame layer's name carries a hash of its sources, so a rerun
reuses the frames whose sources did not change (resume), and a stage that is
replaced never points at frames of another simulation: the stage file is
renamed into place last, and only then are the frame layers that the replaced
stage named, and this one does not, removed. Nothing else in the frames folder
is touched: a file no whitecap stage listed is not whitecap's to delete. (``whitecap
export`` also lists every file in ``export.json`` before writing, so the next
export removes what an interrupted one left.)

Units of the camera: USD gives focal length and apertures in tenths of a
scene unit; with metersPerUnit 1 that is 1 dm, so the value in mm is
divided by 100.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import MissingDependency
from ..io.atomic import atomic_path
from ..io.cache import PointSet, SceneCache
from ..io.mesh import SurfaceMesh
from ..io.registry import SCENE, register

INSTALL_HINT = "install it with: pip install 'whitecap[usd]' (Pixar's usd-core)"
WORLD = "/World"
FLUID = "/World/fluid"
FLUID_POINTS = "/World/fluid_particles"
DIFFUSE = "/World/diffuse"
OBSTACLES = "/World/obstacles"
CAMERA = "/World/camera"
#: USD camera lengths are in tenths of a scene unit: mm → dm at metersPerUnit 1.
MM_PER_TENTH_UNIT = 100.0


def require_pxr():
    try:
        from pxr import Usd  # noqa: F401
    except ImportError:
        raise MissingDependency(f"USD export needs Pixar's 'usd-core' (module pxr), which is not installed; "
                                f"{INSTALL_HINT}") from None


def frames_dir(path: Path) -> Path:
    return path.parent / f"{path.stem}_frames"


def manifest_path(path: Path) -> Path:
    return path.parent / f"{path.stem}.manifest.usda"


#: a frame layer's name (frame_layer_path): frame index and 12 hex digits of its sources' hash
FRAME_LAYER_NAME = re.compile(r"^frame_\d{5,}_[0-9a-f]{12}\.usdc$")


def frame_layer_path(path: Path, index: int, fingerprint: str) -> Path:
    digest = hashlib.sha256(fingerprint.encode()).hexdigest()[:12]
    return frames_dir(path) / f"frame_{index:05d}_{digest}.usdc"


def point_path(name: str) -> str:
    return FLUID_POINTS if name == "fluid" else f"{DIFFUSE}/{name}"


def files(path: str | Path, cache: SceneCache) -> list[Path]:
    """Every file :func:`write_usd` writes for ``cache`` at ``path``."""
    path = Path(path)
    return [path, manifest_path(path)] + [frame_layer_path(path, i, cache.fingerprint(i)) for i, _ in cache.frames]


# ---------------------------------------------------------------------------- helpers
def _vec3f(a: np.ndarray):
    from pxr import Vt

    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, np.float32).reshape(-1, 3))


def _extent(points: np.ndarray, pad: float = 0.0):
    from pxr import Vt

    if len(points) == 0:
        return Vt.Vec3fArray(2)
    return _vec3f(np.array([points.min(0) - pad, points.max(0) + pad]))


def _matrix(m: np.ndarray):
    """A column-vector 4×4 as USD's row-vector Gf.Matrix4d."""
    from pxr import Gf

    return Gf.Matrix4d(np.asarray(m, float).T.tolist())


def _set_samples(attr, values: dict, convert: Callable) -> None:
    """One default value (key None) or one time sample per frame index."""
    from pxr import Usd

    for i, v in values.items():
        attr.Set(convert(v), Usd.TimeCode.Default() if i is None else Usd.TimeCode(i))


# ---------------------------------------------------------------------------- one frame
def frame_layer(cache: SceneCache, index: int):
    """An in-memory stage holding one frame: its fluid and particles as time samples at ``index``."""
    from pxr import Usd, UsdGeom, Vt

    g = cache.load(index)
    stage = Usd.Stage.CreateInMemory()
    stage.SetStartTimeCode(index)
    stage.SetEndTimeCode(index)
    t = Usd.TimeCode(index)
    if cache.has_mesh:
        mesh = g.mesh if g.mesh is not None else SurfaceMesh.empty()
        m = UsdGeom.Mesh.Define(stage, FLUID)
        m.CreatePointsAttr().Set(_vec3f(mesh.vertices), t)
        m.CreateFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(mesh.faces), 3, np.int32)), t)
        m.CreateFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(mesh.faces.reshape(-1)), t)
        # A frame without normals or velocities gets empty arrays: USD ignores arrays whose
        # length does not match the points (renderers then compute normals / skip blur).
        normals = mesh.normals if mesh.normals is not None else np.zeros((0, 3))
        m.CreateNormalsAttr().Set(_vec3f(normals), t)
        m.CreateVelocitiesAttr().Set(_vec3f(mesh.arrays.get("velocity", np.zeros((0, 3)))), t)
        m.CreateExtentAttr().Set(_extent(mesh.vertices), t)
    for name in cache.point_sets:
        ps = g.points.get(name) or PointSet(np.zeros((0, 3)), None, np.zeros(0), np.zeros(0))
        p = UsdGeom.Points.Define(stage, point_path(name))
        p.CreatePointsAttr().Set(_vec3f(ps.positions), t)
        p.CreateWidthsAttr().Set(Vt.FloatArray.FromNumpy(ps.widths), t)
        p.CreateIdsAttr().Set(Vt.Int64Array.FromNumpy(ps.ids), t)
        p.CreateVelocitiesAttr().Set(_vec3f(ps.velocities if ps.velocities is not None else np.zeros((0, 3))), t)
        pad = float(ps.widths.max()) / 2 if len(ps) else 0.0
        p.CreateExtentAttr().Set(_extent(ps.positions, pad), t)
    stage.GetRootLayer().customLayerData = {"whitecap:sources": cache.fingerprint(index)}
    return stage


# ---------------------------------------------------------------------------- the stage
def _define_prims(stage, cache: SceneCache) -> None:
    """World, the fluid and point-set prims (values come from the clips), obstacles, camera."""
    from pxr import Gf, Usd, UsdGeom, Vt

    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    stage.SetTimeCodesPerSecond(cache.frame_rate)
    stage.SetFramesPerSecond(cache.frame_rate)
    stage.SetStartTimeCode(cache.first)
    stage.SetEndTimeCode(cache.last)
    world = UsdGeom.Xform.Define(stage, WORLD)
    stage.SetDefaultPrim(world.GetPrim())
    if cache.has_mesh:
        m = UsdGeom.Mesh.Define(stage, FLUID)
        m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        m.CreateNormalsAttr()
        m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    if any(n != "fluid" for n in cache.point_sets):
        UsdGeom.Scope.Define(stage, DIFFUSE)
    for name in cache.point_sets:
        p = UsdGeom.Points.Define(stage, point_path(name))
        p.CreateWidthsAttr()
        p.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    if cache.obstacles:
        UsdGeom.Scope.Define(stage, OBSTACLES)
    for ob in cache.obstacles:
        m = UsdGeom.Mesh.Define(stage, f"{OBSTACLES}/{ob.name}")
        m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        m.CreatePointsAttr(_vec3f(ob.vertices))
        m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(ob.faces), 3, np.int32)))
        m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(ob.faces, np.int32).reshape(-1)))
        m.CreateExtentAttr(_extent(np.asarray(ob.vertices, np.float32)))
        m.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*ob.color)]))
        if ob.poses:  # translate and orient per frame (USD slerps the quaternion between frames)
            move, turn = m.AddTranslateOp(), m.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
            for i, (pos, q) in ob.poses.items():
                move.Set(Gf.Vec3d(*pos), Usd.TimeCode(i))
                turn.Set(Gf.Quatd(q[0], Gf.Vec3d(*q[1:])), Usd.TimeCode(i))
        m.AddTransformOp().Set(_matrix(ob.placement))
    cam = cache.camera
    if cam is not None:
        c = UsdGeom.Camera.Define(stage, CAMERA)
        _set_samples(c.AddTransformOp(), cam.matrices, _matrix)
        c.CreateProjectionAttr(UsdGeom.Tokens.perspective)
        wide = cam.sensor / MM_PER_TENTH_UNIT
        h, v = (wide, wide / cam.aspect) if cam.aspect >= 1 else (wide * cam.aspect, wide)
        c.CreateFocalLengthAttr(cam.lens / MM_PER_TENTH_UNIT)
        c.CreateHorizontalApertureAttr(h)
        c.CreateVerticalApertureAttr(v)
        c.CreateClippingRangeAttr(Gf.Vec2f(*cam.clip))
        if cam.fstop is not None and cam.focus:
            c.CreateFStopAttr(cam.fstop)
            _set_samples(c.CreateFocusDistanceAttr(), cam.focus, float)


def write_usd(path: str | Path, cache: SceneCache, advance: Callable[[str], None] | None = None) -> None:
    """Write ``cache`` as a USD stage at ``path`` (.usd or .usdc: binary; .usda: text) with
    one layer per frame beside it (see the module docstring). Frames whose layer already
    exists from the same sources are kept. ``advance(label)`` is called once per frame."""
    require_pxr()
    from pxr import Sdf, Usd, Vt

    path = Path(path)
    clips = []
    for i, _ in cache.frames:
        f = frame_layer_path(path, i, cache.fingerprint(i))
        if not f.is_file():
            one = frame_layer(cache, i)
            with atomic_path(f) as tmp:
                if not one.GetRootLayer().Export(str(tmp)):
                    raise OSError(f"USD could not write {f}")
        clips.append(f)
        if advance:
            advance(f.name)
    manifest = Usd.ClipsAPI.GenerateClipManifestFromLayers([Sdf.Layer.OpenAsAnonymous(str(clips[0]))], Sdf.Path(WORLD))
    with atomic_path(manifest_path(path)) as tmp:
        if not manifest.Export(str(tmp)):
            raise OSError(f"USD could not write {manifest_path(path)}")
    stage = Usd.Stage.CreateInMemory()
    _define_prims(stage, cache)
    # The clips: frame k's layer is active from its frame on and maps stage time to itself.
    api = Usd.ClipsAPI(stage.GetPrimAtPath(WORLD))
    api.SetClipPrimPath(WORLD)
    api.SetClipAssetPaths(Sdf.AssetPathArray([f"./{f.parent.name}/{f.name}" for f in clips]))
    api.SetClipManifestAssetPath(Sdf.AssetPath(f"./{manifest_path(path).name}"))
    api.SetClipActive(Vt.Vec2dArray([(float(i), float(k)) for k, (i, _) in enumerate(cache.frames)]))
    api.SetClipTimes(Vt.Vec2dArray([(float(i), float(i)) for i, _ in cache.frames]))
    before = previous_frames(path)
    with atomic_path(path) as tmp:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"USD could not write {path}")
    # The stage now names only this export's frames: drop those the replaced stage named
    # (earlier simulations, old settings), and nothing else.
    keep = {f.name for f in clips}
    for f in before:
        if f.name not in keep:
            f.unlink(missing_ok=True)


def previous_frames(path: Path) -> list[Path]:
    """The frame layers that the stage now at ``path`` (an earlier export) uses as value clips:
    files named as :func:`frame_layer_path` names them, in its frames folder. None when there
    is no readable stage there."""
    from pxr import Sdf

    if not path.is_file():
        return []
    try:
        layer = Sdf.Layer.OpenAsAnonymous(str(path))
        spec = layer.GetPrimAtPath(WORLD) if layer is not None else None
        clips = spec.GetInfo("clips") if spec is not None and spec.HasInfo("clips") else {}
        assets = [a.path for a in clips.get("default", {}).get("assetPaths", [])]
    except Exception:  # noqa: BLE001 -- not a stage of ours: it names no frames of ours
        return []
    folder = frames_dir(path)
    found = []
    for a in assets:
        f = path.parent / a
        if f.parent.resolve() == folder.resolve() and FRAME_LAYER_NAME.match(f.name):
            found.append(folder / f.name)
    return found


register("usd", (".usd", ".usdc", ".usda"), writer=write_usd, kind=SCENE)
