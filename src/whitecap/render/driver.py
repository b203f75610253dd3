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

Before any Blender starts, the image size is checked against Blender's limits
and its memory against what the machine has free (:func:`check_image_memory`),
and ``render/`` is checked to be writable: an operating-system error (a
read-only folder, a full disk, in this process or in a worker) propagates as
``OSError`` naming the path.
"""

from __future__ import annotations

import errno
import os
import re
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..config import Render, choices, load_scene
from ..errors import InputError, MissingDependency
from ..executor import ProcessWorkers, WorkerFailed, map_frames
from ..io.atomic import sweep_temps
from ..io.lock import run_lock
from ..io.run import RunInfo
from ..progress import progress
from ..resources import MEMORY_HEADROOM, available_memory  # the Blender processes' share, as simulate's
from ..stage_frames import check_jobs, todo as stage_todo

INSTALL_HINT = "install it with: pip install bpy==5.0.1 (needs Python 3.11 and numpy<2)"
#: Memory one Blender process needs per pixel of the image [B]: Cycles' float RGBA result,
#: its film accumulation and the denoiser's passes (noisy colour, albedo, normal), and the
#: float and 8-bit copies made to save the PNG. An estimate on the high side: a render it
#: lets through fits; one it refuses could not be saved in the memory left anyway.
BYTES_PER_PIXEL = 96


def require_bpy():
    try:
        import bpy  # noqa: F401
    except ImportError:
        raise MissingDependency(
            f"rendering needs Blender's Python module 'bpy', which is not installed; {INSTALL_HINT}"
        ) from None
    return bpy


def render_settings(run_dir: Path, device: str | None = None) -> Render:
    """The run's ``[render]`` section (defaults without a scene.toml); ``device`` overrides its device."""
    scene_file = run_dir / "scene.toml"
    cfg = load_scene(scene_file).render if scene_file.is_file() else Render()
    return cfg.model_copy(update={"device": device}) if device else cfg


def frame_path(run_dir: Path, index: int) -> Path:
    return run_dir / "render" / f"frame_{index:05d}.png"


def _memory_size(text: str) -> int:
    """'16GB', '2.5 GiB' -> bytes (the [cluster] memory field's units, as Dask reads them)."""
    m = re.fullmatch(r"(\d+(?:\.\d+)?)\s*([KMGT])(i?)B", text.strip())
    if not m:
        return 1 << 62
    return int(float(m.group(1)) * (1024 if m.group(3) else 1000) ** ("KMGT".index(m.group(2)) + 1))


def check_image_memory(run_dir: Path, cfg: Render, quality: str, processes: int, cluster: str | None = None) -> None:
    """Refuse, in one line naming scene.toml's field, an image Blender cannot make: a side
    outside Blender's range, or ``processes`` Blender processes whose images need more memory
    than is free here (or than a batch job of ``[cluster]`` has). Runs before Blender starts."""
    from .stage import image_size

    field = "preview_resolution" if quality == "preview" else "resolution"
    where = run_dir / "scene.toml"
    w, h = image_size(cfg, quality == "preview", where)
    per_process = w * h * BYTES_PER_PIXEL
    if cluster in (None, "", "local"):
        need, have, what = per_process * processes, MEMORY_HEADROOM * available_memory(), "this machine has free"
    elif cluster in ("slurm", "pbs"):
        from ..executor import cluster_settings

        mem = cluster_settings(run_dir).memory
        need, have = per_process, MEMORY_HEADROOM * _memory_size(mem)
        what = f"a batch job has ([cluster] memory = {mem})"
    else:
        return  # a scheduler's workers: their memory is not known here
    if need > have:
        many = f" for {processes} Blender processes" if need != per_process else ""
        raise InputError(f"{where}: render.{field}: {w}x{h} px needs about {need / 2**30:.1f} GiB{many}, "
                         f"more than {what} ({have / MEMORY_HEADROOM / 2**30:.1f} GiB); lower the resolution"
                         + (" or --jobs" if many else ""))


