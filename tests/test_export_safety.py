"""Issue 30: export and render never delete what is not theirs, read a run without writing
into it, and refuse what cannot work in one line (or pass the operating system's error on).

Tests that need a read-only directory use chmod where that works (not as root, whom the
kernel lets write anyway) and, so that they also run as root (CI containers), make the
same refusal happen by having the one system call that would meet it fail as it would.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import stat
import subprocess
import tomllib
from pathlib import Path

import numpy as np
import pytest

from whitecap import io as wio
from whitecap.cli import main
from whitecap.io.lock import LOCK_FILE
from whitecap.io.run import RunInfo


def _permissions_enforced() -> bool:
    """Whether this process is refused a write into a read-only directory (root, or any
    process with CAP_DAC_OVERRIDE, is not)."""
    import shutil
    import tempfile

    d = Path(tempfile.mkdtemp())
    try:
        d.chmod(0o555)
        try:
            (d / "probe").touch()
        except PermissionError:
            return True
        return False
    finally:
        d.chmod(0o755)
        shutil.rmtree(d)


needs_permissions = pytest.mark.skipif(not _permissions_enforced(),
                                       reason="this process (root) writes into read-only directories anyway")


def _copy(tiny_run: Path, dest: Path) -> Path:
    import shutil

    shutil.copytree(tiny_run, dest, ignore=shutil.ignore_patterns("export", LOCK_FILE))
    return dest


def _one_line(err: str) -> str:
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err


def _set_render(run: Path, **render) -> None:
    import tomli_w

    scene = tomllib.loads((run / "scene.toml").read_text())
    scene.setdefault("render", {}).update(render)
    (run / "scene.toml").write_text(tomli_w.dumps(scene))


def _nudge(run: Path, kind: str, index: int) -> None:
    """Change one frame's particles (a new source for that frame's exported file)."""
    path = run / f"{kind}/{kind}_{index:05d}.ply"
    f = wio.read(path)
    f.positions[:] += 0.001
    wio.write(path, f)


# ---------------------------------------------------------------------------- item 6: only what the manifest lists
def test_usd_export_keeps_the_users_files_in_the_frames_folder(tiny_run, tmp_path):
    """A notes file in scene_frames/ survives a re-export; the frame layer the new stage no
    longer uses (its source changed) is removed, the others are kept."""
    pytest.importorskip("pxr")
    run = _copy(tiny_run, tmp_path / "run")
    out = tmp_path / "out"
    assert main(["export", str(run), "--to", "usd", "--out", str(out)]) == 0
    frames = out / "scene_frames"
    first = sorted(p.name for p in frames.iterdir())
    notes = frames / "notes.txt"
    notes.write_text("which frames to show the client")
    (frames / "frame_00099_0123456789ab.usdc").write_bytes(b"my own layer, named like whitecap's")
    _nudge(run, "fluid", 2)
    assert main(["export", str(run), "--to", "usd", "--out", str(out)]) == 0
    assert notes.read_text() == "which frames to show the client"
    assert (frames / "frame_00099_0123456789ab.usdc").read_bytes() == b"my own layer, named like whitecap's"
    after = sorted(p.name for p in frames.iterdir() if p.name.startswith("frame_0000"))
    assert len(after) == len(first) == 4
    assert [n for n in first if n not in after] == [n for n in first if n.startswith("frame_00002_")]


def test_an_interrupted_usd_export_is_cleaned_up_by_the_next(tiny_run, tmp_path, monkeypatch):
    """Frame layers written by an export that stopped half-way are listed in export.json
    before they are written, so the next export removes those it does not use."""
    pytest.importorskip("pxr")
    import whitecap.export.usd as usd

    run = _copy(tiny_run, tmp_path / "run")
    out = tmp_path / "out"
    assert main(["export", str(run), "--to", "usd", "--out", str(out)]) == 0
    first = {p.name for p in (out / "scene_frames").iterdir()}
    _nudge(run, "fluid", 0)
    _nudge(run, "fluid", 2)
    real = usd.frame_layer

    def stop_at_frame_2(cache, index):
        if index == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(cache, index)

    monkeypatch.setattr(usd, "frame_layer", stop_at_frame_2)
    assert main(["export", str(run), "--to", "usd", "--out", str(out)]) == 5
    interrupted = {p.name for p in (out / "scene_frames").iterdir()} - first
    assert len(interrupted) == 1  # frame 0's new layer; the stage still names the first export's
    monkeypatch.setattr(usd, "frame_layer", real)
    _nudge(run, "fluid", 0)  # frame 0 changes again: the interrupted export's layer is of no use
    assert main(["export", str(run), "--to", "usd", "--out", str(out)]) == 0
    left = {p.name for p in (out / "scene_frames").iterdir()}
    assert len(left) == 4 and not left & interrupted and len(left & first) == 2  # frames 1 and 3 kept


def test_an_interrupted_vtk_export_is_cleaned_up_by_the_next(tiny_run, tmp_path, monkeypatch):
    """An export with --split-types that stops half-way leaves per-type series; the next
    export (without the split) removes them, and leaves the user's file alone."""
    import whitecap.export.series as export

    run = _copy(tiny_run, tmp_path / "run")
    out = tmp_path / "out"
    out.mkdir()
    (out / "README.txt").write_text("my notes")
    real = export.export_frame
    done = []

    def stop_after_two_diffuse_frames(src, kind, paths, to):
        if kind == "diffuse" and len(done) == 2:
            raise KeyboardInterrupt
        real(src, kind, paths, to)
        if kind == "diffuse":
            done.append(src)

    monkeypatch.setattr(export, "export_frame", stop_after_two_diffuse_frames)
    assert main(["export", str(run), "--out", str(out), "--split-types"]) == 130
    assert list((out / "diffuse_foam").glob("*.vtp"))
    monkeypatch.setattr(export, "export_frame", real)
    assert main(["export", str(run), "--out", str(out)]) == 0
    assert not any((out / d).exists() and any((out / d).iterdir())
                   for d in ("diffuse_spray", "diffuse_foam", "diffuse_bubble"))
    assert (out / "README.txt").read_text() == "my notes"
    listed = json.loads((out / "export.json").read_text())["files"]
    assert all((out / rel).is_file() for rel in listed) and not any(rel.startswith("diffuse_") for rel in listed)


