"""Cluster runs as users meet them when something is off (issue 30).

- A frame is the same bytes whichever executor meshes it: this process, a
  local pool worker, a Dask worker (splashsurf's threads used to change the
  last bits of a large frame from run to run).
- ``--cluster`` with a malformed address, a listener that never answers, or
  a service that answers junk: one line, within the connect timeout.
- ``--cluster local`` starts no dashboard and prints no socket warning; a
  worker's death prints no raw Dask log line.
- A partly done cluster run resumes with each result recorded as the frame it
  belongs to, when frames finish out of order; a frame whose result was lost
  with its worker and made again is delivered with its value.
- A local cluster that cannot start, and a scene.blend save whose worker
  died: one line each.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import signal
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")


from whitecap import pipeline  # noqa: E402
from whitecap.cli import main  # noqa: E402
from whitecap.executor import NO_DASHBOARD  # noqa: E402  (test clusters start as whitecap's: no fixed port)
from whitecap.io import ParticleFrame, read_mesh, write as write_particles  # noqa: E402
from whitecap.io.run import RunInfo  # noqa: E402

from .test_cluster import _files, _small_run  # noqa: E402  (a copy of the tiny run with a quick preview)


@pytest.fixture(scope="module")
def worker_processes():
    """One Dask worker in its own process, as on a real cluster (one thread: frames bring their own)."""
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=logging.CRITICAL, scheduler_kwargs=NO_DASHBOARD) as c:
        yield c


# ============================================================================ item 13: the same bytes anywhere
R = 0.004  # particle radius [m]: spacing 8 mm


def dam_break_frame(seed: int = 3) -> ParticleFrame:
    """About 30k particles a moment after a dam break: a leaning column, a tongue along the floor, spray."""
    rng = np.random.default_rng(seed)
    s = 2 * R
    g = np.stack(np.meshgrid(np.arange(0, 0.24, s), np.arange(0, 0.20, s), np.arange(0, 0.32, s), indexing="ij"),
                 -1).reshape(-1, 3)
    g[:, 0] += 0.6 * g[:, 2] ** 2  # the column's top leans downstream
    tongue = np.stack(np.meshgrid(np.arange(0.24, 0.50, s), np.arange(0, 0.20, s), np.arange(0, 2 * s, s),
                                  indexing="ij"), -1).reshape(-1, 3)
    spray = rng.uniform([0.35, 0.0, 0.02], [0.55, 0.20, 0.15], (600, 3))
    pos = np.concatenate([g, tongue, spray]) + R
    pos[: len(g) + len(tongue)] += rng.normal(0, 0.1 * s, (len(g) + len(tongue), 3))
    vel = np.zeros_like(pos)
    vel[:, 0] = 2.5 * np.sqrt(np.clip(0.35 - pos[:, 2], 0, None) / 0.35) + rng.normal(0, 0.05, len(pos))
    vel[:, 2] = -1.5 * pos[:, 2] / 0.3 + rng.normal(0, 0.05, len(pos))
    return ParticleFrame(positions=pos, velocities=vel, density=np.full(len(pos), 1000.0))


def mesh_and_digest(src: str, out: str, params) -> tuple[str, bytes, int]:
    """Mesh one frame here (whichever process this is) and say what splashsurf handed back.

    Returns a digest of splashsurf's own arrays (vertex order, positions,
    triangles, normals, velocities: before whitecap rounds anything), the mesh
    file's bytes, and the particle count.
    """
    import pysplashsurf

    from whitecap.surface.reconstruct import mesh_frame

    real, raw = pysplashsurf.reconstruction_pipeline, []

    def spy(*args, **kw):
        result = real(*args, **kw)
        raw.append(result[0])
        return result

    pysplashsurf.reconstruction_pipeline = spy
    try:
        stats = mesh_frame(src, out, params)
    finally:
        pysplashsurf.reconstruction_pipeline = real
    assert len(raw) == 1, "mesh_frame no longer calls pysplashsurf.reconstruction_pipeline: update this test"
    m, h = raw[0], hashlib.sha256()
    for a in [m.mesh.vertices, m.mesh.triangles] + [m.point_attributes[k] for k in sorted(m.point_attributes)]:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest(), Path(out).read_bytes(), stats["particles"]


def test_a_large_frame_is_the_same_bytes_whatever_meshes_it(tmp_path, worker_processes, monkeypatch):
    """The settings a cluster worker gets (pipeline.mesh plans it as one frame per machine) and those a
    local pool gets, in this process, in spawned pool workers and in a Dask worker process, several times:
    every mesh file is the same bytes, and so is what splashsurf itself returned, so the files agree
    because the computation does, not because the rounding happened to hide a difference this time."""
    import cloudpickle

    from whitecap.executor import LocalExecutor
    from whitecap.surface.driver import plan

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    # A site or user environment that asks rayon (splashsurf's thread pool) for several threads.
    monkeypatch.setenv("RAYON_NUM_THREADS", "4")
    seq = tmp_path / "seq"
    write_particles(seq / "fluid_00000.ply", dam_break_frame())
    src = str(seq / "fluid_00000.ply")
    on_worker = local = plan(src, radius=R).params  # what a remote worker and a local pool both mesh with
    out = tmp_path / "out"
    out.mkdir()
    runs = {f"here-{k}": mesh_and_digest(src, str(out / f"here{k}.ply"), p)
            for k, p in enumerate([on_worker, local])}
    for r in LocalExecutor(2).map(mesh_and_digest, [(0, (src, str(out / "pool0.ply"), on_worker)),
                                                    (1, (src, str(out / "pool1.ply"), local))]):
        runs[f"pool-{r.index}"] = r.value
    with distributed.Client(worker_processes.scheduler_address, set_as_default=False) as client:
        runs["dask"] = client.submit(mesh_and_digest, src, str(out / "dask.ply"), on_worker, pure=False).result()
    assert min(n for _, _, n in runs.values()) > 30_000  # large enough to show splashsurf's thread noise
    digests = {k: d for k, (d, _, _) in runs.items()}
    assert len(set(digests.values())) == 1, f"splashsurf's output differs between runs: {digests}"
    files = {k: hashlib.sha256(b).hexdigest()[:12] for k, (_, b, _) in runs.items()}
    assert len(set(files.values())) == 1, f"mesh files differ: {files}"


# ============================================================================ items 15, 16: bad addresses
def _cli_within(args: list[str], limit: float = 60.0) -> tuple[int | None, float]:
    """``whitecap ARGS`` in a thread: its exit status (None if it had not returned after ``limit`` s) and time.

    An exception out of ``main`` (a traceback for the user) fails the test at once."""
    box: dict = {}

    def go() -> None:
        try:
            box["rc"] = main(args)
        except BaseException as exc:  # noqa: BLE001
            box["exc"] = exc

    t = threading.Thread(target=go, daemon=True)
    t0 = time.monotonic()
    t.start()
    t.join(limit)
    if "exc" in box:
        raise AssertionError(f"whitecap {' '.join(args)} ended in a traceback: {box['exc']!r}") from box["exc"]
    return box.get("rc"), time.monotonic() - t0


class Listener:
    """A local TCP service in a thread that accepts connections and answers each with ``reply`` (or nothing)."""

    def __init__(self, reply: bytes | None = None):
        self.reply, self.conns = reply, []
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.accepted = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)

    def _serve(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except (socket.timeout, TimeoutError):
                continue
            except OSError:
                return
            self.accepted += 1
            self.conns.append(conn)
            if self.reply is not None:
                conn.sendall(self.reply)  # and then never a word more, nor a close

    def __enter__(self) -> "Listener":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(5)
        self.sock.close()
        for c in self.conns:
            c.close()


def _untouched(run: Path) -> None:
    assert not (run / "mesh").exists()
    assert not [p for p in run.iterdir() if p.name.startswith(".whitecap-probe")]


@pytest.fixture
def timed_run(tiny_run, tmp_path) -> Path:
    """A run whose [cluster] section waits 2 s for a scheduler."""
    return _small_run(tiny_run, tmp_path / "run", cluster={"connect_timeout": 2.0})


@pytest.mark.parametrize("spec", ["127.0.0.1", "lokal", "notaurl", "bogus://x"])
def test_a_malformed_address_is_refused_in_one_line_before_connecting(timed_run, capsys, monkeypatch, spec):
    def no_connection(*a, **kw):
        raise AssertionError(f"a connection was tried for --cluster {spec}")

    monkeypatch.setattr(socket, "create_connection", no_connection)
    monkeypatch.setattr(distributed, "Client", no_connection)
    rc, seconds = _cli_within(["mesh", str(timed_run), "--cluster", spec])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert "\n" not in err and "Traceback" not in err and err.startswith(f"error: --cluster {spec}: "), err
    for hint in ("local", "slurm", "pbs", "tcp://"):
        assert hint in err, (hint, err)
    if spec == "lokal":
        assert "did you mean 'local'" in err
    if spec == "127.0.0.1":
        assert "tcp://127.0.0.1:PORT" in err
    assert seconds < 30
    _untouched(timed_run)


def test_a_listener_that_never_answers_fails_within_the_connect_timeout(timed_run, capsys):
    with Listener(reply=None) as silent:
        address = f"tcp://127.0.0.1:{silent.port}"
        rc, seconds = _cli_within(["mesh", str(timed_run), "--cluster", address])
        assert silent.accepted >= 1  # it was reached, and it said nothing
    assert rc is not None, f"--cluster {address} still waiting after {seconds:.0f} s (connect_timeout is 2 s)"
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "Traceback" not in err, err
    assert err.startswith(f"error: --cluster {address}: ") and "did not answer as a Dask scheduler within 2 s" in err
    assert seconds < 30
    _untouched(timed_run)


# What a web server says to a stranger: its first 8 bytes, read as a Dask message length, are 3.5 EiB.
HTTP_REPLY = b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n"
# A plausible length followed by bytes that are no Dask message.
GARBAGE_REPLY = (24).to_bytes(8, "little") + b"\xff" * 24


@pytest.mark.parametrize("reply", [HTTP_REPLY, GARBAGE_REPLY], ids=["http", "garbage"])
def test_a_service_that_answers_junk_is_a_one_line_error(timed_run, capsys, reply):
    with Listener(reply=reply) as junk:
        rc, seconds = _cli_within(["mesh", str(timed_run), "--cluster", f"127.0.0.1:{junk.port}"])
    assert rc is not None, f"still waiting after {seconds:.0f} s"
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "Traceback" not in err, err
    assert err.startswith(f"error: --cluster 127.0.0.1:{junk.port}: ") and "not as a Dask scheduler" in err, err
    assert seconds < 30
    _untouched(timed_run)


# ============================================================================ the dashboard, Dask's log lines
def _get(url: str) -> int:
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status
    except urllib.error.HTTPError as exc:
        return exc.code


def test_cluster_local_starts_no_dashboard_and_no_port_warning(tmp_path, capfd):
    """Another program holds Dask's dashboard port 8787: no warning about it, and no dashboard page is served."""
    import warnings

    from whitecap.config import Cluster
    from whitecap.executor import connect

    held = socket.socket()
    try:
        held.bind(("", 8787))
        held.listen(1)
    except OSError:
        pass  # someone else holds it already: the same situation
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            ex = connect("local", tmp_path, Cluster(), jobs=1)
            try:
                http_port = ex.client.scheduler_info()["services"]["dashboard"]
                page = _get(f"http://127.0.0.1:{http_port}/status")
            finally:
                ex.close()
    finally:
        held.close()
    assert not [str(w.message) for w in caught if "8787" in str(w.message) or "port" in str(w.message).lower()]
    err = capfd.readouterr().err
    assert "already in use" not in err and "Traceback" not in err, err
    assert page == 404  # no dashboard, nor a page asking to install bokeh for one