def check_writable(folder: Path) -> None:
    """Create and remove a file in ``folder``: an OSError naming the folder (read-only, full)
    comes here, before Blender starts, rather than from every worker."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".whitecap-write-test-", dir=folder)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or os.strerror(exc.errno or errno.EIO), str(folder)) from None
    os.close(fd)
    os.unlink(probe)


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


class SceneRenderer:
    """One Blender scene of a run, built once, then rendered frame after frame (in this process)."""

    def __init__(self, run_dir: Path, quality: str, threads: int | None, device: str | None = None):
        require_bpy()
        import bpy

        from .scene import build_scene

        self.run_dir = run_dir
        self.info = RunInfo.load(run_dir)
        cfg = render_settings(run_dir, device)
        self.mesh_frames = [i for i, _ in self.info.files("mesh")]
        self.handles = build_scene(self.info, cfg, quality, min(self.mesh_frames), max(self.mesh_frames),
                                   run_dir=run_dir)
        self.scene = bpy.context.scene
        if threads:
            self.scene.render.threads_mode = "FIXED"
            self.scene.render.threads = threads

    def render(self, i: int) -> None:
        """Swap in frame ``i`` and render it to render/frame_NNNNN.png (temporary file, then rename)."""
        import bpy

        from ..io.atomic import atomic_path
        from .scene import load_frame

        load_frame(self.handles, self.run_dir, self.info, i)
        out = frame_path(self.run_dir, i)
        with atomic_path(out) as tmp:
            self.scene.render.filepath = str(tmp)
            self.scene.render.use_file_extension = False
            bpy.ops.render.render(write_still=True)

    def save_blend(self) -> None:
        """render/scene.blend, showing the first frame (the add-on or load_frame updates it per frame)."""
        import bpy

        from ..io.atomic import atomic_path
        from .scene import load_frame

        load_frame(self.handles, self.run_dir, self.info, min(self.mesh_frames))
        blend = self.run_dir / "render" / "scene.blend"
        with atomic_path(blend) as tmp:
            bpy.ops.wm.save_as_mainfile(filepath=str(tmp), check_existing=False, compress=True)


def render_worker(run_dir: Path, quality: str, frames: list[int], threads: int | None, save_blend: bool,
                  device: str | None = None) -> None:
    """Build the scene and render ``frames`` (runs in this process)."""
    r = SceneRenderer(run_dir, quality, threads, device)
    for i in frames:
        r.render(i)
        print(f"rendered {i}", flush=True)
    if save_blend:
        r.save_blend()


def serve_worker(run_dir: Path, quality: str, threads: int | None, device: str | None = None, stdin=None) -> None:
    """Build the scene once, then render the frames named on standard input, one a line, until it closes.

    ``frame N`` renders frame N and answers ``rendered N``; ``blend`` saves
    render/scene.blend and answers ``saved blend``. The Dask render path
    (:mod:`whitecap.render.cluster`) keeps one such process per Dask worker.
    """
    stdin = stdin or sys.stdin
    r = SceneRenderer(run_dir, quality, threads, device)
    print(f"ready {os.getpid()}", flush=True)
    for line in stdin:
        words = line.split()
        if words[:1] == ["frame"]:
            r.render(int(words[1]))
            print(f"rendered {int(words[1])}", flush=True)
        elif words == ["blend"]:
            r.save_blend()
            print("saved blend", flush=True)


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


#: The image qualities of a render: preview (small, few samples) or final ([render] resolution).
QUALITIES = ("preview", "final")
#: Cycles devices a render may ask for instead of [render].device (that field's values).
DEVICES = choices(Render, "device")


@dataclass(frozen=True)
class RenderJob:
    """What one render of a run does: the options of ``whitecap render`` and of
    :func:`whitecap.pipeline.render`, with their defaults, defined here once (the CLI
    and the pipeline build one; :func:`render_run` takes it). Checked on construction.

    ``frames`` is a range ``a:b`` (b excluded) of meshed frames, all of them when None;
    ``jobs`` Blender worker processes here (or, with ``cluster``, the local Dask workers or
    batch jobs); ``force`` renders finished frames again; ``movie`` encodes render/movie.mp4;
    ``device`` (auto, cpu, gpu) overrides ``[render].device``; ``cluster`` (a scheduler
    address, or local, slurm, pbs) renders on Dask, one Blender process per Dask worker.
    """

    quality: str = "preview"
    frames: str | None = None
    jobs: int = 1
    force: bool = False
    movie: bool = True
    show_progress: bool = True
    device: str | None = None
    cluster: str | None = None

    def __post_init__(self) -> None:
        check_jobs("render", self.jobs)
        if self.quality not in QUALITIES:
            raise InputError(f"--quality: expected {' or '.join(QUALITIES)}, got {self.quality!r}")
        if self.device not in (None, *DEVICES):
            raise InputError(f"--device: expected {', '.join(DEVICES[:-1])} or {DEVICES[-1]}, got {self.device!r}")


def render_run(run_dir: str | Path, job: RenderJob) -> dict:
    """Render a run directory as ``job`` says. Returns {'frames': [...], 'movie': path, 'blend': path}.

    With ``job.cluster`` the frames render on Dask (:mod:`whitecap.render.cluster`).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: run directory not found")
    with run_lock(run_dir, "render"):
        try:
            return _render_run(run_dir, job)
        finally:
            sweep_temps(run_dir / "render")  # a worker killed while writing leaves its temporary file


