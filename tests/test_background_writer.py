"""The background writer of `simulate` (issue 31, goal 4): frames, run.json and checkpoints written
by a thread with a bounded queue, in order; resume byte-identical after kill -9, including a kill
while a frame is being written; a full disk in the writer reaches the caller as one OSError."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from whitecap.cli import main
from whitecap.config import scene_from_dict
from whitecap.io.lock import LOCK_FILE
from whitecap.io.run import RunInfo
from whitecap.io.writer import LANE_DEPTH, ORDERED_AHEAD, FrameWriter
from whitecap.pipeline import simulate

from .conftest import ROOT, kill_when, tiny_scene_dict


@pytest.fixture(autouse=True)
def _writer_on(monkeypatch):
    """The background writer runs on a GPU by default; these tests run it on the CPU as well."""
    import whitecap.sim.driver as driver

    monkeypatch.setattr(driver, "BACKGROUND_WRITER", True)

# Checkpoints every 2 frames: a resume recomputes the frames after the last one.
SCENE = tiny_scene_dict(output={"frames": 5, "checkpoint_interval": 2}, foam={"enabled": False})


def _snapshot(run: Path) -> dict[str, bytes]:
    """Every file of the run but the lock file (whose holder line changes)."""
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*"))
            if p.is_file() and p.name != LOCK_FILE}


def _listed(run: Path) -> dict[str, int]:
    return {rel: f.index for f in RunInfo.load(run).frames for rel in f.files.values()}


# ----------------------------------------------------------------------------- FrameWriter itself
def test_jobs_run_in_order_and_flush_waits_for_them():
    done = []
    with FrameWriter(maxsize=2) as w:
        for k in range(20):
            w.submit(lambda k=k: done.append(k))
        w.flush()
        assert done == list(range(20))


def test_an_error_in_the_writer_is_raised_by_the_next_call_and_later_jobs_are_skipped():
    done = []
    w = FrameWriter(maxsize=4)
    failed = threading.Event()

    def full():
        failed.set()
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/run/fluid/fluid_00002.ply")

    w.submit(full)
    failed.wait(30)
    with pytest.raises(OSError) as err:
        w.flush()
    assert err.value.filename == "/run/fluid/fluid_00002.ply" and err.value.errno == errno.ENOSPC
    w.close()  # raises nothing: the caller has been told
    w2 = FrameWriter(maxsize=4)
    gate = threading.Event()
    w2.submit(gate.wait)
    w2.submit(full)
    w2.submit(lambda: done.append("after"))  # queued after the failing job: never run
    gate.set()
    with pytest.raises(OSError, match="No space left"):
        for _ in range(1000):  # the next submit or the flush raises it, whichever comes first
            w2.submit(lambda: done.append("later"))
        w2.flush()
    w2.close()
    assert "after" not in done


def test_the_queue_is_bounded_a_slow_disk_blocks_the_caller():
    gate, started = threading.Event(), threading.Event()
    handed = []
    w = FrameWriter(maxsize=2)

    def slow():
        started.set()
        gate.wait(60)

    def submitter():
        w.submit(slow)
        handed.append(1)
        for _ in range(10):
            w.submit(lambda: np.zeros(1000))
            handed.append(1)

    t = threading.Thread(target=submitter, daemon=True)
    t.start()
    assert started.wait(30)
    deadline = time.monotonic() + 30
    while w._queue.qsize() < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    t.join(0.3)
    # One job being written, ORDERED_AHEAD - 1 waiting for it on the ordered thread, one the writer holds and two
    # in the queue: the others wait in the caller, not in memory.
    assert t.is_alive() and w._queue.qsize() == 2 and len(handed) <= ORDERED_AHEAD + 1 + 2 < 11
    gate.set()
    t.join(30)
    w.flush()
    w.close()
    assert len(handed) == 11


def test_a_frames_files_on_lanes_are_written_side_by_side_and_what_lists_them_after_all():
    """Jobs on two lanes run at once (each waits for the other at a barrier: one after the other would never
    pass it); a job without a lane (the frame's run.json) starts only once both are done, on a thread of its
    own, the run.jsons in order; flush waits for the lanes."""
    meet = [threading.Barrier(2, timeout=30) for _ in range(3)]  # a frame's two files meet each other
    log, lock = [], threading.Lock()

    def file(name):
        def job():
            meet[int(name[-1])].wait()  # BrokenBarrierError after 30 s if the other lane's job is not running
            time.sleep(0.05 if name.startswith("fluid") else 0)
            with lock:
                log.append((name, threading.current_thread().name))
        return job

    with FrameWriter(maxsize=2, name="w") as w:
        for k in range(3):
            w.submit(file(f"fluid{k}"), "fluid", lane="fluid")
            w.submit(file(f"diffuse{k}"), "diffuse", lane="diffuse")
            w.submit(lambda k=k: log.append((f"run.json{k}", threading.current_thread().name)), "run.json")
        w.flush()
        assert len(log) == 9
    at = {n: i for i, (n, _) in enumerate(log)}
    for k in range(3):  # the diffuse file (no sleep) finished first: the two ran at once; run.json after both
        assert at[f"diffuse{k}"] < at[f"fluid{k}"] < at[f"run.json{k}"]
    assert at["run.json0"] < at["run.json1"] < at["run.json2"]
    threads = {n.rstrip("0123456789"): t for n, t in log}
    assert threads["run.json"].startswith("w-ordered") and threads["fluid"].startswith("w-fluid")
    assert threads["diffuse"].startswith("w-diffuse")


def test_the_next_frames_files_are_written_while_the_last_frames_run_json_waits():
    """Frame k + 1's files go on while a job without a lane handed over before them (frame k's run.json, its
    checkpoint) is still being written: the lanes never wait for what lists the files before theirs."""
    gate, listing = threading.Event(), threading.Event()
    done = []

    def slow_run_json():
        listing.set()
        gate.wait(60)
        done.append("run.json0")

    w = FrameWriter(maxsize=2)
    w.submit(lambda: done.append("fluid0"), "fluid", lane="fluid")
    w.submit(slow_run_json, "run.json")
    assert listing.wait(30)
    next_file = threading.Event()
    w.submit(lambda: (done.append("fluid1"), next_file.set()), "fluid", lane="fluid")
    assert next_file.wait(30)  # written while run.json0 still runs
    w.submit(lambda: done.append("run.json1"), "run.json")
    assert done == ["fluid0", "fluid1"]
    gate.set()
    w.flush()
    w.close()
    assert done == ["fluid0", "fluid1", "run.json0", "run.json1"]


def test_a_lane_writes_depth_files_side_by_side_and_holds_the_next_back():
    """A lane runs ``depth`` of its jobs at once (frame k's diffuse file and frame k + 1's meet at a barrier: one
    after the other would never pass it); the next waits until one of them is done."""
    meet = threading.Barrier(2, timeout=30)
    gate = threading.Event()
    log = []

    def file(k):
        def job():
            meet.wait()
            gate.wait(60)
            log.append(k)
        return job

    w = FrameWriter(maxsize=2, depth=2)
    w.submit(file(0), "diffuse", lane="diffuse")
    w.submit(file(1), "diffuse", lane="diffuse")
    third = threading.Event()
    w.submit(third.set, "diffuse", lane="diffuse")
    assert not third.wait(0.3) and log == []  # held back: both threads of the lane are busy
    gate.set()
    assert third.wait(30)
    w.flush()
    w.close()
    assert sorted(log) == [0, 1]


def test_an_error_on_a_lane_skips_what_would_list_its_file_and_reaches_the_caller():
    """A failed file: the file beside it is written, what would list it is skipped, and so is a job that starts
    after the failure (on the failed lane, of depth 1 here, the next job starts only once the failed one is
    done)."""
    done = []
    w = FrameWriter(maxsize=4, depth=1)
    beside = threading.Event()

    def full():
        beside.wait(30)  # fails once the fluid file beside it is written
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/run/diffuse/diffuse_00003.ply")

    def fluid():
        done.append("fluid")
        beside.set()

    w.submit(full, "diffuse", lane="diffuse")
    w.submit(fluid, "fluid", lane="fluid")  # beside it: written
    w.submit(lambda: done.append("run.json"), "run.json")  # would list the diffuse file: skipped
    w.submit(lambda: done.append("next diffuse"), "diffuse", lane="diffuse")  # after the failure: skipped
    with pytest.raises(OSError) as err:
        w.flush()
    assert err.value.filename == "/run/diffuse/diffuse_00003.ply"
    w.close()
    assert done == ["fluid"]


def test_a_lane_of_depth_one_holds_one_job_and_flush_waits_for_it():
    """A lane's next job waits in the writer's bounded queue, not in the lane: a slow disk still blocks the
    caller, with at most the lane's job, the one the writer holds and ``maxsize`` queued in memory."""
    gate, started = threading.Event(), threading.Event()
    finished = []
    w = FrameWriter(maxsize=1, depth=1)

    def slow():
        started.set()
        gate.wait(60)
        finished.append("slow")

    w.submit(slow, lane="fluid")
    assert started.wait(30)
    w.submit(lambda: finished.append("second"), lane="fluid")  # taken by the writer, which waits for the lane
    deadline = time.monotonic() + 30
    while w._queue.qsize() and time.monotonic() < deadline:
        time.sleep(0.01)
    w.submit(lambda: finished.append("third"), lane="fluid")  # in the queue, which is now full
    fourth = threading.Thread(target=lambda: w.submit(lambda: finished.append("fourth"), lane="fluid"), daemon=True)
    fourth.start()
    flusher = threading.Thread(target=w.flush, daemon=True)
    fourth.join(0.3)
    flusher.start()
    flusher.join(0.3)
    assert fourth.is_alive() and flusher.is_alive() and finished == []
    gate.set()
    fourth.join(30)
    flusher.join(30)
    w.flush()
    assert not flusher.is_alive() and finished == ["slow", "second", "third", "fourth"]
    w.close()


