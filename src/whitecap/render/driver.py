"""Offline rendering of a run in Blender (the ``bpy`` module), plus the Blender add-on.

``render_run`` builds the Blender scene once per worker process, then for
each frame swaps in that frame's fluid mesh and diffuse point clouds and
renders it with Cycles to ``render/frame_NNNNN.png`` (temporary file, then
rename). Finished frames are skipped on rerun: a frame counts as finished
when its PNG has this quality's size and ``run.json`` records it as made
from the run's current simulation (a frame rendered from an earlier
simulation is rendered again). The run is locked while rendering. The movie is encoded with
imageio-ffmpeg and the scene is saved as ``render/scene.blend``.

Cycles already uses every core for one frame, so on a small machine one
worker is fastest; ``jobs`` > 1 starts that many worker processes, each
rendering an interleaved share of the frames with Cycles threads split
between them (worth it when scene updates dominate, or on many cores).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from ..config import Render, load_scene
from ..errors import InputError, MissingDependency
from ..io.lock import run_lock
from ..io.run import RunInfo
from ..progress import progress
from ..workers import child_env

INSTALL_HINT = "install it with: pip install bpy==5.0.1 (needs Python 3.11 and numpy<2)"


def require_bpy():
    try:
        import bpy  # noqa: F401
    except ImportError:
        raise MissingDependency(f"rendering needs Blender's Python module 'bpy', which is not installed; {INSTALL_HINT}") from None
    return bpy


def render_settings(run_dir: Path, device: str | None = None) -> Render:
    """The run's ``[render]`` section (defaults without a scene.toml); ``device`` overrides its device."""
    scene_file = run_dir / "scene.toml"
    cfg = load_scene(scene_file).render if scene_file.is_file() else Render()
    return cfg.model_copy(update={"device": device}) if device else cfg


def frame_path(run_dir: Path, index: int) -> Path:
    return run_dir / "render" / f"frame_{index:05d}.png"


def parse_range(spec: str | None, available: list[int]) -> list[int]:
    """'a:b' (inclusive of a, exclusive of b, like Python) or 'a' or None -> frame indices."""
    if not spec:
        return available
    try:
        if ":" in spec:
            a, b = spec.split(":", 1)
            lo = int(a) if a else min(available)
            hi = int(b) if b else max(available) + 1
            return [i for i in available if lo <= i < hi]
        return [i for i in available if i == int(spec)]
    except ValueError:
        raise InputError(f"--frames: expected a:b, got {spec!r}") from None


def render_worker(run_dir: Path, quality: str, frames: list[int], threads: int | None, save_blend: bool,
                  device: str | None = None) -> None:
    """Build the scene and render ``frames`` (runs in this process)."""
    require_bpy()
    import bpy

    from ..io.atomic import atomic_path
    from .scene import build_scene, load_frame

    info = RunInfo.load(run_dir)
    cfg = render_settings(run_dir, device)
    mesh_frames = [i for i, _ in info.files("mesh")]
    h = build_scene(info, cfg, quality, min(mesh_frames), max(mesh_frames))
    sc = bpy.context.scene
    if threads:
        sc.render.threads_mode = "FIXED"
        sc.render.threads = threads
    for i in frames:
        load_frame(h, run_dir, info, i)
        out = frame_path(run_dir, i)
        with atomic_path(out) as tmp:
            sc.render.filepath = str(tmp)
            sc.render.use_file_extension = False
            bpy.ops.render.render(write_still=True)
        print(f"rendered {i}", flush=True)
    if save_blend:
        # The saved scene shows the first frame; the add-on or a re-run of
        # load_frame updates it per frame.
        load_frame(h, run_dir, info, min(mesh_frames))
        blend = run_dir / "render" / "scene.blend"
        with atomic_path(blend) as tmp:
            bpy.ops.wm.save_as_mainfile(filepath=str(tmp), check_existing=False, compress=True)


def _done(png: Path, size: tuple[int, int]) -> bool:
    """A finished frame exists at this quality's size (a rerun at another quality redoes it)."""
    if not png.exists():
        return False
    try:
        from PIL import Image

        with Image.open(png) as im:
            return tuple(im.size) == tuple(size)
    except Exception:
        return False


def encode_movie(run_dir: Path, fps: float, indices: list[int] | None = None) -> Path:
    """render/movie.mp4 from the rendered frames (all of them, or ``indices``)."""
    from ..io.movie import encode_mp4

    frames = [frame_path(run_dir, i) for i in indices] if indices else sorted((run_dir / "render").glob("frame_*.png"))
    return encode_mp4(frames, run_dir / "render" / "movie.mp4", fps)


