"""Loading: a whitecap run directory, a folder of sequences (or its subfolders), one numbered
file or an ``@`` pattern. A run loads through the shared bpy layer (whitecap/blender) as
``whitecap render`` builds it: the same materials, diffuse spheres, obstacle placement and,
from the run's render/scene.blend where it has one, the same camera, lights and world."""

import os

import bpy
import numpy as np

from . import handlers, paths, readers, sequences
from .properties import KINDS, POINT_KINDS, add_template
from .shared import COUNT_NAMES, Obstacle, RunInfo, looks, mesh, place, rigid_bin, run

SPACING_SAMPLES = 256  # points whose nearest-neighbour distance estimates the particle spacing
DEFAULT_FPS = 24.0  # a plain folder's frame rate when the operator is given none
RIGID_FOLDER = "rigid_bodies"  # SPlisHSPlasH's folder of rb_data_<k>.bin (cases/splishsplash.BIN_FOLDER)


def spacing(geom):
    """Half the median nearest-neighbour distance of a sample of points (a particle radius)."""
    from mathutils import kdtree

    pts = geom.points
    if len(pts) < 2:
        return 0.0
    tree = kdtree.KDTree(len(pts))
    for k, p in enumerate(pts):
        tree.insert(p, k)
    tree.balance()
    step = max(1, len(pts) // SPACING_SAMPLES)
    d = [tree.find_n(pts[k], 2)[1][2] for k in range(0, len(pts), step)]
    return float(np.median(d)) / 2


def new_sequence(context, made, name, directory, prefix, suffix, kind, *, run_kind="", type_code=-1,
                 radius=None, offset=0):
    """A sequence object showing the current frame; ``made`` collects what was created. A point
    kind gets the shared spheres: a diffuse type at the renderer's radius range (blender/looks),
    other points at the radius their files give (or their spacing)."""
    me = bpy.data.meshes.new(name)
    made.append(me)
    obj = bpy.data.objects.new(name, me)
    made.append(obj)
    context.scene.collection.objects.link(obj)
    seq = obj.whitecap_seq
    seq["directory"], seq["prefix"], seq["suffix"], seq["run_kind"] = (
        paths.stored(directory, context.scene), prefix, suffix, run_kind)
    seq["type_code"], seq["frame_offset"] = type_code, offset
    seq["kind"] = [k[0] for k in KINDS].index(kind)
    if kind in POINT_KINDS:
        if type_code >= 0:  # a diffuse type: the renderer's sizes, drawn per id
            rmin, rmax = looks.diffuse_radius(type_code, radius)
            seq["radius_min"], seq["radius_max"], seq["seed"] = rmin, rmax, looks.SEEDS[type_code]
        else:
            if radius is None:
                frames = handlers.frame_table(seq, context.scene)
                try:
                    radius = spacing(readers.read(frames[min(frames)])) or 0.01
                except ValueError:
                    radius = 0.01
            seq["radius_min"] = seq["radius_max"] = radius
            seq["file_radius"] = True
        made.append(add_template(obj, seq))
    elif kind == "FLUID":
        me.materials.append(looks.material("FLUID"))
    seq["enabled"] = True
    handlers.update_object(obj, context.scene, force=True)
    return obj


def guess_kind(prefix, suffix):
    p = prefix.lower()
    if p.startswith(("rb_", "rigid")):  # SPlisHSPlasH's rigid-body meshes
        return "OTHER"
    if suffix.lower() in (".bgeo",) or p.startswith(("part", "particle", "fluid_particles")) or "diffuse" in p:
        return "PARTICLES"
    return "FLUID"


def load_path(context, path, filter_text="", recursive=False, fps=DEFAULT_FPS):
    """Load a run directory, a folder of sequences, one numbered file or a pattern; returns the
    objects. A failed load leaves nothing behind."""
    made = []
    try:
        objs = _load(context, path, made, filter_text, recursive, fps)
        # Renders replace mesh data on every frame change: keep the interface off the scene meanwhile
        context.scene.render.use_lock_interface = True
        return objs
    except Exception:
        for idb in reversed(made):
            coll = {bpy.types.Object: bpy.data.objects, bpy.types.Mesh: bpy.data.meshes}.get(type(idb),
                                                                                            bpy.data.node_groups)
            try:
                coll.remove(idb)
            except (ReferenceError, RuntimeError, TypeError):
                pass
        raise


def set_timeline(sc, first, last, fps):
    sc.render.fps = max(1, int(round(fps)))
    sc.render.fps_base = sc.render.fps / fps
    sc.frame_start, sc.frame_end = first, last
    if sc.frame_current < first or sc.frame_current > last:
        sc.frame_current = first


def _load(context, path, made, filter_text, recursive, fps):
    p = os.path.normpath(bpy.path.abspath(path))
    if "@" not in os.path.basename(p) and not os.path.exists(p):
        raise ValueError(f"{p}: no such file or folder")
    rd = p if os.path.isdir(p) else os.path.dirname(p)
    if os.path.isfile(os.path.join(rd, "run.json")) and (os.path.isdir(p) or os.path.basename(p) == "run.json"):
        return load_run(context, rd, made)
    sc = context.scene
    bins = rigid_bin.bin_files(p if os.path.isdir(p) else os.path.dirname(p))
    if bins and (p.lower().endswith(".bin") or os.path.basename(p) == RIGID_FOLDER):
        return load_rigid_bodies(context, rd, bins, made, fps)
    if os.path.isdir(p):
        found = [(d, prefix, suffix, sequences.frames_of(d, prefix, suffix))
                 for d, prefix, suffix in sequences.sequences_in(p, filter_text, recursive)]
    else:
        d, prefix, suffix = sequences.sequence_of(p)
        found = [(d, prefix, suffix, sequences.frames_of(d, prefix, suffix))]
    first = min(min(f) for *_, f in found)
    last = max(max(f) for *_, f in found)
    set_timeline(sc, sc.frame_start, sc.frame_start + last - first, fps)  # file `first` at the first frame
    return [new_sequence(context, made, prefix.rstrip("_-. ") or "sequence", d, prefix, suffix,
                         guess_kind(prefix, suffix), offset=sc.frame_start - first)
            for d, prefix, suffix, _ in found]


def load_run(context, rd, made):
    """The fluid (surface mesh, else particles), one object per diffuse type, the obstacles, the
    timeline at the run's frames and rate, and the stage (camera, lights, world) F12 needs."""
    try:
        info = RunInfo.load(rd)
    except Exception as exc:
        raise ValueError(str(exc)) from None
    sc = context.scene
    mesh_files, fluid, diffuse = (run.current_files(info, k) for k in ("mesh", "fluid", "diffuse"))
    if not mesh_files and not fluid:
        raise ValueError(f"{rd}: the run has no fluid frames yet; run `whitecap simulate` first")
    indices = [i for files in (mesh_files, fluid, diffuse) for i, _ in files]
    set_timeline(sc, min(indices), max(indices), float(info.frame_rate))
    r = float(info.particle_radius)
    objs = []

    def folder(files):
        return os.path.dirname(os.path.join(rd, files[0][1]))

    if mesh_files:
        objs.append(new_sequence(context, made, "fluid", folder(mesh_files), "", "", "FLUID", run_kind="mesh"))
    else:
        objs.append(new_sequence(context, made, "fluid_particles", folder(fluid), "", "", "PARTICLES",
                                 run_kind="fluid", radius=r))
    if diffuse:
        for t, name in enumerate(COUNT_NAMES):
            objs.append(new_sequence(context, made, name, folder(diffuse), "", "", looks.DIFFUSE_KINDS[t],
                                     run_kind="diffuse", type_code=t, radius=r))
    for k, entry in enumerate(info.obstacles):
        obj = add_obstacle(context, made, rd, info, entry, k)
        if obj is not None:
            objs.append(obj)
    if sc.camera is None:
        made.extend(run.add_stage(sc, rd, info))
    return objs


def add_obstacle(context, made, rd, info, entry, k):
    """An obstacle's render mesh (else its collision mesh), found as whitecap finds it (the
    scene's folder, else the run's own) and placed and keyed by the shared layer."""
    path = run.obstacle_mesh_file(entry, info, rd)
    if path is None:
        print(f"whitecap: obstacle {k}: {entry.render_file}: file not found, left out")
        return None
    geom = readers.read(str(path))
    me = bpy.data.meshes.new(f"obstacle_{k}")
    made.append(me)
    mesh.fill_mesh(me, geom.points, geom.loops, geom.starts)
    me.materials.append(looks.obstacle_material(entry))
    obj = place.obstacle_object(f"obstacle_{k}", me, entry, info.frames, k, context.scene.collection)
    made.append(obj)
    return obj


#: SPlisHSPlasH is y up: its (x, y, z) shows as (x, -z, y), z up (whitecap.io.axes.to_z_up)
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def load_rigid_bodies(context, d, bins, made, fps):
    """SPlisHSPlasH's rigid bodies from ``rigid_bodies/rb_data_<k>.bin``, read and posed by the code
    ``whitecap import`` uses (cases/rigid_bin.py): one object per body over its mesh at the first
    frame, z up, keyed per file with the pose relative to it (blender/place.key_body); file k
    shows at scene frame start + k - first."""
    from .shared import WhitecapError

    ks = sorted(bins)
    try:
        header, Rs, ts = rigid_bin.read_bin_run(bins, ks)
    except WhitecapError as exc:
        raise ValueError(str(exc)) from None
    sc = context.scene
    set_timeline(sc, sc.frame_start, sc.frame_start + ks[-1] - ks[0], fps)
    objs = []
    for i, (name, scale, wall) in enumerate(header):
        geom = readers.read(os.path.join(d, name))
        me = bpy.data.meshes.new(os.path.splitext(name)[0])
        made.append(me)
        pts = rigid_bin.first_world(geom.points, scale, Rs[i][0], ts[i][0], Y_UP)
        mesh.fill_mesh(me, pts, geom.loops, geom.starts)
        me.materials.append(looks.obstacle_material(Obstacle(material="glass" if wall else "stone")))
        obj = bpy.data.objects.new(me.name, me)
        made.append(obj)
        sc.collection.objects.link(obj)
        if len(ks) > 1:
            poses = rigid_bin.relative_poses(Rs[i], ts[i], Y_UP)
            place.key_body(obj, [(sc.frame_start + k - ks[0], p) for k, p in zip(ks, poses)])
        objs.append(obj)
    return objs
