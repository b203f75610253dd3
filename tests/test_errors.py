"""Odd input, OS failures and interrupts end in a clear one-line message (or just work), never a
traceback or a hang."""

from __future__ import annotations

import errno
import os
import shutil
import sys
from pathlib import Path

import pytest

from whitecap.cli import main


def test_output_path_under_a_regular_file_is_one_line_naming_it(tiny_run, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory\n")
    code = main(["export", str(tiny_run), "--out", str(blocker / "export")])
    err = capsys.readouterr().err.strip()
    assert code == 5 and len(err.splitlines()) == 1, err
    assert err.startswith("error: ") and str(blocker) in err and "Not a directory" in err
    scene = tmp_path / "scene.toml"
    (scene).write_text("[[fluid]]\nlower = [0, 0, 0]\nupper = [0.1, 0.1, 0.1]\n")
    code = main(["simulate", str(scene), "--out", str(blocker)])  # the run directory itself is a file
    err = capsys.readouterr().err.strip()
    assert code == 5 and err == f"error: {blocker}: a file is in the way of a directory", err


def test_disk_full_names_the_file_being_written(tiny_run, tmp_path, monkeypatch, capsys):
    # A full disk fails the write into the temporary file (or its rename) with ENOSPC and
    # no file name of its own; the message must still say which output could not be written.
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)

    def full(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "replace", full)
    code = main(["export", str(run)])
    err = capsys.readouterr().err.strip()
    assert code == 5 and len(err.splitlines()) == 1, err
    # The first file an export writes is its list of what it will write (export.json)
    assert err == f"error: {run / 'export' / 'export.json'}: No space left on device"
    assert not list((run / "export").rglob("*.tmp*"))  # no temporary file left behind


def test_interrupt_suggests_only_options_the_command_has(monkeypatch, capsys, tmp_path):
    import re

    from whitecap import pipeline
    from whitecap.cli import build_parser

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    sub = next(a for a in build_parser()._actions if a.dest == "command").choices
    for cmd, fn in (("simulate", "simulate"), ("mesh", "mesh"), ("run", "run"), ("render", "render"),
                    ("foam", "foam"), ("export", "export")):
        monkeypatch.setattr(pipeline, fn, interrupted)
        code = main([cmd, str(tmp_path / "x")])
        err = capsys.readouterr().err.strip()
        assert code == 130 and err.startswith("interrupted") and len(err.splitlines()) == 1, (cmd, err)
        known = {o for action in sub[cmd]._actions for o in action.option_strings}
        assert set(re.findall(r"--[a-z-]+", err)) <= known, (cmd, err)
        if cmd in ("mesh", "render", "run"):  # these skip finished frames when run again
            assert "rerun the same command" in err, (cmd, err)
    monkeypatch.setattr(pipeline, "simulate", interrupted)
    main(["simulate", str(tmp_path / "x")])
    assert "--resume" in capsys.readouterr().err


def _scene_file(tmp_path, text: str):
    path = tmp_path / "scene.toml"
    path.write_text('[solver]\nparticle_radius = 0.01\n' + text)
    return str(path)


