"""The place a run is shown in: container, sky, ground, camera framing (bpy calls only where noted).

:func:`build_scene` in :mod:`whitecap.render.scene` calls these steps; the
pure-numpy parts (sun direction, framing, paths) run without Blender, so the
render driver and the tests can use them too.

Container. The domain box's solid walls are drawn as a tank: walls and floor
of real thickness outside the box, open at the top. ``glass`` is a clear
dielectric of IOR 1.5; ``basin`` is opaque concrete, seen from higher up. The fluid
mesh reaches the walls (the meshing stage moves the vertices facing a solid
wall onto it, see :func:`whitecap.surface.reconstruct.close_wall_gap`), and
the glass's inner faces sit :data:`GLASS_OVERLAP` r inside the box, so the
water overlaps the glass slightly. That is the usual way of modelling liquid
in a glass for a path tracer: two coincident surfaces flicker between each
other, and any gap is a film of air that shows as a bright silver line of
total internal reflection; a thin overlap has neither, and the error it makes
(refraction at the water surface inside the glass uses the water/air ratio
1.33 instead of the water/glass ratio 1.33/1.5) bends rays by a few degrees
over a sub-millimetre layer, which nothing shows.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..config import Render
from ..errors import InputError
from ..io.record import Obstacle
from ..io.run import RunInfo, obstacle_path

#: The glass's inner faces sit this many particle radii inside the domain box, under the water's edge.
GLASS_OVERLAP = 0.1
#: Blender's physical skies are in physical units, several times brighter than a sun lamp of a few
#: W/m²; this scale, chosen by eye on preview frames (exposure 0, the default 3 W/m² sun), lets the sky fill the
#: shadows without washing out the sun's light.
SKY_SCALE = 0.2
#: Window glass (soda-lime) refractive index.
GLASS_IOR = 1.5
#: Container wall thickness when [render].wall_thickness is unset, in particle radii.
WALL_RADII = 2.5
#: Share of the image that the fluid's bounds fill along the tighter direction when the camera frames them.
FRAME_FILL = 0.9
#: Direction from the framed point to the default camera: in front (−y), a little right, above.
VIEW_DIRECTION = (0.35, -1.0, 0.55)
#: The same for an opaque basin, from high enough to see over its front wall.
VIEW_DIRECTION_BASIN = (0.15, -0.35, 1.0)
#: Frames whose bounds are read to frame the camera (evenly spread over the run).
FRAMING_SAMPLES = 16
#: Bounds of a frame leave out this share of its vertices on each side (a stray droplet does not widen the shot).
FRAMING_TRIM = 0.002
#: Blender's default camera sensor width [mm] (the wider image side with sensor_fit AUTO).
SENSOR_WIDTH = 36.0


# ============================================================================ pure helpers
def sun_direction(angles_deg) -> np.ndarray:
    """Unit vector toward the sun for a sun lamp with Euler XYZ rotation ``angles_deg``.

    A Blender sun lamp shines along its local −z, so the sun lies along R·(0, 0, 1).
    """
    x, y, z = (math.radians(a) for a in angles_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(x), -math.sin(x)], [0, math.sin(x), math.cos(x)]])
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    rz = np.array([[math.cos(z), -math.sin(z), 0], [math.sin(z), math.cos(z), 0], [0, 0, 1]])
    return rz @ ry @ rx @ np.array([0.0, 0.0, 1.0])


def sky_sun_angles(direction) -> tuple[float, float]:
    """(sun_elevation, sun_rotation) [rad] of Blender's sky texture for a sun along ``direction``.

    The sky puts its sun at (cos e · sin ρ, cos e · cos ρ, sin e): rotation ρ is
    measured from +y toward +x (checked by rendering the sun disc of the
    MULTIPLE_SCATTERING sky with bpy 5.0.1 at ρ = 40° and 100°).
    """
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    return math.asin(max(-1.0, min(1.0, d[2]))), math.atan2(d[0], d[1])


def environment_path(cfg: Render, info: RunInfo, run_dir: Path) -> Path | None:
    """The HDRI file of ``[render].environment``, resolved against the scene's directory; a missing one is an error."""
    if not cfg.environment:
        return None
    p = Path(cfg.environment)
    if not p.is_absolute():
        p = Path(info.extra.get("scene_dir", run_dir)) / p
    if not p.is_file():
        raise InputError(f"{run_dir / 'scene.toml'}: render.environment: file not found: {p}")
    if p.suffix.lower() not in (".hdr", ".exr"):
        raise InputError(f"{run_dir / 'scene.toml'}: render.environment: expected an .hdr or .exr image, got {p.name}")
    return p