def _render_run(run_dir: Path, job: RenderJob) -> dict:
    quality, frames, cluster = job.quality, job.frames, job.cluster
    info = RunInfo.load(run_dir)
    meshes = [i for i, _ in info.files("mesh")]
    if not meshes:
        raise InputError(f"{run_dir}: no surface meshes yet; run `whitecap mesh {run_dir}` first")
    wanted = parse_range(frames, meshes)
    if not wanted:
        raise InputError(f"--frames {frames}: no meshed frames in that range (have {meshes[0]}..{meshes[-1]})")
    cfg = render_settings(run_dir, job.device)
    check_image_memory(run_dir, cfg, quality, max(1, min(job.jobs or 1, len(wanted))), cluster)
    (run_dir / "render").mkdir(parents=True, exist_ok=True)
    check_writable(run_dir / "render")
    if not cluster:  # on a cluster, Blender runs on the workers
        require_bpy()
    from .stage import environment_path, texture_path

    # A missing image fails here, in one line, not in every worker.
    environment_path(cfg, info, run_dir)
    for k, entry in enumerate(info.obstacles):
        texture_path(entry, k, info, run_dir)
    if cfg.device == "gpu" and not cluster:  # fail here, in one line, rather than in every worker
        from .scene import cycles_device

        cycles_device("gpu")
    width, height = cfg.preview_resolution if quality == "preview" else cfg.resolution
    size = (width, height)
    current = {i for i, _ in info.files("render")}  # rendered from this simulation
    keys = {i: frame_key(run_dir, info, cfg, quality, i) for i in wanted}
    todo = stage_todo(wanted, lambda i: i in current and info.frame(i).render_key == keys[i]
                      and _done(frame_path(run_dir, i), size), job.force)
    blend = run_dir / "render" / "scene.blend"
    made = info.extra.get("blend")
    look = frame_key(run_dir, info, cfg, quality, None)
    need_blend = job.force or not blend.exists() or not (isinstance(made, dict)
                                                         and made.get("made_from") == info.simulation
                                                         and made.get("key") == look)
    jobs = max(1, min(job.jobs or 1, len(todo) or 1))
    bar = progress(disable=not job.show_progress)
    with bar:
        task = bar.add_task("render", total=len(wanted), completed=len(wanted) - len(todo), info=quality)
        if cluster and (todo or need_blend):
            from ..executor import cluster_settings, connect

            ex = connect(cluster, run_dir, cfg=cluster_settings(run_dir), jobs=jobs if jobs > 1 else None)
            try:
                from .cluster import render_on_cluster

                blender = render_on_cluster(ex, run_dir, quality, cfg.device, todo, need_blend, bar, task,
                                            lambda i: _record(run_dir, [i], keys=keys), report=job.show_progress)
            finally:
                bar.stop()
                ex.close()
            if need_blend:
                _record(run_dir, [], blend=look)
        elif todo or need_blend:
            _render_locally(run_dir, quality, cfg.device, todo, need_blend, jobs, bar, task,
                            lambda r: _record(run_dir, [r.index], keys=keys))
            if need_blend:
                _record(run_dir, [], blend=look)
    result = {"frames": [frame_path(run_dir, i) for i in wanted], "blend": blend, "movie": None}
    if cluster and (todo or need_blend):
        result["blender_processes"] = len(blender)  # one per Dask worker that rendered, not one per frame
    if job.movie:
        result["movie"] = encode_movie(run_dir, info.frame_rate, wanted)
    _record(run_dir, wanted)
    return result