def test_a_foreign_export_json_deletes_nothing(tiny_run, tmp_path, capsys):
    """An export.json that is not whitecap's (no format, no simulation identity) lists nothing to
    delete, and is the user's own file: the export refuses rather than overwrite it."""
    run = _copy(tiny_run, tmp_path / "run")
    out = tmp_path / "out"
    out.mkdir()
    (out / "data.csv").write_text("1,2,3\n")
    theirs = json.dumps({"files": ["data.csv"]})
    (out / "export.json").write_text(theirs)
    assert main(["export", str(run), "--out", str(out)]) == 2
    assert "export.json: not a whitecap manifest" in capsys.readouterr().err
    assert (out / "data.csv").read_text() == "1,2,3\n" and (out / "export.json").read_text() == theirs


def test_export_never_overwrites_a_users_file_in_its_way(tiny_run, tmp_path, capsys):
    run = _copy(tiny_run, tmp_path / "run")
    out = tmp_path / "out"
    out.mkdir()
    (out / "fluid.pvd").write_text("my ParaView collection")
    assert main(["export", str(run), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "fluid.pvd: not written by whitecap" in err, err
    assert (out / "fluid.pvd").read_text() == "my ParaView collection"


# ---------------------------------------------------------------------------- item 7: a read-only run
def _lock_file_cannot_be_opened(monkeypatch, run: Path) -> list[str]:
    """Make opening RUN/.whitecap.lock fail as on a read-only run (for root too); returns the
    attempts seen."""
    real = os.open
    lock = str(run / LOCK_FILE)
    seen = []

    def guarded(path, flags, *a, **k):
        if os.fspath(path) == lock:
            seen.append(flags)
            if flags & (os.O_CREAT | os.O_RDWR | os.O_WRONLY):
                raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), lock)
            if not os.path.exists(lock):
                raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), lock)
        return real(path, flags, *a, **k)

    monkeypatch.setattr(os, "open", guarded)
    return seen