def has_own_container(info: RunInfo) -> bool:
    """Whether the run brings its own tank: an obstacle with role "container" (an imported case)."""
    return any(o.role == "container" for o in info.obstacles)


def container_kind(cfg: Render, info: RunInfo) -> str:
    """``[render].container``, or its default: glass where the run's walls held the fluid, else none.
    A run with a container of its own (an imported tank: an obstacle with role "container") gets
    none: its tank is drawn as that obstacle, and a second glass box around the domain would hide it."""
    if has_own_container(info) or cfg.sea:  # the sea runs on where the walls were (render/sea.py)
        return "none"
    if cfg.container is not None:
        return cfg.container
    return "glass" if info.solid_walls() else "none"


def wall_thickness(cfg: Render, info: RunInfo) -> float:
    return cfg.wall_thickness if cfg.wall_thickness else WALL_RADII * info.particle_radius


def fluid_bounds(run_dir: Path, info: RunInfo) -> tuple[np.ndarray, np.ndarray] | None:
    """Bounds of the fluid over the run: the union of per-frame bounds of up to
    FRAMING_SAMPLES meshes (or particle files where there are no meshes), each
    trimmed by FRAMING_TRIM on both sides. None when no frame has any fluid."""
    from ..io import read, read_mesh

    kind = "mesh" if info.files("mesh") else "fluid"
    files = info.files(kind)
    if not files:
        return None
    pick = sorted(set(np.linspace(0, len(files) - 1, min(FRAMING_SAMPLES, len(files))).round().astype(int)))
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for k in pick:
        path = run_dir / files[k][1]
        if kind == "mesh":
            pts = read_mesh(path).vertices
        else:
            pts = read(path).positions
        if len(pts) == 0:
            continue
        if len(pts) > 1000:
            q = np.quantile(pts, [FRAMING_TRIM, 1 - FRAMING_TRIM], axis=0)
        else:
            q = np.array([pts.min(0), pts.max(0)])
        lo, hi = np.minimum(lo, q[0]), np.maximum(hi, q[1])
    if not np.isfinite(lo).all():
        return None
    return lo, hi


def frame_box(lo, hi, target, direction, lens: float, aspect: float, fill: float = FRAME_FILL) -> float:
    """Distance from ``target`` along ``direction`` at which the box [lo, hi] just fits
    ``fill`` of a pinhole image (width/height ``aspect``, focal length ``lens`` mm on a
    SENSOR_WIDTH mm sensor across the wider side), the camera looking at ``target`` with z up."""
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    fwd = -u
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    half_w = SENSOR_WIDTH / 2 / lens if aspect >= 1 else SENSOR_WIDTH / 2 / lens * aspect
    half_h = half_w / aspect
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    q = corners - np.asarray(target, float)
    need = np.maximum(np.abs(q @ right) / (fill * half_w), np.abs(q @ up) / (fill * half_h)) + q @ u
    return float(need.max())


def camera_path(cfg: Render, info: RunInfo, bounds=None, aspect: float = 4 / 3) -> tuple[list, list, list]:
    """Camera positions at the first and last frame and the target point.

    Camera keys that are set are used as they are. Unset, the camera looks at
    the centre of ``bounds`` (the fluid over the run and the obstacles; the
    domain when None) from VIEW_DIRECTION, at the distance where the bounds
    fill FRAME_FILL of the image along the tighter direction.
    """
    if bounds is None:
        bounds = (np.array(info.domain["lower"], float), np.array(info.domain["upper"], float))
    lo, hi = (np.asarray(b, float) for b in bounds)
    target = np.array(cfg.camera_target, float) if cfg.camera_target else (lo + hi) / 2
    if cfg.camera_start:
        start = np.array(cfg.camera_start, float)
    else:
        # An opaque tank, drawn (basin) or the case's own (an imported container), is seen from high
        # enough to look over its front wall; a glass one (a closed tank, cases/splishsplash.py) from the side.
        opaque = container_kind(cfg, info) == "basin" or any(
            o.role == "container" and o.material != "glass" for o in info.obstacles)
        view = VIEW_DIRECTION_BASIN if opaque else VIEW_DIRECTION
        dist = frame_box(lo, hi, target, view, cfg.lens, aspect)
        u = np.asarray(view, float) / np.linalg.norm(view)
        start = target + dist * u
    end = np.array(cfg.camera_end, float) if cfg.camera_end else start
    return start.tolist(), end.tolist(), target.tolist()