def test_batch_cluster_scheduler_serves_no_dashboard():
    """slurm/pbs: the scheduler runs here; it serves no dashboard (whose link no one would be shown)."""
    from whitecap.config import Cluster
    from whitecap.executor import batch_cluster

    c = batch_cluster("slurm", Cluster())
    try:
        page = _get(f"http://127.0.0.1:{c.scheduler_info['services']['dashboard']}/status")
    finally:
        c.close()
    assert page == 404


class KillAtFrame(distributed.WorkerPlugin):
    """Test plugin: a worker dies (SIGKILL) whenever it is about to write the mesh of frame ``index``."""

    def __init__(self, index: int):
        self.index = index

    def setup(self, worker=None):
        import importlib

        rec = importlib.import_module("whitecap.surface.reconstruct")
        real, name = rec.write_mesh, f"fluid_{self.index:05d}."

        def write_mesh(path, surface):
            if Path(path).name.startswith(name):
                os.kill(os.getpid(), signal.SIGKILL)
            return real(path, surface)

        rec.write_mesh = write_mesh


TIMESTAMPED = re.compile(r"^\d{4}-\d\d-\d\d[ T]\d\d:\d\d:\d\d", re.M)
DASK_LOGGER = re.compile(r"\b(distributed|tornado)(\.\w+)* - (DEBUG|INFO|WARNING|ERROR|CRITICAL) - ")


