"""What runs when the frame changes, a file is saved or a render starts, and the frame update itself.

A sequence object's mesh is refilled in place with the file of its frame. A frame whose
file cannot be read shows an empty mesh and the error on the object (its ``error``, shown
in the panels), never the previous frame; with the scene's *Fail renders on a bad frame*
a render that would show such a frame stops with an error. In Edit Mode the mesh is left
alone (refilling it there would empty it when the user leaves Edit Mode).
"""

import os
import time

import bpy
import numpy as np
from bpy.app.handlers import persistent

from . import paths, readers, sequences
from .shared import RunInfo, mesh, run

_FRAMES: dict[tuple, dict[int, str]] = {}  # (folder, prefix, suffix, run kind) -> {frame: path}; cleared by Refresh
_RENDER = {"on": False, "camera": None}


def forget_tables():
    _FRAMES.clear()


def frame_table(seq, scene=None):
    """{frame number: file} of a sequence: the run's current files (run.json) for a run's
    sequence, else the numbered files in its folder."""
    d = paths.resolve(seq.directory, scene)
    key = (d, seq.prefix, seq.suffix, seq.run_kind)
    if key not in _FRAMES:
        if not os.path.isdir(d):
            raise ValueError(f"{d}: no such folder (set the sequence's folder in the whitecap panel)")
        if seq.run_kind:
            rd = os.path.dirname(d)
            try:
                info = RunInfo.load(rd)
            except Exception as exc:
                raise ValueError(str(exc)) from None
            _FRAMES[key] = {i: os.path.join(rd, rel) for i, rel in run.current_files(info, seq.run_kind)}
        else:
            _FRAMES[key] = {i: os.path.join(d, f) for i, f in sequences.frames_of(d, seq.prefix, seq.suffix).items()}
    frames = _FRAMES[key]
    if not frames:
        raise ValueError(f"{d}: no files {seq.prefix}*{seq.suffix}")
    return frames


def file_index(frames, number, mode="HOLD"):
    """The file shown at a (whole) sequence frame number: the last one at or before it; before
    the first or after the last file, ``mode`` holds the end file, loops, or shows nothing (None)."""
    lo, hi = min(frames), max(frames)
    if number < lo or number > hi:
        if mode == "BLANK":
            return None
        if mode == "LOOP":
            number = lo + (number - lo) % (hi - lo + 1)
    have = [i for i in frames if i <= number]
    return max(have) if have else lo


def index_at(seq, frames, frame, subframe):
    """The file index shown at scene frame ``frame + subframe`` (None: nothing). With Own frame,
    the object's (animatable) Frame property picks it. A sub-frame (a motion-blur shutter step)
    keeps the frame's mesh: the file already shown stays while it is the file of the frame before
    or after, so the ``velocity`` attribute does the blur."""
    if seq.use_frame:
        return file_index(frames, int(np.floor(seq.frame + 1e-6)), seq.out_of_range)
    lo = file_index(frames, frame - seq.frame_offset, seq.out_of_range)
    if subframe > 1e-6:
        hi = file_index(frames, frame + 1 - seq.frame_offset, seq.out_of_range)
        if seq.current in (lo, hi) and seq.current >= 0:
            return seq.current
    return lo


def fill(obj, geom, seq):
    """The object's mesh refilled with ``geom`` (a type's points only, for a diffuse type)."""
    pts, arrays, loops, starts, normals = geom.points, attribute_arrays(geom), geom.loops, geom.starts, geom.normals
    if seq.type_code >= 0:
        low = {k.lower(): k for k in geom.arrays}
        types = geom.arrays.get(low.get("type", ""), np.zeros(len(geom), np.int32))
        keep = np.asarray(types).astype(np.int64) == seq.type_code
        pts, arrays, loops, starts, normals = pts[keep], [(k, a[keep]) for k, a in arrays], None, None, None
    if seq.up == "Y":
        pts = y_up(pts)
        arrays = [(k, y_up(a) if k == "velocity" else a) for k, a in arrays]
        normals = None if normals is None else y_up(normals)
    mesh.fill_mesh(obj.data, pts, loops, starts, arrays, normals if seq.normals else None, seq.smooth)


def show_nothing(obj, seq, error=""):
    mesh.fill_mesh(obj.data, np.zeros((0, 3)))
    seq.error = error
    seq.shown_file = ""