def _box_mesh(lo, hi, thickness: float, inset: float, top: float):
    """An open-top tank around the box [lo, hi]: outer shell ``thickness`` outside it, cavity
    ``inset`` inside it, both up to height ``top``. Vertices (16, 3) and quads (14, 4)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    o_lo, o_hi = lo - thickness, hi + thickness
    i_lo, i_hi = lo + inset, hi - inset

    def ring(a, b, z):
        return [[a[0], a[1], z], [b[0], a[1], z], [b[0], b[1], z], [a[0], b[1], z]]

    v = np.array(ring(o_lo, o_hi, o_lo[2]) + ring(o_lo, o_hi, top) + ring(i_lo, i_hi, top) + ring(i_lo, i_hi, i_lo[2]))
    quads = [[0, 3, 2, 1], [12, 13, 14, 15]]  # outer bottom, cavity floor
    for k in range(4):
        k1 = (k + 1) % 4
        quads.append([k, k1, 4 + k1, 4 + k])  # outer side
        quads.append([4 + k, 4 + k1, 8 + k1, 8 + k])  # rim
        quads.append([8 + k, 8 + k1, 12 + k1, 12 + k])  # inner side
    return v, np.array(quads)


# ============================================================================ bpy steps
def set_exposure(sc, cfg: Render) -> None:
    """AgX view transform with ``[render].exposure`` stops."""
    # The list of view transforms is a dynamic enum whose bl_rna items do not
    # show AgX in a background bpy, so ask for it and fall back on a refusal.
    try:
        sc.view_settings.view_transform = "AgX"
    except TypeError:
        sc.view_settings.view_transform = "Filmic"
    sc.view_settings.exposure = cfg.exposure


def add_environment(sc, cfg: Render, hdri: Path | None, preview: bool = False):
    """The world: the user's HDRI, or Blender's physical sky with a sun lamp where the sky has its sun.

    In preview the physical sky is not sampled as a light: without its sun
    (the lamp carries it) it is smooth, so rays that hit it by chance light
    the scene well enough at 16 samples, and each bounce saves a shadow ray
    (measured: about a quarter of a preview frame's CPU time). An HDRI, which
    may hold a sun of its own, is always sampled.
    """
    import bpy

    world = bpy.data.worlds.new("whitecap_sky")
    sc.world = world
    world.use_nodes = True
    nt = world.node_tree
    bg = nt.nodes.get("Background")
    bg.inputs["Strength"].default_value = cfg.world_strength
    if hdri is not None:
        tex = nt.nodes.new("ShaderNodeTexEnvironment")
        tex.image = bpy.data.images.load(str(hdri), check_existing=True)
        nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
        return None
    bg.inputs["Strength"].default_value = cfg.world_strength * SKY_SCALE
    sky = nt.nodes.new("ShaderNodeTexSky")
    sky.sky_type = cfg.sky_type
    d = sun_direction(cfg.sun_angle)
    if cfg.sky_type in ("PREETHAM", "HOSEK_WILKIE"):
        sky.sun_direction = d.tolist()
    else:
        sky.sun_elevation, sky.sun_rotation = sky_sun_angles(d)
        # The sun's light comes from the lamp below, which Cycles samples
        # directly; a sun disc in the sky map would only add noise.
        sky.sun_disc = False
    nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    if preview:
        world.cycles.sampling_method = "NONE"
    sun_data = bpy.data.lights.new("sun", "SUN")
    sun_data.energy = cfg.sun_strength
    sun_data.angle = math.radians(1.0)
    sun = bpy.data.objects.new("sun", sun_data)
    sun.rotation_euler = [math.radians(a) for a in cfg.sun_angle]
    sc.collection.objects.link(sun)
    return sun


def _tiles(nt, coord, tile: float, colours, mortar):
    """Square tiles of edge ``tile`` [m] (a Brick texture without offset) in object space."""
    b = nt.nodes.new("ShaderNodeTexBrick")
    b.offset = 0.0
    b.squash = 1.0
    b.inputs["Scale"].default_value = 1.0
    b.inputs["Brick Width"].default_value = tile
    b.inputs["Row Height"].default_value = tile
    b.inputs["Mortar Size"].default_value = 0.04 * tile
    b.inputs["Bias"].default_value = 0.0
    b.inputs["Color1"].default_value = (*colours[0], 1.0)
    b.inputs["Color2"].default_value = (*colours[1], 1.0)
    b.inputs["Mortar"].default_value = (*mortar, 1.0)
    nt.links.new(coord, b.inputs["Vector"])
    return b


def surface_material(name: str, texture: str, tile: float, preview: bool = False):
    """An opaque material with a procedural ``texture`` (tiles, checker, concrete) of feature size ``tile`` [m].

    In preview the noise bump is left out: a Bump node evaluates its height
    three times per shading point, about a tenth of a preview frame's CPU time
    where the ground fills the frame (bench_render.py), for relief that 320x240
    pixels hardly show; colours and tiles stay."""
    import bpy

    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes.get("Principled BSDF")
    coord = nt.nodes.new("ShaderNodeTexCoord").outputs["Object"]
    noise = nt.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 4.0 / tile
    nt.links.new(coord, noise.inputs["Vector"])
    if texture == "checker":
        tex = nt.nodes.new("ShaderNodeTexChecker")
        tex.inputs["Scale"].default_value = 1.0 / tile
        tex.inputs["Color1"].default_value = (0.75, 0.74, 0.7, 1.0)
        tex.inputs["Color2"].default_value = (0.12, 0.13, 0.14, 1.0)
        nt.links.new(coord, tex.inputs["Vector"])
        colour = tex.outputs["Color"]
        rough = 0.5
    elif texture == "concrete":
        ramp = nt.nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (0.28, 0.27, 0.25, 1.0)
        ramp.color_ramp.elements[1].color = (0.52, 0.5, 0.47, 1.0)
        nt.links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
        colour = ramp.outputs["Color"]
        rough = 0.85
    else:  # tiles: pale, slightly varied, with dark grout
        tex = _tiles(nt, coord, tile, ((0.42, 0.36, 0.3), (0.33, 0.29, 0.25)), (0.06, 0.06, 0.06))
        colour = tex.outputs["Color"]
        rough = 0.35
    bsdf.inputs["Roughness"].default_value = rough
    nt.links.new(colour, bsdf.inputs["Base Color"])
    if preview:
        return mat
    bump = nt.nodes.new("ShaderNodeBump")
    bump.inputs["Strength"].default_value = 0.15
    nt.links.new(noise.outputs["Fac"], bump.inputs["Height"])
    nt.links.new(bump.outputs["Normal"], bsdf.inputs["Normal"])
    return mat


def glass_material(preview: bool = False):
    """Clear glass of IOR GLASS_IOR. In preview a plain Glass BSDF (the same
    dielectric without the Principled BSDF's extra layers) is used: it looks
    alike and saves about 6% of a preview frame's CPU time."""
    import bpy

    mat = bpy.data.materials.new("whitecap_glass")
    if preview:
        mat.use_nodes = True
        nt = mat.node_tree
        nt.nodes.remove(nt.nodes.get("Principled BSDF"))
        glass = nt.nodes.new("ShaderNodeBsdfGlass")
        glass.inputs["Color"].default_value = (0.93, 0.97, 0.96, 1.0)
        glass.inputs["IOR"].default_value = GLASS_IOR
        glass.inputs["Roughness"].default_value = 0.0
        nt.links.new(glass.outputs[0], nt.nodes.get("Material Output").inputs["Surface"])
        return mat
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (0.93, 0.97, 0.96, 1.0)  # the faint green of soda-lime glass
    bsdf.inputs["Transmission Weight"].default_value = 1.0
    bsdf.inputs["IOR"].default_value = GLASS_IOR
    bsdf.inputs["Roughness"].default_value = 0.0
    return mat


def add_container(sc, cfg: Render, info: RunInfo, preview: bool = False):
    """The tank around the domain box (see the module docstring), or None for ``container = "none"``."""
    import bmesh
    import bpy

    kind = container_kind(cfg, info)
    if kind == "none":
        return None
    lo, hi = np.array(info.domain["lower"], float), np.array(info.domain["upper"], float)
    t = wall_thickness(cfg, info)
    inset = GLASS_OVERLAP * info.particle_radius if kind == "glass" else 0.0
    v, quads = _box_mesh(lo, hi, t, inset, hi[2])
    me = bpy.data.meshes.new(f"container_{kind}")
    bm = bmesh.new()
    verts = [bm.verts.new(p) for p in v]
    for q in quads:
        bm.faces.new([verts[i] for i in q])
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces)  # outward from the solid glass: Cycles needs it to refract
    bm.to_mesh(me)
    bm.free()
    obj = bpy.data.objects.new("container", me)
    tile = max(4 * t, float((hi - lo).max()) / 12)
    # Concrete, a 3D texture, reads the same on the walls and the floor (the tiles are flat in x, y).
    obj.data.materials.append(glass_material(preview) if kind == "glass"
                              else surface_material("whitecap_basin", "concrete", tile, preview))
    sc.collection.objects.link(obj)
    return obj


def add_ground(sc, cfg: Render, info: RunInfo, preview: bool = False):
    """A large textured ground under the domain (and under the container's floor)."""
    import bpy

    from .scene import make_mesh

    lo, hi = np.array(info.domain["lower"], float), np.array(info.domain["upper"], float)
    size = float(np.linalg.norm(hi - lo))
    c = (lo + hi) / 2
    z = lo[2] - (wall_thickness(cfg, info) if container_kind(cfg, info) != "none" else 0.0) - 1e-4 * size
    half = 20.0 * size
    gv = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]]) + [c[0], c[1], z]
    obj = bpy.data.objects.new("ground", make_mesh("ground", gv, np.array([[0, 1, 2], [0, 2, 3]])))
    tile = _nice_tile(size / 12)
    obj.data.materials.append(surface_material("whitecap_ground", cfg.ground_texture, tile, preview))
    sc.collection.objects.link(obj)
    return obj