def test_a_dying_worker_prints_no_raw_dask_log_line(tiny_run, tmp_path, capfd, monkeypatch):
    """`mesh --cluster local`: the worker that takes frame 2 dies every time. Dask logs an error about it
    (timestamped, with its logger's name); whitecap prints only its own lines: the bar, the summary and
    one error naming the frame."""
    import cloudpickle
    import dask

    from whitecap.executor import DaskExecutor

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    real_check = DaskExecutor.check_shared

    def check_shared(self):  # the test's hook into the cluster whitecap starts itself
        self.client.register_plugin(KillAtFrame(2), name="kill-at-frame-2")
        return real_check(self)

    monkeypatch.setattr(DaskExecutor, "check_shared", check_shared)
    monkeypatch.setenv("WHITECAP_PROGRESS", "1")  # the progress bar on, as in a terminal
    # Dask's logging as outside pytest (whose own log capture makes Dask skip it): a stderr handler
    # with timestamps on the 'distributed' logger, which does not propagate.
    dask_log = logging.getLogger("distributed")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s - %(name)s - %(levelname)s - %(message)s"))
    monkeypatch.setattr(dask_log, "handlers", [handler])
    monkeypatch.setattr(dask_log, "propagate", False)
    run = _small_run(tiny_run, tmp_path / "run")
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):  # the first death fails the frame
        rc = main(["mesh", str(run), "--cluster", "local", "--jobs", "2"])
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc != 0
    assert not TIMESTAMPED.search(err), err
    assert not DASK_LOGGER.search(err) and "Traceback" not in err, err
    assert lines[-1].startswith("error: mesh: 1 of 4 frames failed on the cluster (frame 2: KilledWorker"), lines[-1]
    assert [i for i, _ in RunInfo.load(run).files("mesh")] == [0, 1, 3]  # the others are kept