def update_object(obj, scene, force=False):
    """Show the object's frame; True when the mesh changed. A file that cannot be read leaves an
    empty mesh and the error in ``seq.error`` (and raises nothing)."""
    seq = obj.whitecap_seq
    if obj.mode == "EDIT":
        return False  # refilled when the user leaves Edit Mode and the frame changes
    try:
        frames = frame_table(seq, scene)
    except ValueError as exc:
        show_nothing(obj, seq, str(exc))
        seq.current = -1
        return True
    i = index_at(seq, frames, scene.frame_current, scene.frame_subframe)
    if i is None:
        if seq.current != -2 or force:
            show_nothing(obj, seq)
            seq.current = -2
            return True
        return False
    if i == seq.current and not force and not seq.error:
        return False
    t0 = time.perf_counter()
    try:
        geom = readers.read(frames[i])
        fill(obj, geom, seq)
        seq.error = ""
        seq.shown_file = frames[i]
    except Exception as exc:  # a bad file: an empty mesh and the reason, never the previous frame
        show_nothing(obj, seq, str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        print(f"whitecap: {obj.name}: {seq.error}")
    seq.load_ms = 1000.0 * (time.perf_counter() - t0)
    seq.current = i
    return True


def sequence_objects(scene):
    return [o for o in scene.objects if o.type == "MESH" and o.whitecap_seq.directory and o.whitecap_seq.enabled]


def update_all(scene, force=False):
    for obj in sequence_objects(scene):
        update_object(obj, scene, force)


def reload(obj, scene):
    if obj.type == "MESH" and obj.whitecap_seq.directory and obj.whitecap_seq.enabled:
        update_object(obj, scene, force=True)


# ----------------------------------------------------------------------------- geometry helpers
VELOCITY_NAMES = ("vel", "velocity", "v")  # whitecap.io.registry's tables (tests/test_addon.py checks)
DENSITY_NAMES = ("rhop", "rho", "density")
ID_NAMES = ("idp", "id")
PRESSURE_NAMES = ("press", "pressure")
STANDARD = (("velocity", VELOCITY_NAMES), ("density", DENSITY_NAMES), ("id", ID_NAMES), ("pressure", PRESSURE_NAMES))


def attribute_arrays(geom):
    """[(name, array)] of a file's point arrays: the standard names for velocity, density,
    id and pressure (whatever the solver called them), every other array by its own name."""
    out, taken = [], set()
    low = {k.lower(): k for k in geom.arrays}
    for std, names in STANDARD:
        key = next((low[n] for n in names if n in low), None)
        if key is not None:
            out.append((std, geom.arrays[key]))
            taken |= {key, std}
    for k, a in geom.arrays.items():
        if k not in taken and not k.startswith(".") and k.lower() not in mesh.RESERVED and k.lower() not in taken:
            out.append((k, a))
            taken.add(k.lower())
    return out


def y_up(a):
    """(x, y, z) of y-up data -> (x, -z, y), z up (whitecap.io.axes.to_z_up)."""
    return np.stack([a[:, 0], -a[:, 2], a[:, 1]], axis=1)


# ----------------------------------------------------------------------------- handlers
def _log(scene):
    if not (_RENDER["on"] and scene.whitecap_log):
        return
    path = bpy.path.abspath(scene.whitecap_log)
    with open(path, "a") as fh:
        for obj in sequence_objects(scene):
            seq = obj.whitecap_seq
            fh.write(f"{scene.frame_current}\t{obj.name}\t{seq.shown_file or '-'}\t{seq.load_ms:.1f} ms"
                     f"{chr(9) + 'ERROR ' + seq.error if seq.error else ''}\n")


def _errors(scene):
    return [f"{o.name}: {o.whitecap_seq.error}" for o in sequence_objects(scene) if o.whitecap_seq.error]


#: Exit status of a background render stopped by a bad frame.
FAILED_RENDER_STATUS = 3


@persistent
def on_frame_change(scene, depsgraph=None):
    update_all(scene)
    _log(scene)
    if _RENDER["on"] and scene.whitecap_fail_render:
        stop_bad_render(scene)


def stop_bad_render(scene):
    """Fail a render that reached a frame a sequence cannot show (Fail renders on a bad frame).

    Blender's Python cannot cancel a render once it runs: an exception in a handler is printed and
    the render goes on, and taking the camera away mid-animation crashes Blender 5.0 (it is only
    safe at render_init, where :func:`on_render_init` does it). So a background render (``blender
    -b ... -a``, or bpy as a module) exits at once with status :data:`FAILED_RENDER_STATUS` and the
    reason, before the bad frame is written; in the interface, where exiting would close the
    artist's Blender, the frame renders with the empty mesh, and the error stays on the object,
    in the panel and in the render log."""
    bad = _errors(scene)
    if not bad:
        return
    msg = f"whitecap: render stopped at frame {scene.frame_current}: " + "; ".join(bad)
    print(msg)
    if bpy.app.background:
        import sys

        sys.stderr.write(msg + "\n")
        sys.stderr.flush()
        raise SystemExit(FAILED_RENDER_STATUS)


@persistent
def on_render_init(scene, *args):
    """A render starts: log from now on; with Fail renders on a bad frame, a frame that cannot be
    shown stops it (Blender cannot render without a camera, so the camera is held back until the
    render is over)."""
    _RENDER["on"] = True
    update_all(scene)
    bad = _errors(scene)
    if bad and scene.whitecap_fail_render and scene.camera is not None:
        print("whitecap: render stopped: " + "; ".join(bad))
        _RENDER["camera"] = scene.camera.name
        scene.camera = None
    _log(scene)


@persistent
def on_render_done(scene, *args):
    _RENDER["on"] = False
    restore_camera(scene)


def restore_camera(scene):
    name = _RENDER.pop("camera", None)
    _RENDER["camera"] = None
    if name and name in bpy.data.objects and scene.camera is None:
        scene.camera = bpy.data.objects[name]


@persistent
def on_depsgraph(scene, depsgraph=None):
    if _RENDER.get("camera") and not _RENDER["on"]:
        restore_camera(scene)


@persistent
def on_save(filepath="", *args):
    """Store every sequence's folder relative to the .blend being written."""
    if not isinstance(filepath, str) or not filepath:
        return
    for scene in bpy.data.scenes:
        for obj in scene.objects:
            seq = getattr(obj, "whitecap_seq", None)
            if seq is not None and seq.directory and (os.path.isabs(seq.directory) or seq.directory.startswith("//")):
                new = paths.stored(paths.resolve(seq.directory, scene), scene, filepath)
                if new != seq.directory:
                    seq["directory"] = new  # no reload: the folder is the same


HANDLERS = (("frame_change_post", on_frame_change), ("save_pre", on_save), ("render_init", on_render_init),
            ("render_complete", on_render_done), ("render_cancel", on_render_done),
            ("depsgraph_update_post", on_depsgraph))


def register():
    for name, fn in HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn not in lst:
            lst.append(fn)


def unregister():
    for name, fn in HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn in lst:
            lst.remove(fn)