def test_a_lane_without_a_thread_fails_as_a_write_would_and_flush_does_not_hang(monkeypatch):
    """No thread to be had for a lane (the process at its limit): the job's error reaches the caller and what
    would list its file is skipped, instead of the writer's thread dying with its jobs unfinished."""
    from whitecap.io import writer as wr

    def no_thread(*args, **kwargs):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(wr, "ThreadPoolExecutor", no_thread)
    done = []
    w = FrameWriter(maxsize=2)
    w.submit(lambda: done.append("fluid"), "fluid", lane="fluid")
    w.submit(lambda: done.append("run.json"), "run.json")
    flusher = threading.Thread(target=lambda: pytest.raises(RuntimeError, w.flush), daemon=True)
    flusher.start()
    flusher.join(30)
    assert not flusher.is_alive() and done == []
    w.close()
    assert "can't start new thread" in str(w.error)


# ----------------------------------------------------------------------------- simulate
def test_run_json_never_lists_an_incomplete_file_and_checkpoints_follow_their_frames(tmp_path, monkeypatch):
    """A slow writer: each run.json saved lists only files already on disk, the foam stage's too, which
    the writer's thread writes (not the loop's), as does each counts.csv, and the checkpoint of frame k is
    written once run.json lists every frame up to k."""
    import whitecap.diffuse.driver as foam_driver
    import whitecap.sim.driver as driver

    run = tmp_path / "R"
    bad, threads = [], set()
    real_save, real_text, real_write, real_arrays = RunInfo.save, driver.write_text, driver.write, driver.write_arrays
    real_foam_write, real_foam_text = foam_driver.write, foam_driver.write_text

    def unwritten(run_dir, frames) -> list:
        return [rel for f in frames for rel in f["files"].values() if not (Path(run_dir) / rel).is_file()]

    def save(self, run_dir):  # the saves before the first frame
        bad.extend(unwritten(run_dir, [f.model_dump() for f in self.frames]))
        real_save(self, run_dir)

    def save_text(path, text):  # a frame's run.json, handed to the writer as text
        if Path(path).name == "run.json":
            bad.extend(unwritten(Path(path).parent, json.loads(text)["frames"]))
        real_text(path, text)

    def slow_write(path, frame):
        time.sleep(0.05)  # the loop runs ahead of the disk: only the queue's order keeps run.json honest
        real_write(path, frame)

    def slow_foam_write(path, frame):
        threads.add(threading.current_thread().name)
        time.sleep(0.05)
        real_foam_write(path, frame)

    def save_counts(path, text):  # counts.csv: its rows' frames' diffuse files are on disk
        rows = [int(line.split(",")[0]) for line in text.splitlines()[1:]]
        bad.extend(f"counts.csv row {k}" for k in rows
                   if not (Path(path).parent / f"diffuse_{k:05d}.ply").is_file())
        real_foam_text(path, text)

    def checkpoint(path, data):
        k = int(data["frame"])
        listed = sorted({i for i in _listed(run).values()})
        if listed[: k + 1] != list(range(k + 1)):
            bad.append(f"checkpoint {k} before frames {listed}")
        real_arrays(path, data)

    monkeypatch.setattr(RunInfo, "save", save)
    monkeypatch.setattr(driver, "write_text", save_text)
    monkeypatch.setattr(driver, "write", slow_write)
    monkeypatch.setattr(foam_driver, "write", slow_foam_write)
    monkeypatch.setattr(foam_driver, "write_text", save_counts)
    monkeypatch.setattr(driver, "write_arrays", checkpoint)
    scene = tiny_scene_dict(output={"frames": 5, "checkpoint_interval": 2},
                            foam={"preset": "auto", "k_ta": 400.0, "k_wc": 5000.0})
    simulate(scene_from_dict(scene), out=run, show_progress=False)
    assert bad == []
    listed = _listed(run)
    assert sorted(set(listed.values())) == [0, 1, 2, 3, 4, 5]
    # on the writer's diffuse lane, beside the frame's fluid file (and the next frame's)
    assert sum(rel.startswith("diffuse/") for rel in listed) == 6 and 1 <= len(threads) <= LANE_DEPTH
    assert all(t.startswith("whitecap-writer-diffuse") for t in threads)