# ============================================================================ results belong to their frames
class LostThenRecomputed:
    """A Dask future as the client can see it when the worker holding its result dies just after it finished:
    no longer 'finished' (the scheduler is running the frame again), and result() waits for the new one."""

    def __init__(self, key: str, result, lost: bool):
        self.key, self._result = key, result
        self.status = "lost" if lost else "finished"

    def result(self, timeout=None):
        return self._result

    def exception(self, timeout=None):
        return None


class InlineClient:
    """Just enough of distributed.Client for DaskExecutor.map: runs each task here, at once."""

    loop = None

    def __init__(self, lost_key_prefix: str):
        self.lost = lost_key_prefix

    def submit(self, fn, *args, key: str, pure: bool = False):
        return LostThenRecomputed(key, fn(*args), lost=key.startswith(self.lost))

    def cancel(self, futures):
        pass

    def close(self):
        pass


def _double(x: int) -> int:
    return 2 * x


def test_a_frame_whose_result_was_lost_and_made_again_is_delivered(tmp_path, monkeypatch):
    from whitecap.executor import DaskExecutor

    monkeypatch.setattr(distributed, "as_completed", lambda futures, **kw: iter(futures))
    ex = DaskExecutor(InlineClient("frame-00002"), tmp_path)
    try:
        got = {r.index: (r.value, r.error) for r in ex.map(_double, [(i, (10 * i,)) for i in range(4)])}
    finally:
        ex.close()
    assert got == {i: (20 * i, None) for i in range(4)}