def _nice_tile(x: float) -> float:
    """A tile edge of 1, 2 or 5 × 10^k metres near ``x``."""
    k = math.floor(math.log10(x))
    return min((m * 10.0**k for m in (1, 2, 5, 10)), key=lambda t: abs(math.log(t / x)))


def scene_bounds(run_dir: Path | None, info: RunInfo, obstacles=()) -> tuple[np.ndarray, np.ndarray]:
    """What the default camera frames: the fluid over the run plus the obstacles' boxes.

    ``obstacles`` holds one (n, 3) array of world points per obstacle (its box
    corners or its vertices), so the framing needs no Blender."""
    b = fluid_bounds(run_dir, info) if run_dir is not None else None
    lo, hi = (b if b is not None else (np.array(info.domain["lower"], float), np.array(info.domain["upper"], float)))
    for pts in obstacles:
        pts = np.asarray(pts, float).reshape(-1, 3)
        if len(pts):
            lo, hi = np.minimum(lo, pts.min(0)), np.maximum(hi, pts.max(0))
    return lo, hi


#: Blender's range for an image side [px] (RenderSettings.resolution_x and _y).
MIN_SIDE, MAX_SIDE = 4, 65536


def image_size(cfg: Render, preview: bool = False, where: str | Path = "scene.toml") -> tuple[int, int]:
    """(width, height) of the image at this quality; a side outside Blender's range is an
    InputError naming ``where`` (the run's scene.toml) and the field."""
    field = "preview_resolution" if preview else "resolution"
    w, h = (int(v) for v in getattr(cfg, field))
    if not (MIN_SIDE <= w <= MAX_SIDE and MIN_SIDE <= h <= MAX_SIDE):
        raise InputError(f"{where}: render.{field}: {w}x{h} px: each side must be {MIN_SIDE} to {MAX_SIDE} px "
                         "(Blender's limits)")
    return w, h