def test_output_is_byte_identical_with_the_writer_on_and_off(tmp_path, monkeypatch):
    import whitecap.sim.driver as driver

    d = tiny_scene_dict(output={"frames": 3, "formats": ["ply", "npz"], "checkpoint_interval": 2},
                        foam={"preset": "auto", "k_ta": 400.0, "k_wc": 5000.0})
    simulate(scene_from_dict(d), out=tmp_path / "on", show_progress=False)
    monkeypatch.setattr(driver, "BACKGROUND_WRITER", False)
    simulate(scene_from_dict(d), out=tmp_path / "off", show_progress=False)
    on, off = _snapshot(tmp_path / "on"), _snapshot(tmp_path / "off")
    assert on.keys() == off.keys() and "diffuse/diffuse_00003.ply" in on and "fluid/fluid_00003.npz" in on
    # run.json records where the scene lies (the same here) and nothing of the run directory's own path
    assert [k for k in on if on[k] != off[k]] == []


def test_disk_full_in_the_writer_is_one_line_naming_the_file_and_resume_continues(tmp_path, monkeypatch, capsys):
    full_run, run = tmp_path / "full", tmp_path / "R"
    simulate(scene_from_dict(SCENE), out=full_run, show_progress=False, foam=False)
    scene_toml = tmp_path / "s.toml"
    scene_toml.write_text(scene_from_dict(SCENE).to_toml())
    real_replace = os.replace

    def replace(src, dst):
        if str(dst).endswith("fluid_00003.ply"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    code = main(["simulate", str(scene_toml), "--out", str(run), "--no-foam"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("error")]  # after the progress bar
    assert code == 5 and len(err) == 1, err
    err = err[0]
    assert err == f"error: {run / 'fluid' / 'fluid_00003.ply'}: No space left on device", err
    listed = _listed(run)
    assert "fluid/fluid_00003.ply" not in listed and max(listed.values()) <= 2  # nothing after the failed file
    assert not list(run.rglob("*.tmp*"))
    assert int(np.load(run / "checkpoint.npz")["frame"]) == 2
    monkeypatch.setattr(os, "replace", real_replace)
    assert main(["simulate", str(scene_toml), "--out", str(run), "--no-foam", "--resume"]) == 0
    a, b = _snapshot(full_run), _snapshot(run)
    assert sorted(a) == sorted(b)
    assert [k for k in a if k.startswith("fluid/") and a[k] != b[k]] == []


CHILD = textwrap.dedent("""
    import json, os, sys, time
    sys.path.insert(0, {src!r})
    import whitecap.sim.driver as driver
    driver.BACKGROUND_WRITER = True
    from whitecap.config import scene_from_dict
    from whitecap.io.atomic import atomic_path
    from whitecap.pipeline import simulate

    real = driver.write
    signal_file = {signal!r}

    def write(path, frame):
        if path.name == "fluid_00003.ply":  # half a file in its temporary name, then wait for SIGKILL
            with atomic_path(path) as tmp:
                tmp.write_bytes(b"ply\\nformat binary_little_endian 1.0\\n")
                open(signal_file, "w").close()
                time.sleep(600)
        return real(path, frame)

    driver.write = write
    simulate(scene_from_dict(json.loads({scene!r})), out={out!r}, show_progress=False, foam=False)
""")


def test_kill_9_while_a_frame_is_being_written_resumes_byte_identical(tmp_path):
    full_run, run, sig = tmp_path / "full", tmp_path / "R", tmp_path / "writing"
    simulate(scene_from_dict(SCENE), out=full_run, show_progress=False, foam=False)
    code = CHILD.format(src=str(ROOT / "src"), signal=str(sig), scene=json.dumps(SCENE), out=str(run))
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             env={**os.environ, "WHITECAP_PROGRESS": "0"})
    kill_when(child, sig, "frame 3's write")
    # Killed mid-file: its temporary file is there, the file itself is not, and run.json does not list it.
    assert list((run / "fluid").glob(".fluid_00003.*.tmp.ply")) and not (run / "fluid" / "fluid_00003.ply").exists()
    listed = _listed(run)
    full = _snapshot(full_run)
    for rel in listed:  # every file run.json lists is complete: the very bytes of the uninterrupted run
        assert (run / rel).read_bytes() == full[rel], rel
    k = int(np.load(run / "checkpoint.npz")["frame"])
    assert k == 2 and sorted(set(listed.values())) == [0, 1, 2]  # the checkpoint follows its frames
    simulate(scene_from_dict(SCENE), out=run, resume=True, show_progress=False, foam=False)
    after = _snapshot(run)
    assert sorted(after) == sorted(full)  # the temporary file is swept
    assert [rel for rel in full if full[rel] != after[rel]] == []


def test_device_idle_has_nothing_to_wait_for_on_the_cpu():
    """On the CPU a kernel is done when its launch returns: runtime.device_idle waits for nothing."""
    from whitecap.sim import runtime

    runtime.init("cpu")
    assert runtime.device_idle() is False


def test_the_switch_interval_is_short_while_a_writer_runs_and_restored_after():
    """While any FrameWriter runs, the interpreter's switch interval is writer.SWITCH_INTERVAL (the writer's
    thread gets the GIL back soon after each call that let it go); after the last one closes, the one before."""
    import sys

    from whitecap.io import writer as wr

    before = sys.getswitchinterval()
    a = FrameWriter()
    b = FrameWriter()
    assert sys.getswitchinterval() == pytest.approx(min(before, wr.SWITCH_INTERVAL))
    a.close()
    assert sys.getswitchinterval() == pytest.approx(min(before, wr.SWITCH_INTERVAL))
    b.close()
    b.close()  # twice: no second restore
    assert sys.getswitchinterval() == pytest.approx(before)


def test_a_diffuse_frame_still_coming_back_from_the_device_is_written_and_checkpointed_whole(tmp_path, monkeypatch):
    """On CUDA the foam stage leaves each frame's read-back running on a thread of its own while the next frame
    is computed (runtime.rows_to_host_later, FoamGenerator.pending). Here a stand-in makes that copy late, on
    another thread, into host arrays first filled with 0xFF (the records packed into a Taichi array first, as on
    CUDA: runtime.copies_rows): the diffuse files and checkpoints must be the same
    bytes as those of the copy made at once, so the writer and the checkpoint wait for it."""
    from concurrent.futures import ThreadPoolExecutor

    from whitecap.sim import runtime

    scene = scene_from_dict(tiny_scene_dict(output={"frames": 8, "checkpoint_interval": 3}, foam={"enabled": True}))
    simulate(scene, out=tmp_path / "now", show_progress=False)
    pool, late = ThreadPoolExecutor(max_workers=1), []

    def rows_to_host_later(*pairs, then=None):
        rows = [(host, nd.to_numpy()[: len(host)]) for host, nd in pairs]  # the device's rows as they are now
        for host, _ in rows:
            host.view(np.uint8).fill(0xFF)  # what a read before the copy would see

        def copy() -> bool:
            time.sleep(0.05)
            for host, r in rows:
                host[...] = r
            if then is not None:
                then()
            return True

        late.append(sum(len(h) for h, _ in rows))
        return pool.submit(copy)

    monkeypatch.setattr(runtime, "rows_to_host_later", rows_to_host_later)
    monkeypatch.setattr(runtime, "copies_rows", lambda: True)  # the records packed into a device array, as on CUDA
    simulate(scene, out=tmp_path / "late", show_progress=False)
    pool.shutdown()
    assert sum(late) > 0, "no diffuse particle was read back late"
    now, later = _snapshot(tmp_path / "now"), _snapshot(tmp_path / "late")
    assert any(k.startswith("diffuse/") for k in now) and "checkpoint.npz" in now
    assert later == now


def test_the_next_frames_kernels_run_while_the_last_frames_records_come_back_never_packing_over_them(
        tmp_path, monkeypatch):
    """On CUDA a frame's diffuse records come back on a thread of their own while the next frame is computed: the
    next step's advection runs before that copy is done (the loop waits for it only where the records' device array
    is packed again, FoamGenerator._download), and no records array is packed while a copy of it is in flight.
    Here a stand-in copy (as in the test above) finishes only once the next frame's advection has started, or after
    a second without it (the next frame waited for the copy first, as before 2026-11-28), and then stays in flight
    0.3 s more: a pack of its records that does not wait for it finds it in flight, which stops the run.
    The files are those of copies made at once."""
    from concurrent.futures import ThreadPoolExecutor

    from whitecap.diffuse import kernels as K
    from whitecap.sim import records, runtime

    scene = scene_from_dict(tiny_scene_dict(output={"frames": 6}, foam={"enabled": True}))
    simulate(scene, out=tmp_path / "now", show_progress=False)
    pool, advected, packing = ThreadPoolExecutor(max_workers=1), threading.Event(), threading.Event()
    in_flight: set[int] = set()  # the device arrays a copy still reads
    overlapped: list[bool] = []  # per copy: the next frame's advection started before it was done

    advect = K.advect_diffuse
    monkeypatch.setattr(K, "advect_diffuse", lambda *a: advected.set() or advect(*a))
    made = records.RecordReader.__init__

    def guarded_reader(self, *a, **kw):
        made(self, *a, **kw)
        pack = self.pack

        def guarded(n, *args):
            if id(args[-1]) in in_flight:  # (the fluid's records, packed every frame too, are never in flight)
                packing.set()
                raise AssertionError("records packed over while their copy is in flight")
            return pack(n, *args)

        self.pack = guarded

    def rows_to_host_later(*pairs, then=None):
        rows = [(host, nd.to_numpy()[: len(host)]) for host, nd in pairs]  # the device's rows as they are now
        keys = {id(nd) for _, nd in pairs}
        in_flight.update(keys)
        advected.clear()
        packing.clear()

        def copy() -> bool:
            overlapped.append(advected.wait(1.0))
            packing.wait(0.3)
            for host, r in rows:
                host[...] = r
            in_flight.difference_update(keys)
            if then is not None:
                then()
            return True

        return pool.submit(copy)

    monkeypatch.setattr(records.RecordReader, "__init__", guarded_reader)
    monkeypatch.setattr(runtime, "rows_to_host_later", rows_to_host_later)
    monkeypatch.setattr(runtime, "copies_rows", lambda: True)  # the records packed into a device array, as on CUDA
    simulate(scene, out=tmp_path / "late", show_progress=False)
    pool.shutdown()
    assert len(overlapped) >= 3 and all(overlapped[:-1]), overlapped  # the last frame has no next one
    assert _snapshot(tmp_path / "late") == _snapshot(tmp_path / "now")


def test_a_collection_on_another_thread_makes_taichis_context_current_there_first(monkeypatch):
    """runtime._context_for_collection (CUDA only; here with a stand-in for libcuda): a cyclic collection that
    starts on a thread without Taichi's context (the writer's, which may free a Taichi ndarray there) makes it
    current on that thread first, once a thread; the thread that started Taichi, and a collection's end, call
    nothing. On an H100 the same free without it aborted the process (tests/test_gpu.py)."""
    import gc

    from whitecap.sim import runtime

    calls = []

    class Lib:
        def cuCtxSetCurrent(self, ctx):
            calls.append((threading.current_thread().name, ctx.value))
            return 0

    monkeypatch.setattr(runtime, "_LIBCUDA", Lib())
    monkeypatch.setattr(runtime, "_CONTEXT", __import__("ctypes").c_void_p(0xC0FFEE))
    monkeypatch.setattr(runtime, "_THREAD", threading.local())
    runtime._THREAD.has_context = True  # this thread started Taichi (runtime._free_on_any_thread)

    def collect_twice():
        gc.collect()
        gc.collect()

    gc.callbacks.append(runtime._context_for_collection)  # (the interpreter holds this very list)
    try:
        gc.collect()  # on the thread that has the context: nothing to do
        t = threading.Thread(target=collect_twice, name="writer-like")
        t.start()
        t.join()
        assert calls == [("writer-like", 0xC0FFEE)]  # once, before the first collection there
        u = threading.Thread(target=gc.collect, name="another")
        u.start()
        u.join()
    finally:
        gc.callbacks.remove(runtime._context_for_collection)
    assert calls == [("writer-like", 0xC0FFEE), ("another", 0xC0FFEE)]


def test_frames_made_as_their_files_records_are_the_files_and_checkpoints_of_frames_packed_by_the_writer(
        tmp_path, monkeypatch):
    """simulate with foam: the solver's fluid frames and the foam stage's diffuse frames come back as their PLY
    records, made by sim.records' kernels (the frames' arrays views of them, which the writer writes as they are);
    every file of the run (fluid PLY and npz, diffuse, checkpoints, run.json) is the same bytes as with every frame
    read back array by array and packed by the writer (sim.records.WORDS_MAX 0), and the writer packs none."""
    from whitecap.io import ply
    from whitecap.sim import pbf, records

    scene = scene_from_dict(tiny_scene_dict(output={"frames": 6, "checkpoint_interval": 2, "formats": ["ply", "npz"]},
                                            foam={"preset": "auto", "k_ta": 400.0, "k_wc": 5000.0}))
    with monkeypatch.context() as m:
        m.setattr(records, "WORDS_MAX", 0)
        simulate(scene, out=tmp_path / "arrays", show_progress=False)
    made = []
    arrays = pbf.PBFSolver.arrays

    def watched(solver, *a, **kw):
        got = arrays(solver, *a, **kw)
        made.append(got.get("records") is not None and np.shares_memory(got["positions"], got["records"]))
        return got

    def no_packing(*a):
        raise AssertionError("the writer packed a frame made as its records")

    monkeypatch.setattr(pbf.PBFSolver, "arrays", watched)
    monkeypatch.setattr(ply, "_pack", no_packing)
    simulate(scene, out=tmp_path / "records", show_progress=False)
    assert made and all(made)
    a, b = _snapshot(tmp_path / "arrays"), _snapshot(tmp_path / "records")
    assert "checkpoint.npz" in a and any(k.startswith("fluid/") and k.endswith(".npz") for k in a)
    assert max(len(v) for k, v in a.items() if k.startswith("diffuse/")) > 400 + 37 * 5  # diffuse particles written
    assert a == b


def test_a_finished_run_extended_steps_on_from_its_last_frame(tmp_path, monkeypatch):
    """Checkpoints every 2 frames, a run of 5: its last frame is checkpointed too (not only the multiples of the
    interval), so that the run extended to 7 frames steps on from frame 5 and writes frames 6 and 7 alone, not
    frame 5 again from the checkpoint of frame 4."""
    import whitecap.sim.driver as driver

    run = tmp_path / "R"
    simulate(scene_from_dict(SCENE), out=run, show_progress=False, foam=False)
    assert int(np.load(run / "checkpoint.npz")["frame"]) == 5
    written, real = [], driver.write
    monkeypatch.setattr(driver, "write", lambda path, *a, **kw: written.append(Path(path).name) or real(path, *a, **kw))
    simulate(scene_from_dict(SCENE), out=run, resume=True, frames=7, show_progress=False, foam=False)
    assert sorted(set(written)) == ["fluid_00006.ply", "fluid_00007.ply"]
    assert sorted(set(_listed(run).values())) == list(range(8))


def test_the_foam_stage_waits_for_its_heavy_kernels_with_the_gil_let_go(monkeypatch):
    """On a GPU, Taichi's own waits (a kernel's return value, a read into NumPy) hold the GIL while the device works,
    so the writer's and the reader's threads stand still meanwhile. After each of the foam stage's heavy kernels
    (the potentials, the advection, a chunk's classification) runtime.device_idle waits first, with the GIL let
    go. Here, with every launch recorded in order over a splash that makes thousands of candidates, no read-back
    follows a heavy kernel without a device_idle between them."""
    from tests.test_diffuse_generate import DT, _generator, _splash
    from whitecap.diffuse import kernels as K
    from whitecap.sim import runtime, scan

    runtime.init("cpu")
    events: list[str] = []

    def spy(module, name, kind):
        real = getattr(module, name)

        def call(*args, **kw):
            out = real(*args, **kw)
            events.append(f"{kind} {name}")
            return out

        monkeypatch.setattr(module, name, call)

    for name in ("fluid_potentials", "advect_diffuse", "classify_candidates"):
        spy(K, name, "heavy")
    for name in ("mark_crest_neighbours", "pack_potentials", "birth_sums", "birth_counts", "tally_kinds"):
        spy(K, name, "read")
    spy(scan, "prefix_sum", "read")
    idle = runtime.device_idle
    monkeypatch.setattr(runtime, "device_idle", lambda: events.append("idle") or idle())
    gen = _generator((30.0, 1.0, 1.0))
    made = 0
    for k in range(4):
        f = _splash()
        f.positions = f.positions + k * DT * f.velocities
        made += len(gen.step(f, k, DT))
    waiting = None
    for e in events:
        if e.startswith("heavy"):
            waiting = e
        elif e == "idle":
            waiting = None
        else:
            assert waiting is None, f"{e} after {waiting} without device_idle"
    ran = {e for e in events if e != "idle"}
    assert made and {"heavy advect_diffuse", "heavy classify_candidates", "read mark_crest_neighbours"} <= ran, ran