@pytest.fixture(scope="module")
def in_process_cluster():
    """Two worker threads in this process: a frame's writing can be slowed from the test."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None,
                                  silence_logs=logging.CRITICAL, scheduler_kwargs=NO_DASHBOARD) as c:
        yield c


def test_a_partly_done_cluster_run_resumes_with_each_result_recorded_as_its_own_frame(
        tiny_run, tmp_path, in_process_cluster, monkeypatch, capsys):
    """A first cluster run makes frames 0 and 3 (1 and 2 have broken inputs); with the inputs mended, the
    rerun makes only 1 and 2, and 2 finishes first. Every result is its own frame's: the stats, run.json
    and the files (the bytes of a serial run's)."""
    import importlib

    rec = importlib.import_module("whitecap.surface.reconstruct")  # the module, not surface's function
    address = in_process_cluster.scheduler_address
    reference = _small_run(tiny_run, tmp_path / "serial")
    pipeline.mesh(reference, jobs=1, show_progress=False)

    run = _small_run(tiny_run, tmp_path / "run")
    inputs = dict(RunInfo.load(run).files("fluid"))
    assert sorted(inputs) == [0, 1, 2, 3]
    kept = {i: (run / inputs[i]).read_bytes() for i in (1, 2)}
    for i in (1, 2):
        (run / inputs[i]).write_bytes(kept[i][:300])
    assert main(["mesh", str(run), "--cluster", address]) != 0
    assert [i for i, _ in RunInfo.load(run).files("mesh")] == [0, 3]
    first = {p.name: p.stat().st_mtime_ns for p in (run / "mesh").iterdir()}
    for i in (1, 2):
        (run / inputs[i]).write_bytes(kept[i])

    real, finished, frame_2_written = rec.write_mesh, [], threading.Event()

    def write_mesh(path, surface):
        if Path(path).name.startswith("fluid_00001."):
            frame_2_written.wait(60)  # frame 1 waits: frame 2, submitted after it, finishes first
        real(path, surface)
        finished.append(int(Path(path).name.split("_")[1].split(".")[0]))
        if Path(path).name.startswith("fluid_00002."):
            frame_2_written.set()

    monkeypatch.setattr(rec, "write_mesh", write_mesh)
    stats = pipeline.mesh(run, cluster=address, show_progress=False)
    capsys.readouterr()
    assert finished == [2, 1], f"the frames did not finish out of order ({finished}): the test tested nothing"
    assert [(s["index"], s["skipped"]) for s in stats] == [(0, True), (1, False), (2, False), (3, True)]
    for s in stats:
        assert Path(s["out"]).name == f"fluid_{s['index']:05d}.ply", s
    made = {s["index"]: s for s in stats if not s["skipped"]}
    assert made[1]["faces"] != made[2]["faces"]  # the frames differ, so a swap would show
    for i in (1, 2):  # each frame's stats describe that frame's file
        assert made[i]["faces"] == len(read_mesh(run / "mesh" / f"fluid_{i:05d}.ply").faces)
    assert dict(RunInfo.load(run).files("mesh")) == {i: f"mesh/fluid_{i:05d}.ply" for i in range(4)}
    assert _files(run / "mesh") == _files(reference / "mesh")
    assert {n: (run / "mesh" / n).stat().st_mtime_ns for n in first} == first  # frames 0 and 3 not made again


def test_a_local_cluster_that_does_not_start_is_one_line_with_a_hint(tiny_run, tmp_path, capsys, monkeypatch):
    """A script without the `if __name__ == '__main__':` guard makes each spawned worker run it again, and
    Dask's LocalCluster fails with 'Nanny failed to start'; whitecap says so in one line, with the remedy."""
    def nanny_fails(*args, **kw):
        raise RuntimeError("Nanny failed to start.")

    monkeypatch.setattr(distributed, "LocalCluster", nanny_fails)
    run = _small_run(tiny_run, tmp_path / "run")
    rc, _ = _cli_within(["mesh", str(run), "--cluster", "local"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err, err
    assert err.startswith("error: --cluster local: the local Dask cluster did not start (RuntimeError: Nanny failed")
    assert "if __name__ == '__main__':" in err
    _untouched(run)


class _Failing:
    class last_worker:
        address = "tcp://10.0.0.9:4000"

    def result(self):
        raise distributed.scheduler.KilledWorker("save-blend", self.last_worker, 3)


class _BlendCluster:
    """Just enough of a DaskExecutor for render_on_cluster: the task that saves scene.blend loses its worker."""

    cluster, frame_threads, summaries = True, 0, []

    class client:
        @staticmethod
        def submit(fn, *args, pure=False):
            return _Failing()

    def register(self, plugin, name):
        pass

    def unregister(self, name):
        pass


def test_saving_the_blend_file_on_a_dead_worker_is_one_line(tmp_path):
    from whitecap.errors import WhitecapError
    from whitecap.render.cluster import render_on_cluster

    with pytest.raises(WhitecapError) as err:
        render_on_cluster(_BlendCluster(), tmp_path, "preview", "CPU", [], True, None, None, lambda i: None)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("render: saving render/scene.blend on the cluster failed (KilledWorker")