def _render_locally(run_dir: Path, quality: str, device: str, todo: list[int], need_blend: bool, jobs: int, bar,
                    task, on_done) -> None:
    """``todo`` on ``jobs`` Blender worker processes here (:class:`whitecap.executor.ProcessWorkers`:
    each builds the scene once and renders an interleaved share, Cycles' threads split between
    them), the first saving render/scene.blend after its frames when ``need_blend``. ``on_done``
    records each frame as it comes. An OS error in a worker is raised as itself (CLI exit 5)."""
    threads = max(1, (os.cpu_count() or 1) // jobs) if jobs > 1 else 0

    def command(k: int, share: list[int]) -> list[str]:
        return [sys.executable, "-m", "whitecap.render.worker", str(run_dir), quality, ",".join(map(str, share)) or "-",
                str(threads), "1" if (k == 0 and need_blend) else "0", device]

    try:
        map_frames(ProcessWorkers(jobs, word="rendered"), "render", command, [(i, ()) for i in todo], bar, task,
                   on_done)
    except WorkerFailed as exc:
        raise InputError(f"{run_dir}: Blender render failed: {exc}") from None


def frame_key(run_dir: Path, info: RunInfo, cfg, quality: str, index: int | None) -> str:
    """What a rendered frame was made from, beyond the simulation: the render settings and quality
    (not the device), and the frame's surface and diffuse files as they are now (name, size, time).
    A frame whose key changed (new [render] settings, a mesh remade with other settings, foam made
    again) is rendered again instead of being skipped beside frames of the new look."""
    import hashlib
    import json

    frame = info.frame(index) if index is not None else None  # None: the look alone (scene.blend)
    files = frame.files if frame is not None else {}
    inputs = []
    for kind in ("mesh", "diffuse"):
        if kind in files:
            st = (run_dir / files[kind]).stat()
            inputs.append([kind, files[kind], st.st_size, st.st_mtime_ns])
    look = {k: v for k, v in cfg.model_dump(mode="json").items() if k != "device"}
    bodies = [b.model_dump() for b in frame.bodies] if frame is not None and frame.bodies is not None else None
    obstacles = [o.model_dump() for o in info.obstacles]
    text = json.dumps([look, quality, inputs, obstacles, bodies], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _record(run_dir: Path, indices: list[int], blend: str | None = None, keys: dict | None = None) -> None:
    """Record rendered frames (and the saved scene) in run.json as made from the current simulation,
    each with its :func:`frame_key`."""
    info = RunInfo.load(run_dir)
    for i in indices:
        info.set_file(i, "render", f"render/frame_{i:05d}.png")
        if keys and i in keys:
            info.frame(i).render_key = keys[i]
    if blend:
        info.extra["blend"] = {"file": "render/scene.blend", "made_from": info.simulation, "key": blend}
    info.save(run_dir)


def _is_addon_zip(path: Path) -> bool:
    """A zip holding a Blender extension manifest of whitecap's (an earlier build_addon)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            return b'id = "whitecap' in z.read("blender_manifest.toml")
    except (OSError, KeyError, zipfile.BadZipFile):
        return False


def build_addon(out: str | Path | None = None) -> Path:
    """Zip the Blender extension: blender_manifest.toml, the add-on's modules, and in its
    ``whitecap`` folder the whitecap modules it shares with ``whitecap render`` (the bpy layer
    whitecap/blender and what it imports: errors, io/diffuse_types, io/record, io/run, io/atomic)."""
    import zipfile

    from ..io.atomic import atomic_path

    src = Path(__file__).parent / "addon"
    out = Path(out) if out else Path("whitecap_blender_addon.zip")
    if out.is_dir():
        out = out / "whitecap_blender_addon.zip"
    if out.exists() and not _is_addon_zip(out):  # never over the user's file
        raise InputError(f"{out}: exists and is not a whitecap add-on zip; choose another --out")
    with atomic_path(out) as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
            wheels = addon_wheels()
            for f in sorted(src.iterdir()):
                if f.is_file() and f.suffix == ".py":
                    z.write(f, f.name)
            z.writestr("blender_manifest.toml", manifest_with_wheels((src / "blender_manifest.toml").read_text(),
                                                                     sorted(wheels)))
            for name, data in wheels.items():
                z.writestr(name, data)
            for name, text in addon_shared_files().items():
                z.writestr(name, text)
    return out


#: The Python packages the extension carries as wheels (with their requirements): plyfile parses
#: PLY for whitecap's io/ply.py, the add-on's copy included; meshio reads every other mesh format.
#: Blender bundles numpy, so it is left out.
ADDON_PACKAGES = ("meshio", "plyfile")
BLENDER_BUNDLES = ("numpy",)


def _requirements(dist) -> list[str]:
    """The names a distribution needs in Blender's Python (no extras; other markers evaluated where
    the packaging module is there, else left out)."""
    out = []
    for text in dist.requires or []:
        name, _, marker = text.partition(";")
        if marker.strip():
            try:
                from packaging.markers import Marker

                if not Marker(marker).evaluate({"extra": ""}):
                    continue
            except ImportError:
                continue
        m = re.match(r"\s*([A-Za-z0-9._-]+)", name)
        assert m is not None, text  # a requirement starts with its project's name (PEP 508)
        out.append(m.group(1))
    return out


def addon_wheels() -> dict[str, bytes]:
    """{"wheels/<file>.whl": bytes} of :data:`ADDON_PACKAGES` and their pure-Python requirements,
    each made from the installed distribution (no network: whitecap itself depends on meshio,
    so pip installed them). The wheel holds the package's files as installed, its dist-info
    with a fresh RECORD (file, sha256, size). Pure-Python only: a compiled requirement would need
    a wheel per platform, and is refused."""
    import base64
    import hashlib
    import io as _io
    import zipfile
    from importlib.metadata import PackageNotFoundError, distribution

    todo, seen, out = list(ADDON_PACKAGES), set(), {}
    while todo:
        name = todo.pop(0).lower().replace("_", "-")
        if name in seen or name in BLENDER_BUNDLES:
            continue
        seen.add(name)
        try:
            dist = distribution(name)
        except PackageNotFoundError:
            raise MissingDependency(f"blender-addon: {name} is not installed (pip install {name}); "
                                    "the extension carries it as a wheel") from None
        todo += _requirements(dist)
        wheel_meta = dist.read_text("WHEEL") or ""
        tags = [ln.split(":", 1)[1].strip() for ln in wheel_meta.splitlines() if ln.startswith("Tag:")]
        if "Root-Is-Purelib: true" not in wheel_meta or not tags or not tags[0].endswith("-none-any"):
            raise InputError(f"blender-addon: {name} is not a pure-Python package; the extension cannot carry it")
        base = Path(str(dist.locate_file("")))  # a Path (typed as importlib.metadata's SimplePath)
        files = sorted(str(f) for f in dist.files or [] if not str(f).startswith("..") and "__pycache__" not in str(f)
                       and not str(f).endswith((".pyc", "RECORD", "INSTALLER", "REQUESTED", "direct_url.json")))
        info_dir = next(f.split("/")[0] for f in files if f.split("/")[0].endswith(".dist-info"))
        buf, record = _io.BytesIO(), []
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as w:
            for rel in files:
                data = (base / rel).read_bytes()
                w.writestr(rel, data)
                digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
                record.append(f"{rel},sha256={digest},{len(data)}")
            record.append(f"{info_dir}/RECORD,,")
            w.writestr(f"{info_dir}/RECORD", "\n".join(record) + "\n")
        stem = re.sub(r"[-_.]+", "_", dist.metadata["Name"]).lower()
        out[f"wheels/{stem}-{dist.version}-{tags[0]}.whl"] = buf.getvalue()
    return out


def manifest_with_wheels(text: str, wheels: list[str]) -> str:
    """The manifest with ``wheels = [...]`` (paths in the zip) before its first table or comment."""
    line = "wheels = [" + ", ".join(f'"./{w}"' for w in wheels) + "]\n"
    ends = [k for k in (text.find("\n["), text.find("\n#")) if k >= 0]
    return text + "\n" + line if not ends else text[:min(ends) + 1] + line + text[min(ends) + 1:]


#: whitecap modules the extension carries (below the package), beside the whole bpy layer
ADDON_SHARED = ("errors.py", "io/diffuse_types.py", "io/record.py", "io/run.py", "io/atomic.py", "geometry.py",
                "cases/rigid_bin.py", "cases/rigid_fit.py",
                # the add-on's readers parse with whitecap's own format modules (numpy, plyfile),
                # with what they import
                "io/bgeo.py", "io/ply.py", "io/threads.py", "io/vtu.py", "io/vtk_xml.py", "io/registry.py",
                "io/frame.py", "io/axes.py")


def addon_shared_files() -> dict[str, bytes]:
    """{path in the zip: bytes} of the whitecap modules the add-on imports, with package files that
    import nothing (whitecap's own ``__init__`` files load the whole pipeline, which Blender lacks)."""
    pkg = Path(__file__).parents[1]
    files = {f"whitecap/{rel}": (pkg / rel).read_bytes() for rel in ADDON_SHARED}
    files.update({f"whitecap/blender/{f.name}": f.read_bytes() for f in sorted((pkg / "blender").glob("*.py"))})
    stub = b'"""whitecap modules shared with the Blender add-on (copied by `whitecap blender-addon`)."""\n'
    files["whitecap/__init__.py"] = stub
    files["whitecap/io/__init__.py"] = stub
    files["whitecap/cases/__init__.py"] = stub
    return files