def test_a_fluid_block_without_particles_is_named_with_the_reason(tmp_path, capsys):
    import trimesh

    thin = _scene_file(tmp_path, "[[fluid]]\nlower = [0, 0, 0]\nupper = [0.1, 0.1, 0.1]\n"
                                 "[[fluid]]\nlower = [0.2, 0, 0]\nupper = [0.3, 0.1, 0.015]\n")
    code = main(["simulate", thin, "--out", str(tmp_path / "a")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1, err
    assert err.startswith("error: fluid[1] (from [0.2, 0.0, 0.0] to [0.3, 0.1, 0.015]): holds no particle")
    assert "2r = 0.02 m" in err and "no fluid" not in err
    box = tmp_path / "box.stl"
    trimesh.creation.box(extents=[0.2, 0.2, 0.2]).export(str(box))
    buried = _scene_file(tmp_path, "[[fluid]]\nlower = [0.25, 0.05, 0.05]\nupper = [0.35, 0.15, 0.15]\n"
                                   f'[[obstacle]]\nmesh = "{box}"\ntranslate = [0.3, 0.1, 0.1]\n')
    code = main(["simulate", buried, "--out", str(tmp_path / "b")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1, err
    assert err.startswith("error: fluid[0] (from [0.25, 0.05, 0.05] to [0.35, 0.15, 0.15]): lies entirely inside")


def test_unreadable_checkpoint_in_run_suggests_what_run_can_do(tiny_run, tmp_path, capsys):
    import re

    from whitecap.cli import build_parser

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    (run / "checkpoint.npz").write_bytes(b"not a zip")
    code = main(["run", str(run / "scene.toml"), "--out", str(run), "--until", "simulate", "--frames", "5"])
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert code != 0 and len(errors) == 1 and "checkpoint.npz" in errors[0], errors
    err = errors[0]
    suggested = re.search(r"`whitecap (\w+)([^`]*)`", err)
    assert suggested, err  # a command the user can type, with options that command has
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices[suggested[1]]
    known = {o for action in sub._actions for o in action.option_strings}
    assert set(re.findall(r"--[a-z-]+", suggested[2])) <= known and "without --resume" not in err


def _sequence(folder, frames):
    """Numbered PLY files from a list of (positions, velocities) pairs."""
    import numpy as np

    from whitecap.io import ParticleFrame, write

    folder.mkdir(parents=True, exist_ok=True)
    for i, (x, v) in enumerate(frames):
        write(folder / f"fluid_{i:05d}.ply", ParticleFrame(np.asarray(x).reshape(-1, 3), np.asarray(v).reshape(-1, 3)))
    return folder


def _block(n_side=6, r=0.01, speed=2.0, seed=0):
    import numpy as np

    a = np.arange(n_side) * 2 * r + r
    x = np.stack(np.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)
    v = np.random.default_rng(seed).normal(0, speed, x.shape)
    return x, v


def test_empty_frames_give_empty_output_or_a_clear_message(tmp_path, capsys):
    import imageio.v3 as iio
    import numpy as np

    empty = (np.zeros((0, 3)), np.zeros((0, 3)))
    only_empty = _sequence(tmp_path / "empty", [empty] * 3)
    code = main(["view", str(only_empty), "--headless", "-o", str(tmp_path / "v0")])
    assert code == 0, capsys.readouterr().err
    shots = sorted((tmp_path / "v0").glob("view_*.png"))
    assert len(shots) == 3
    img = iio.imread(shots[0])[..., :3].astype(int)
    drawn = np.abs(img - img[-1, -1]).max(axis=2) > 30
    assert drawn.mean() < 0.02  # the domain box's lines only, no particle
    code = main(["foam", str(only_empty), "-o", str(tmp_path / "f0"), "--radius", "0.01", "--dt", "0.03"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err == f"error: {only_empty}: all 3 frames are empty (no particles), so there is nothing " \
        "to make diffuse particles from"
    # Empty frames among full ones: the viewer frames the particles, foam counts zero for the empty ones.
    mixed = _sequence(tmp_path / "mixed", [empty, _block(), empty, _block(seed=1)])
    assert main(["view", str(mixed), "--headless", "-o", str(tmp_path / "v1"), "--frames", "2"]) == 0
    img = iio.imread(tmp_path / "v1" / "view_00001.png")[..., :3].astype(int)
    h, w = img.shape[:2]
    centre = img[h // 3: 2 * h // 3, w // 3: 2 * w // 3]
    assert np.ptp(centre, axis=(0, 1)).max() > 60  # the block fills the middle of the picture
    assert main(["foam", str(mixed), "-o", str(tmp_path / "f1"), "--radius", "0.01", "--dt", "0.03"]) == 0
    rows = [line.split(",") for line in (tmp_path / "f1" / "diffuse" / "counts.csv").read_text().split()[1:]]
    assert [r[0] for r in rows] == ["0", "1", "2", "3"]
    assert sum(map(int, rows[0][2:])) == 0 and sum(map(int, rows[1][2:])) > 0


def test_nan_positions_are_refused_by_view_and_export(tiny_run, tmp_path, capsys):
    import numpy as np

    from whitecap.io import read, write

    x, v = _block()
    bad = x.copy()
    bad[7] = np.nan
    for name, frames, culprit in (("first", [(bad, v), (x, v)], 0), ("later", [(x, v), (x, v), (bad, v)], 2)):
        seq = _sequence(tmp_path / name, frames)
        code = main(["view", str(seq), "--headless", "-o", str(tmp_path / f"v_{name}")])
        err = capsys.readouterr().err.strip()
        assert code == 2 and err == f"error: {seq / f'fluid_{culprit:05d}.ply'}: positions: 1 particles are NaN " \
            "or infinite", (name, err)
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    f = read(run / "fluid" / "fluid_00002.ply")
    f.velocities[3] = np.inf
    write(run / "fluid" / "fluid_00002.ply", f)
    code = main(["export", str(run)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err == f"error: {run / 'fluid' / 'fluid_00002.ply'}: velocities: 1 particles are NaN or infinite"


def test_a_foam_pass_refuses_a_frame_with_infinite_velocities_naming_it(tiny_run, tmp_path, capsys):
    """`whitecap foam` over a run whose third frame holds an infinite velocity (a foreign sequence is checked whole
    before the pass; a run's frames are checked as the pass reads them): one line naming the file and the field,
    exit 2, and no diffuse file for that frame."""
    from whitecap.io import read, write

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    f = read(run / "fluid" / "fluid_00002.ply")
    f.velocities[3, 1] = float("inf")
    write(run / "fluid" / "fluid_00002.ply", f)
    code = main(["foam", str(run), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err == f"error: {run / 'fluid' / 'fluid_00002.ply'}: velocities: 1 particles are NaN or " \
        "infinite"
    assert not (tmp_path / "out" / "diffuse" / "diffuse_00002.ply").exists()


def test_mesh_no_velocity_reads_files_without_one(tmp_path, capsys):
    import meshio
    import numpy as np

    from whitecap.io.mesh import read_mesh

    x, _ = _block(n_side=8)
    for i in range(2):  # VTU files with positions only, as some exporters write them
        meshio.write(tmp_path / f"p_{i:04d}.vtu", meshio.Mesh(x, [("vertex", np.arange(len(x))[:, None])]))
    pattern = str(tmp_path / "p_*.vtu")
    code = main(["mesh", pattern, "--radius", "0.01", "-j", "1", "-o", str(tmp_path / "m0")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith(f"error: {tmp_path / 'p_0000.vtu'}: missing array 'velocity'"), err
    assert main(["mesh", pattern, "--radius", "0.01", "--no-velocity", "-j", "1", "-o", str(tmp_path / "m1")]) == 0
    m = read_mesh(tmp_path / "m1" / "fluid_00001.ply")
    # The surface wraps the block of particles (centres 0.01..0.15, radius 0.01).
    assert len(m.faces) > 100
    assert np.allclose(m.vertices.min(0), 0.0, atol=0.01) and np.allclose(m.vertices.max(0), 0.16, atol=0.01)


def _children(pid: int) -> list[int]:
    """Pids whose parent is ``pid`` (from /proc)."""
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = open(f"/proc/{d}/stat").read()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d))
    return out


def _alive(pid: int) -> bool:
    try:
        state = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.parametrize("sig", ["SIGKILL", "SIGTERM"])
def test_mesh_workers_die_with_a_killed_parent(tmp_path, sig):
    import signal
    import subprocess
    import sys
    import time

    if not os.path.isdir("/proc"):
        pytest.skip("needs /proc to find the worker processes")
    x, v = _block(n_side=12)
    seq = _sequence(tmp_path / "seq", [(x + 0.001 * k, v) for k in range(150)])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    parent = subprocess.Popen([sys.executable, "-m", "whitecap.cli", "mesh", str(seq), "--radius", "0.01", "-j", "2",
                               "-o", str(tmp_path / "mesh")], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 120
        # Wait until both workers are busy: meshes are being written.
        while time.monotonic() < deadline and parent.poll() is None:
            workers = [p for p in _children(parent.pid)
                       if b"multiprocessing" in open(f"/proc/{p}/cmdline", "rb").read()
                       and b"resource_tracker" not in open(f"/proc/{p}/cmdline", "rb").read()]
            if len(workers) == 2 and len(list((tmp_path / "mesh").glob("*.ply"))) >= 4:
                break
            time.sleep(0.1)
        assert parent.poll() is None and len(workers) == 2, "the workers never started, or meshing ended too soon"
        os.kill(parent.pid, getattr(signal, sig))
        parent.wait()
        deadline = time.monotonic() + 30  # generous: the watchdog looks every half second
        while time.monotonic() < deadline and any(map(_alive, workers)):
            time.sleep(0.1)
        assert not any(map(_alive, workers)), "workers outlived their killed parent"
        assert len(list((tmp_path / "mesh").glob("*.ply"))) < 150
    finally:
        for p in [parent.pid, *workers]:
            try:
                os.kill(p, signal.SIGKILL)
            except OSError:
                pass


WATCHED = r"""
import sys, time
import whitecap.workers as w
w.PR_SET_PDEATHSIG = 0  # an invalid prctl option: only the watchdog thread is left
w.die_with_parent(int(sys.argv[1]))
print("ready", flush=True)
time.sleep(300)
"""
STARTER = r"""
import os, subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", sys.argv[1], str(os.getpid())])
print(child.pid, flush=True)
time.sleep(300)
"""


def test_the_parent_watchdog_alone_ends_an_orphan(tmp_path):
    # Where the kernel cannot be asked (not Linux), the watchdog thread must do it.
    import signal
    import subprocess
    import sys
    import time

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    starter = subprocess.Popen([sys.executable, "-c", STARTER, WATCHED], stdout=subprocess.PIPE, text=True, env=env)
    child = None
    try:
        child = int(starter.stdout.readline())
        assert starter.stdout.readline().strip() == "ready"
        os.kill(starter.pid, signal.SIGKILL)
        starter.wait()
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and _alive(child):
            time.sleep(0.1)
        assert not _alive(child), "the orphan outlived its parent"
    finally:
        for p in (starter.pid, child):
            try:
                os.kill(p, signal.SIGKILL)
            except (OSError, TypeError):
                pass


ENDED = r"""
import atexit, json, os, sys
import whitecap.workers as w
from whitecap.executor import exit_on_os_error
atexit.register(os.abort)  # a crash in the interpreter's teardown, as bpy's now and then
def work():
    print("rendered 3")  # block-buffered into a pipe: only a flush before the exit shows it
    how = sys.argv[1]
    if how == "value":
        raise ValueError("frame 3: no such mesh")
    if how == "disk":
        raise OSError(28, "No space left on device", "/out/render/frame_00003.png")
    if how == "exit":
        raise SystemExit("alembic_export returned {'CANCELLED'}")
w.run_then_end(work, exit_on_os_error if sys.argv[1] == "disk" else None)
"""


@pytest.mark.parametrize("how, code, last", [
    ("ok", 0, None),
    ("value", 1, "ValueError: frame 3: no such mesh"),
    ("disk", 5, None),
    ("exit", 1, "alembic_export returned {'CANCELLED'}"),
])
def test_a_worker_ends_with_its_own_status_whatever_the_teardown_does(how, code, last):
    """workers.run_then_end: a bpy worker's status is its work's (0, 1 with the error on the last line of standard
    error, the OS-error protocol), and its output reaches the parent, though the interpreter's teardown would
    abort (bpy's did, now and then, after every frame was written: a finished render reported as failed)."""
    import subprocess

    from whitecap.executor import worker_os_error

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    res = subprocess.run([sys.executable, "-c", ENDED, how], capture_output=True, text=True, env=env, timeout=60)
    assert res.returncode == code, res.stderr
    assert res.stdout.splitlines() == ["rendered 3"]
    if last is not None:
        assert res.stderr.strip().splitlines()[-1] == last
    if how == "disk":
        err = worker_os_error(res.stderr)
        assert err is not None and err.errno == 28 and err.filename == "/out/render/frame_00003.png"


SRC = Path(__file__).resolve().parents[1] / "src"
SESSION_DIR = r"""
import os, sys, types
import whitecap.workers as w
if sys.argv[1] == "bpy":
    import bpy
else:  # a stand-in bpy whose temporary folder is the one given
    sys.modules["bpy"] = types.SimpleNamespace(app=types.SimpleNamespace(tempdir=sys.argv[1] + os.sep))
print(sys.modules["bpy"].app.tempdir, flush=True)
w.run_then_end(lambda: None)
"""


@pytest.mark.parametrize("name, removed, base", [("blender_a1B2c3", True, False), ("renders", False, False),
                                                 ("blender_a1B2c3x", False, False), ("blender_a1B2c3", False, True)])
def test_a_worker_removes_blenders_own_temporary_folder_and_nothing_else(tmp_path, name, removed, base):
    """workers.end_process skips bpy's teardown (os._exit), and with it Blender's removal of the temporary folder
    it made when it started: each render worker left one behind. The worker removes it itself, but only a folder
    with the name Blender gives its own (blender_XXXXXX), never one a user's settings point Blender at, nor the
    base folder Blender falls back to when it cannot make its own there (here TMPDIR, named like one of Blender's)."""
    import subprocess

    folder = tmp_path / name
    (folder / "inside").mkdir(parents=True)
    (folder / "inside" / "keep.txt").write_text("a user's file")
    env = {**os.environ, "PYTHONPATH": str(SRC), **({"TMPDIR": str(folder)} if base else {})}
    res = subprocess.run([sys.executable, "-c", SESSION_DIR, str(folder)], capture_output=True, text=True, env=env,
                         timeout=60)
    assert res.returncode == 0, res.stderr
    assert folder.exists() is not removed and (folder / "inside" / "keep.txt").exists() is not removed


def test_a_blender_worker_leaves_no_temporary_folder_behind():
    """The same with bpy itself: the folder bpy.app.tempdir names exists while the worker runs and is gone after."""
    pytest.importorskip("bpy")
    import subprocess

    env = {**os.environ, "PYTHONPATH": str(SRC)}
    res = subprocess.run([sys.executable, "-c", SESSION_DIR, "bpy"], capture_output=True, text=True, env=env,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    made = res.stdout.splitlines()[-1]
    assert os.path.basename(os.path.normpath(made)).startswith("blender_") and not os.path.exists(made)