def image_aspect(cfg: Render, preview: bool = False) -> float:
    """Width / height of the rendered image at this quality."""
    w, h = cfg.preview_resolution if preview else cfg.resolution
    return int(w) / int(h)


def camera_keys(cfg: Render, info: RunInfo, bounds, first: int, last: int,
                aspect: float) -> tuple[dict[int, list[float]], list[float]]:
    """The camera position at every frame first..last and the point it looks at.

    Positions run linearly from :func:`camera_path`'s start to its end and turn
    ``camera_orbit`` degrees about the vertical through the target over the run.
    The renderer keys its camera with these; the USD and Alembic exports write them.
    A follow camera or preset (render/camera_follow.py) gives its positions and its first look-at point."""
    from . import camera_follow

    if camera_follow.active(cfg):
        follow, targets = camera_follow.follow_keys(cfg, info, bounds, first, last, aspect)
        return follow, targets[first]
    start, end, target = camera_path(cfg, info, bounds, aspect=aspect)
    keys: dict[int, list[float]] = {}
    for frame in range(first, last + 1):
        u = 0.0 if last == first else (frame - first) / (last - first)
        p = (1 - u) * np.array(start) + u * np.array(end)
        if cfg.camera_orbit:
            ang = math.radians(cfg.camera_orbit) * u
            d = p - np.array(target)
            rot = np.array([[math.cos(ang), -math.sin(ang), 0], [math.sin(ang), math.cos(ang), 0], [0, 0, 1]])
            p = np.array(target) + rot @ d
        keys[frame] = p.tolist()
    return keys, target