def render_run(
    run_dir: str | Path,
    quality: str = "preview",
    frames: str | None = None,
    jobs: int = 1,
    force: bool = False,
    movie: bool = True,
    show_progress: bool = True,
    device: str | None = None,
) -> dict:
    """Render a run directory. Returns {'frames': [...], 'movie': path, 'blend': path}.

    ``device`` (auto, cpu, gpu) overrides ``[render].device``.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: run directory not found")
    with run_lock(run_dir, "render"):
        return _render_run(run_dir, quality, frames, jobs, force, movie, show_progress, device)


def _render_run(run_dir: Path, quality: str, frames: str | None, jobs: int, force: bool, movie: bool,
                show_progress: bool, device: str | None) -> dict:
    if quality not in ("preview", "final"):
        raise InputError(f"--quality: expected preview or final, got {quality!r}")
    if device not in (None, "auto", "cpu", "gpu"):
        raise InputError(f"--device: expected auto, cpu or gpu, got {device!r}")
    info = RunInfo.load(run_dir)
    meshes = [i for i, _ in info.files("mesh")]
    if not meshes:
        raise InputError(f"{run_dir}: no surface meshes yet; run `whitecap mesh {run_dir}` first")
    require_bpy()
    wanted = parse_range(frames, meshes)
    if not wanted:
        raise InputError(f"--frames {frames}: no meshed frames in that range (have {meshes[0]}..{meshes[-1]})")
    cfg = render_settings(run_dir, device)
    if cfg.device == "gpu":  # fail here, in one line, rather than in every worker
        from .scene import cycles_device

        cycles_device("gpu")
    size = tuple(cfg.preview_resolution if quality == "preview" else cfg.resolution)
    current = {i for i, _ in info.files("render")}  # rendered from this simulation
    todo = [i for i in wanted if force or i not in current or not _done(frame_path(run_dir, i), size)]
    blend = run_dir / "render" / "scene.blend"
    made = info.extra.get("blend")
    need_blend = force or not blend.exists() or not (isinstance(made, dict) and made.get("made_from") == info.simulation)
    (run_dir / "render").mkdir(parents=True, exist_ok=True)
    jobs = max(1, min(int(jobs or 1), len(todo) or 1))
    bar = progress(disable=not show_progress)
    with bar:
        task = bar.add_task("render", total=len(wanted), completed=len(wanted) - len(todo), info=quality)
        if todo or need_blend:
            import tempfile

            procs, logs = [], []
            threads = max(1, (os.cpu_count() or 1) // jobs) if jobs > 1 else 0
            for k in range(jobs):
                share = todo[k::jobs]
                cmd = [
                    sys.executable, "-m", "whitecap.render.worker", str(run_dir), quality,
                    ",".join(map(str, share)) or "-", str(threads), "1" if (k == 0 and need_blend) else "0",
                    cfg.device,
                ]
                log = tempfile.TemporaryFile(mode="w+")
                logs.append(log)
                procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True, env=child_env()))
            for p in procs:
                for line in p.stdout:  # one line per finished frame, recorded at once (resumable)
                    if line.startswith("rendered"):
                        _record(run_dir, [int(line.split()[1])])
                        bar.advance(task)
            errors = []
            for p, log in zip(procs, logs):
                p.wait()
                if p.returncode:
                    log.seek(0)
                    errors.append((log.read().strip().splitlines() or ["unknown error"])[-1])
            if errors:
                raise InputError(f"{run_dir}: Blender render failed: {errors[0]}")
            if need_blend:
                _record(run_dir, [], blend=True)
    result = {"frames": [frame_path(run_dir, i) for i in wanted], "blend": blend, "movie": None}
    if movie:
        result["movie"] = encode_movie(run_dir, info.frame_rate, wanted)
    _record(run_dir, wanted)
    return result


def _record(run_dir: Path, indices: list[int], blend: bool = False) -> None:
    """Record rendered frames (and the saved scene) in run.json as made from the current simulation."""
    info = RunInfo.load(run_dir)
    for i in indices:
        info.set_file(i, "render", f"render/frame_{i:05d}.png")
    if blend:
        info.extra["blend"] = {"file": "render/scene.blend", "made_from": info.simulation}
    info.save(run_dir)


def build_addon(out: str | Path | None = None) -> Path:
    """Zip the Blender extension (blender_manifest.toml + add-on package)."""
    import zipfile

    from ..io.atomic import atomic_path

    src = Path(__file__).parent / "addon"
    # whitecap modules the add-on imports as its own (pure Python, no imports): one definition
    shared = {"diffuse_types.py": Path(__file__).parents[1] / "io" / "diffuse_types.py"}
    out = Path(out) if out else Path("whitecap_blender_addon.zip")
    with atomic_path(out) as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
            for f in sorted(src.iterdir()):
                if f.is_file() and f.suffix in (".py", ".toml"):
                    z.write(f, f.name)
            for name, f in shared.items():
                z.write(f, name)
    return out