@pytest.mark.parametrize("to", ["vtk", "usd"])
def test_export_of_a_run_whose_lock_file_cannot_be_made_goes_elsewhere(tiny_run, tmp_path, monkeypatch, to):
    """Root-safe form of the read-only run: the lock file cannot be created in the run, and
    an export to --out elsewhere still works, reading the run without a lock file."""
    if to == "usd":
        pytest.importorskip("pxr")
    run = _copy(tiny_run, tmp_path / "run")
    before = sorted(p.name for p in run.iterdir())
    seen = _lock_file_cannot_be_opened(monkeypatch, run)
    assert main(["export", str(run), "--to", to, "--out", str(tmp_path / "out")]) == 0
    assert seen  # the export did try the run's lock
    assert sorted(p.name for p in run.iterdir()) == before
    assert (tmp_path / "out" / "export.json").is_file()


@needs_permissions
def test_export_of_a_read_only_run(tiny_run, tmp_path):
    """chmod -R a-w on the run: export --out elsewhere works and writes nothing into the run;
    an export into the run itself is refused with the operating system's error (exit 5)."""
    run = _copy(tiny_run, tmp_path / "run")
    (run / LOCK_FILE).touch()  # left by the simulation that wrote the run: read-only like the rest
    before = sorted(p.name for p in run.iterdir())
    paths = [run, *run.rglob("*")]
    for p in paths:
        p.chmod(p.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    try:
        assert main(["export", str(run), "--out", str(tmp_path / "out")]) == 0
        assert sorted(p.name for p in run.iterdir()) == before
        assert (tmp_path / "out" / "fluid.pvd").is_file()
        assert main(["export", str(run)]) == 5
    finally:
        for p in paths:
            p.chmod(p.stat().st_mode | stat.S_IWUSR)


def test_readers_share_the_run_and_a_writer_excludes_them(tiny_run, tmp_path, capsys):
    """Another process reading the run (a shared flock) does not stop an export elsewhere;
    a process writing it (an exclusive flock) does, in one line, and the export writes nothing."""
    run = _copy(tiny_run, tmp_path / "run")
    fd = os.open(run / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH)  # as another export reading this run
        assert main(["export", str(run), "--out", str(tmp_path / "a")]) == 0
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.write(fd, b"pid 1: simulate: whitecap simulate scene.toml --resume\n")
        fcntl.flock(fd, fcntl.LOCK_EX)  # as a simulation writing into it
        capsys.readouterr()
        assert main(["export", str(run), "--out", str(tmp_path / "b")]) == 2
        err = _one_line(capsys.readouterr().err)
        assert str(run) in err and "simulate" in err
        assert not (tmp_path / "b" / "export.json").exists()
    finally:
        os.close(fd)


def test_two_exports_into_one_place_exclude_each_other(tiny_run, tmp_path, capsys):
    """The output directory outside the run is locked (on the directory itself: no lock file
    among the user's files)."""
    run = _copy(tiny_run, tmp_path / "run")
    out = tmp_path / "out"
    out.mkdir()
    fd = os.open(out, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # as another export writing there
        assert main(["export", str(run), "--out", str(out)]) == 2
        assert str(out) in _one_line(capsys.readouterr().err)
    finally:
        os.close(fd)
    assert main(["export", str(run), "--out", str(out)]) == 0
    assert not (out / LOCK_FILE).exists()


# ---------------------------------------------------------------------------- item 18: obstacle mesh format
def test_usd_export_with_an_obstacle_mesh_of_unknown_extension(tiny_run, tmp_path, capsys):
    pytest.importorskip("pxr")
    run = _copy(tiny_run, tmp_path / "run")
    (run / "block.foo").write_text("o block\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    meta = json.loads((run / "run.json").read_text())
    meta["obstacles"] = [{"mesh": "block.foo", "translate": [0.3, 0.1, 0.1]}]
    meta["extra"]["scene_dir"] = str(run)
    (run / "run.json").write_text(json.dumps(meta))
    assert main(["export", str(run), "--to", "usd", "--out", str(tmp_path / "out")]) == 2
    err = _one_line(capsys.readouterr().err)
    assert "block.foo" in err and "'.foo'" in err
    assert not (tmp_path / "out" / "scene.usd").exists()


# ---------------------------------------------------------------------------- --jobs
@pytest.mark.parametrize("jobs", ["0", "-3"])
def test_jobs_below_one_are_refused_by_export_and_render(tiny_run, tmp_path, jobs, capsys):
    run = _copy(tiny_run, tmp_path / "run")
    assert main(["export", str(run), "--jobs", jobs, "--out", str(tmp_path / "out")]) == 2
    assert _one_line(capsys.readouterr().err) == f"error: export: --jobs must be at least 1 (got {jobs})\n"
    assert not (tmp_path / "out").exists()
    assert main(["render", str(run), "--jobs", jobs]) == 2
    assert _one_line(capsys.readouterr().err) == f"error: render: --jobs must be at least 1 (got {jobs})\n"
    from whitecap.errors import InputError
    from whitecap.export.scene import export_scene

    with pytest.raises(InputError, match=rf"^export: --jobs must be at least 1 \(got {jobs}\)$"):
        export_scene(run, to="usd", out=tmp_path / "out", show_progress=False, jobs=int(jobs))
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------- render: before Blender starts
@pytest.fixture
def meshed_run(tiny_run, tmp_path) -> Path:
    """The tiny run with a small surface mesh recorded for each frame (enough for render's checks)."""
    import trimesh

    from whitecap.io.mesh import SurfaceMesh, write_mesh

    run = _copy(tiny_run, tmp_path / "run")
    info = RunInfo.load(run)
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    for f in info.frames:
        rel = f"mesh/fluid_{f.index:05d}.ply"
        write_mesh(run / rel, SurfaceMesh(np.asarray(box.vertices), np.asarray(box.faces)))
        info.set_file(f.index, "mesh", rel)
    info.save(run)
    return run


@pytest.fixture
def no_blender(monkeypatch):
    """Fail the test if render starts a Blender worker process."""
    import whitecap.executor as executor
    import whitecap.render.driver as driver

    def refuse(*a, **k):
        raise AssertionError(f"Blender was started: {a[0] if a else k}")

    monkeypatch.setattr(executor.subprocess, "Popen", refuse)  # the worker processes' (executor.ProcessWorkers)
    monkeypatch.setattr(driver, "require_bpy", lambda: None)


@pytest.mark.parametrize("resolution, says", [([100000, 100000], "each side must be 4 to 65536 px"),
                                              ([0, 1080], "each side must be 4 to 65536 px"),
                                              ([20000, 20000], "more than this machine has free")])
def test_render_refuses_an_image_it_cannot_make_before_blender_starts(meshed_run, no_blender, monkeypatch, capsys,
                                                                      resolution, says):
    import whitecap.render.driver as driver

    monkeypatch.setattr(driver, "available_memory", lambda: 8 << 30)  # 8 GiB free, whatever this machine has
    _set_render(meshed_run, resolution=resolution)
    assert main(["render", str(meshed_run), "--quality", "final"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert str(meshed_run / "scene.toml") in err and "render.resolution" in err and says in err


def test_render_memory_counts_every_worker(meshed_run, no_blender, monkeypatch, capsys):
    """4000×4000 at 96 B/px is 1.4 GiB: one Blender fits in 2 GiB free, three do not."""
    import whitecap.render.driver as driver

    monkeypatch.setattr(driver, "available_memory", lambda: 2 << 30)
    _set_render(meshed_run, resolution=[4000, 4000])
    driver.check_image_memory(meshed_run, driver.render_settings(meshed_run), "final", 1)
    assert main(["render", str(meshed_run), "--quality", "final", "--jobs", "3"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert "for 3 Blender processes" in err and "--jobs" in err


def _render_folder_read_only(monkeypatch, render: Path) -> None:
    """Creating a file in RUN/render fails as in a read-only folder (for root too)."""
    import tempfile

    real = tempfile.mkstemp

    def guarded(*a, dir=None, **k):
        if dir is not None and Path(dir).resolve() == render.resolve():
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.path.join(dir, "tmpXXXXXXXX"))
        return real(*a, dir=dir, **k)

    monkeypatch.setattr(tempfile, "mkstemp", guarded)


def test_render_into_a_read_only_render_folder_is_the_os_error(meshed_run, no_blender, monkeypatch, capsys):
    (meshed_run / "render").mkdir()
    _render_folder_read_only(monkeypatch, meshed_run / "render")
    assert main(["render", str(meshed_run)]) == 5
    err = _one_line(capsys.readouterr().err)
    assert err == f"error: {meshed_run / 'render'}: {os.strerror(errno.EACCES)}\n"


@needs_permissions
def test_render_into_a_chmod_read_only_render_folder(meshed_run, no_blender, capsys):
    render = meshed_run / "render"
    render.mkdir()
    render.chmod(0o555)
    try:
        assert main(["render", str(meshed_run)]) == 5
        assert str(render) in _one_line(capsys.readouterr().err)
    finally:
        render.chmod(0o755)


# A worker whose render meets a full disk (bpy is not needed: the frame function is replaced).
WORKER_FULL_DISK = r"""
import errno, os, sys
from pathlib import Path
import whitecap.render.worker as w
def full(run, quality, frames, threads, save, device):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(Path(run) / "render" / f"frame_{frames[0]:05d}.png"))
w.render_worker = full
w.main()
"""


def test_a_worker_on_a_full_disk_is_the_os_error(meshed_run, monkeypatch, capsys):
    """The worker's OSError reaches the user as the OS error naming the file (exit 5), not
    as "Blender render failed" (exit 2)."""
    import whitecap.executor as executor
    import whitecap.render.driver as driver

    real = subprocess.Popen
    monkeypatch.setattr(driver, "require_bpy", lambda: None)
    monkeypatch.setattr(executor.subprocess, "Popen",  # the worker processes' (executor.ProcessWorkers)
                        lambda cmd, **k: real([cmd[0], "-c", WORKER_FULL_DISK, *cmd[3:]], **k))
    assert main(["render", str(meshed_run), "--frames", "1:2", "--no-movie"]) == 5
    err = capsys.readouterr().err.splitlines()[-1] + "\n"  # after the progress bar, where one is drawn
    assert err == f"error: {meshed_run / 'render' / 'frame_00001.png'}: {os.strerror(errno.ENOSPC)}\n"


# ---------------------------------------------------------------------------- export on a full disk
def test_vtk_export_on_a_full_disk_is_the_os_error(tiny_run, tmp_path, monkeypatch, capsys):
    """VTK's writer, writing into a full disk (/dev/full), fails with errno ENOSPC: the user
    sees the OS error naming the file and exit 5, as the README promises."""
    import whitecap.io.vtk_xml as vtk_xml

    real = vtk_xml._vtk

    def onto_a_full_disk():
        numpy_support, points, cells, poly, Writer, reader = real()

        class FullDisk(Writer):
            def SetFileName(self, name):
                super().SetFileName("/dev/full")

        return numpy_support, points, cells, poly, FullDisk, reader

    monkeypatch.setattr(vtk_xml, "_vtk", onto_a_full_disk)
    run = _copy(tiny_run, tmp_path / "run")
    assert main(["export", str(run), "--out", str(tmp_path / "out")]) == 5
    err = _one_line(capsys.readouterr().err)
    assert os.strerror(errno.ENOSPC) in err and str(tmp_path / "out") in err