def camera_clip(position, target) -> tuple[float, float]:
    """Near and far clipping distances [m]: 10⁻³ and 10³ times the distance to the target."""
    d = float(np.linalg.norm(np.subtract(position, target)))
    return 1e-3 * d, 1e3 * d


def look_at_matrix(position, target) -> np.ndarray:
    """4×4 world matrix (column vectors) of a camera at ``position`` looking at ``target``
    with z up, as Blender's TRACK_TO (−z toward the target, y up) places it."""
    fwd = np.subtract(target, position).astype(float)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight down or up: keep x as right
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, -fwd, position
    return m


def depth_of_field(cam, cfg: Render, target_obj) -> None:
    """Depth of field when ``fstop`` is set, focused on ``focus_target`` (or the camera target)."""
    import bpy

    if cfg.fstop is None:
        return
    dof = cam.data.dof
    dof.use_dof = True
    dof.aperture_fstop = cfg.fstop
    if cfg.focus_target:
        focus = bpy.data.objects.new("focus_target", None)
        focus.location = cfg.focus_target
        bpy.context.scene.collection.objects.link(focus)
        dof.focus_object = focus
    else:
        dof.focus_object = target_obj


# ============================================================================ obstacles
def obstacle_render_mesh(entry: Obstacle, info: RunInfo, run_dir: Path | None = None):
    """The obstacle's render mesh (``render_mesh``, else its collision ``mesh``) as a trimesh in
    its own coordinates, found by :func:`obstacle_path`; None when the file is missing."""
    import trimesh

    src = entry.render_file
    path = obstacle_path(src, info, run_dir) if src else None
    if path is None:
        return None
    known = trimesh.available_formats()
    ext = next((e for e in sorted(known, key=len, reverse=True) if path.name.lower().endswith("." + e)), None)
    if ext is None:
        raise InputError(f"{path}: obstacle mesh: unknown file extension '{path.suffix or path.name}' "
                         "(use .obj, .stl, .ply, .off, .glb or .gltf)")
    try:
        return trimesh.load(str(path), force="mesh")
    except (NotImplementedError, ValueError, KeyError, IndexError) as exc:
        raise InputError(f"{path}: obstacle mesh: cannot read it as .{ext} ({exc})".replace("\n", " ")) from None


# ============================================================================ obstacle textures
def texture_path(entry: Obstacle, k: int, info: RunInfo, run_dir: Path) -> Path | None:
    """The image of ``obstacle[k].texture``, resolved against the scene's directory; a missing one is an error."""
    if not entry.texture:
        return None
    p = Path(entry.texture)
    if not p.is_absolute():
        p = Path(info.extra.get("scene_dir", run_dir)) / p
    if not p.is_file():
        raise InputError(f"{run_dir / 'scene.toml'}: obstacle[{k}].texture: file not found: {p}")
    return p


def apply_texture(obj, mesh, entry: Obstacle, k: int, info: RunInfo, run_dir: Path) -> None:
    """Give an obstacle object its image texture, mapped by the UVs of its render mesh (a trimesh)."""
    import bpy

    image = texture_path(entry, k, info, run_dir)
    if image is None:
        return
    uv = getattr(mesh.visual, "uv", None)
    if uv is None or len(uv) != len(mesh.vertices):
        raise InputError(f"obstacle[{k}].texture: the render mesh has no UV coordinates to map {image.name} with")
    me = obj.data
    layer = me.uv_layers.new(name="UVMap")
    faces = np.asarray(mesh.faces).ravel()  # one loop per face corner, in face order (make_mesh)
    layer.data.foreach_set("uv", np.ascontiguousarray(np.asarray(uv, np.float32)[faces]).ravel())
    mat = me.materials[0]
    nt = mat.node_tree
    tex = nt.nodes.new("ShaderNodeTexImage")  # unlinked Vector input: the active UV map
    tex.image = bpy.data.images.load(str(image), check_existing=True)
    nt.links.new(tex.outputs["Color"], nt.nodes.get("Principled BSDF").inputs["Base Color"])
