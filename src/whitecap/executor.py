"""Where per-frame work runs: a local process pool, or a Dask cluster.

The per-frame stages (``mesh``, ``render``, ``export``) are pure functions of
their frame: each reads its inputs from the run directory and writes its
output file there atomically (:mod:`whitecap.io.atomic`). They hand their
frames to an executor through one interface, :func:`map_frames`:

- :class:`LocalExecutor` (the default) runs them in this process (one job) or
  in a pool of spawned worker processes that die with their parent. No Dask
  is needed.
- :class:`ProcessWorkers` starts ``jobs`` long-lived worker processes from a command
  line, each given an interleaved share of the frames, for work whose set-up costs
  more than a frame (``render``: a Blender process builds its scene once, then renders
  frame after frame). Each worker says ``<word> N`` on a line per finished frame.
- :class:`DaskExecutor` (``--cluster ADDRESS|local|slurm|pbs``) submits one
  Dask task per frame. The run directory is the contract: it must be on a
  filesystem every worker sees. The client (this process) holds the run's
  writer lock, records finished frames in ``run.json`` and draws the progress
  bar; workers only write frame files. A frame whose worker dies is retried on
  another worker (the scheduler's ``allowed-failures``); the temporary file
  such a death leaves is removed by the client (:func:`whitecap.io.atomic.sweep_temps`).

Layering: this module sits beside :mod:`whitecap.workers`, under the stages;
it imports Dask only when a cluster is asked for.
"""

from __future__ import annotations

import asyncio
import difflib
import json
import logging
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from concurrent.futures import FIRST_COMPLETED, CancelledError, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable, Iterator, NoReturn

from .errors import InputError, MissingDependency, WhitecapError
from .workers import child_env, die_with_parent, end_process

CLUSTER_HINT = "install it with: pip install 'whitecap[cluster]' (dask, distributed, dask-jobqueue)"
#: the clusters --cluster starts itself; anything else is a scheduler address
CLUSTER_KINDS = ("local", "slurm", "pbs")
#: what --cluster takes, for error messages
ADDRESS_HINT = "give local, slurm, pbs or a scheduler's address tcp://HOST:PORT (`dask scheduler` prints it)"
#: the protocols a Dask scheduler address may name (distributed's comm backends)
SCHEMES = ("tcp", "tls", "ws", "wss", "ucx", "inproc")
#: a Dask scheduler greets every connection with its handshake, a message of this many bytes at most
MAX_HANDSHAKE = 1 << 20
#: scheduler options of the clusters whitecap starts: no dashboard (it needs bokeh, and no one is shown
#: its link); the scheduler's small HTTP server (health checks) on any free port of this machine, so that
#: a port another cluster holds is no warning
NO_DASHBOARD = {"dashboard": False, "dashboard_address": "127.0.0.1:0"}
#: the command each batch system submits jobs with (dask-jobqueue calls it)
SUBMIT_COMMAND = {"slurm": "sbatch", "pbs": "qsub"}
#: file name prefix of the probe written into the shared directory to check that workers see it
PROBE_PREFIX = ".whitecap-probe-"


class ClusterError(WhitecapError):
    """The cluster cannot do the work (scheduler unreachable, run directory not shared)."""


class FrameFailed(WhitecapError):
    """One or more frames failed on the cluster."""


@dataclass
class FrameResult:
    """One finished frame: its index, what the per-frame function returned, where and how long it ran."""

    index: int
    value: Any = None
    worker: str = ""
    seconds: float = 0.0
    error: BaseException | None = None


def _timed(fn: Callable, args: tuple) -> tuple[Any, str, float]:
    """Run ``fn(*args)`` and say where (worker name) and how long it ran (runs on the worker)."""
    t0 = time.perf_counter()
    value = fn(*args)
    return value, _worker_name(), time.perf_counter() - t0


def _worker_name() -> str:
    try:
        from distributed import get_worker

        w = get_worker()
        return str(w.name if w.name is not None and not str(w.name).isdigit() else w.address)
    except (ImportError, ValueError):
        import socket

        return f"{socket.gethostname()}:{os.getpid()}"


def _shared_task(probe: str, token: str, fn: Callable, args: tuple) -> tuple[Any, str, float]:
    """A Dask task: check this worker sees the client's run directory (its probe file), then run the frame."""
    seen = _probe(probe, token)
    if seen is not True:
        raise RunDirNotShared(f"{Path(probe).parent}: Dask worker {_worker_name()} cannot see the run directory "
                              f"({seen}); it must be on a filesystem shared by the client and every worker")
    return _timed(fn, args)


class RunDirNotShared(ClusterError):
    """A worker cannot see the shared run directory (raised on the worker, fatal for the run)."""


# ============================================================================ local
class LocalExecutor:
    """This process (``jobs`` = 1) or a pool of ``jobs`` spawned worker processes."""

    cluster = False

    def __init__(self, jobs: int = 1):
        self.jobs = max(1, int(jobs))

    def map(self, fn: Callable, tasks: list[tuple[int, tuple]]) -> Iterator[FrameResult]:
        """Yield a :class:`FrameResult` per task as it finishes; the first error is raised."""
        if self.jobs == 1 or len(tasks) <= 1:
            for index, args in tasks:
                value, worker, seconds = _timed(fn, args)
                yield FrameResult(index, value, worker, seconds)
            return
        # spawn, not fork: the parent may already hold a thread pool (splashsurf's,
        # Taichi's), which a forked child would inherit in a broken state.
        ctx = get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(self.jobs, len(tasks)), mp_context=ctx, initializer=die_with_parent,
                                 initargs=(os.getpid(),)) as pool:
            pending = {pool.submit(_timed, fn, args): index for index, args in tasks}
            try:
                while pending:
                    finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in finished:
                        index = pending.pop(fut)
                        value, worker, seconds = fut.result()
                        yield FrameResult(index, value, worker, seconds)
            finally:
                for fut in pending:
                    fut.cancel()

    def close(self) -> None:
        pass


# ============================================================================ worker processes
#: A worker process that stops on an operating-system error exits with this status after printing
#: OS_ERROR_TAG and the error as JSON on its last line of standard error (:func:`exit_on_os_error`);
#: :class:`ProcessWorkers` raises the same OSError in the parent.
OS_ERROR_EXIT = 5
OS_ERROR_TAG = "whitecap-oserror "


class WorkerFailed(WhitecapError):
    """A worker process of :class:`ProcessWorkers` failed; the message is its last line of standard error."""


def exit_on_os_error(exc: OSError) -> NoReturn:
    """In a worker process: end with OS_ERROR_EXIT and ``exc`` as JSON on the last line of standard error."""
    name = exc.filename if isinstance(exc.filename, str) else None
    fields = {"errno": exc.errno, "strerror": exc.strerror or str(exc), "filename": name}
    sys.stderr.write(f"{OS_ERROR_TAG}{json.dumps(fields)}\n")
    end_process(OS_ERROR_EXIT)


def worker_os_error(stderr: str) -> OSError | None:
    """The OSError a worker reported on its last tagged line of standard error, if any."""
    for line in reversed(stderr.strip().splitlines()):
        if line.startswith(OS_ERROR_TAG):
            try:
                e = json.loads(line[len(OS_ERROR_TAG):])
                return OSError(e["errno"], e["strerror"], *([e["filename"]] if e.get("filename") else []))
            except (ValueError, KeyError, TypeError):
                return None
    return None


class ProcessWorkers:
    """``jobs`` worker processes, each started from the command line ``command(k, share)`` with
    its interleaved share of the frames (worker k: frames k, k + jobs, ...), each printing
    ``<word> N`` on standard output when frame N is done. Every worker is started, even one
    with no frames (it may have other work: render's first worker saves the scene).

    The workers die with this process (:func:`whitecap.workers.die_with_parent` reads
    :func:`whitecap.workers.child_env`). Frames are reported as the lines come; errors once
    every worker has ended: the first OSError a worker reported (:func:`exit_on_os_error`),
    else :class:`WorkerFailed` with the first failed worker's last line of standard error."""

    cluster = False

    def __init__(self, jobs: int = 1, word: str = "done"):
        self.jobs = max(1, int(jobs))
        self.word = word

    def map(self, command: Callable[[int, list[int]], list[str]], tasks: list[tuple[int, tuple]]
            ) -> Iterator[FrameResult]:
        """Yield a :class:`FrameResult` per frame a worker reports; ``command`` replaces the
        per-frame function of the other executors (the workers run the frames)."""
        procs, logs = [], []
        try:
            for k in range(self.jobs):
                log = tempfile.TemporaryFile(mode="w+")
                logs.append(log)
                share = [index for index, _ in tasks[k::self.jobs]]
                procs.append(subprocess.Popen(command(k, share), stdout=subprocess.PIPE, stderr=log, text=True,
                                              env=child_env()))
            for k, p in enumerate(procs):
                assert p.stdout is not None  # stdout=PIPE
                for line in p.stdout:  # one line per finished frame, reported at once (resumable)
                    words = line.split()
                    if words[:1] == [self.word]:
                        yield FrameResult(int(words[1]), worker=f"worker {k}")
            self._raise_failures(procs, logs)
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                p.wait()
                if p.stdout is not None:
                    p.stdout.close()
            for log in logs:
                log.close()

    @staticmethod
    def _raise_failures(procs: list, logs: list) -> None:
        errors, os_errors = [], []
        for p, log in zip(procs, logs):
            p.wait()
            if p.returncode:
                log.seek(0)
                text = log.read()
                found = worker_os_error(text) if p.returncode == OS_ERROR_EXIT else None
                if found is not None:
                    os_errors.append(found)
                errors.append((text.strip().splitlines() or ["unknown error"])[-1])
        if os_errors:  # a full disk or a read-only folder: the OS error itself
            raise os_errors[0]
        if errors:
            raise WorkerFailed(errors[0])

    def close(self) -> None:
        pass


# ============================================================================ dask
def require_distributed():
    try:
        import distributed
    except ImportError:
        raise MissingDependency(
            f"--cluster needs Dask's 'distributed', which is not installed; {CLUSTER_HINT}"
        ) from None
    return distributed


class DaskExecutor:
    """One Dask task per frame on the cluster a :class:`distributed.Client` is connected to.

    ``shared`` is the directory the workers must see (the run directory);
    ``plugins`` are worker plugins registered before the first task (the
    render stage's Blender plugin keeps one scene per worker).
    """

    cluster = True

    def __init__(self, client, shared: Path, owns: tuple = (), frame_threads: int = 0):
        self.summaries: list[Summary] = []
        #: threads one frame may use on its worker (Cycles), 0 = all the worker's machine has
        self.frame_threads = frame_threads
        self.client = client
        self.shared = Path(shared).resolve()
        self._owns = owns  # the cluster objects this executor started (closed with it)
        self._write_probe()

    @property
    def address(self) -> str:
        return self.client.scheduler.address

    def workers(self) -> int:
        return len(self.client.scheduler_info(n_workers=-1)["workers"])

    def register(self, plugin, name: str) -> None:
        """A worker plugin on every worker, present and future (the render stage's Blender processes)."""
        self.client.register_plugin(plugin, name=name)

    def unregister(self, name: str) -> None:
        """Remove the plugin from every worker (its teardown ends what it started)."""
        try:
            self.client.unregister_worker_plugin(name)
        except Exception:  # a worker that is gone has nothing left to end
            pass

    def _write_probe(self) -> None:
        """A file only this client's run directory holds, which every task looks for before it runs."""
        self.shared.mkdir(parents=True, exist_ok=True)
        for old in self.shared.glob(f"{PROBE_PREFIX}*"):  # left by a client that was killed
            old.unlink(missing_ok=True)
        self.token = uuid.uuid4().hex
        self.probe = self.shared / f"{PROBE_PREFIX}{self.token}"
        self.probe.write_text(self.token)

    def check_shared(self) -> None:
        """Fail at once, in one line, when a connected worker cannot see the shared directory.

        Every worker reads the probe file; a directory of the same name on a
        worker's own disk does not hold it. Workers that join later are checked
        by each task (:class:`RunDirNotShared`, which stops the run).
        """
        seen = self.client.run(_probe, str(self.probe), self.token)
        blind = [addr for addr, ok in seen.items() if ok is not True]
        if blind:
            raise ClusterError(
                f"{self.shared}: {len(blind)} of {len(seen)} Dask workers cannot see the run directory "
                f"(first: {blind[0]}: {seen[blind[0]]}); "
                "it must be on a filesystem shared by the client and every worker"
            )

    def map(self, fn: Callable, tasks: list[tuple[int, tuple]], key: str = "frame") -> Iterator[FrameResult]:
        """Yield a :class:`FrameResult` per task as it finishes; failed frames carry ``error``.

        A worker that dies takes its task with it; the scheduler runs it again on
        another worker (up to ``distributed.scheduler.allowed-failures`` deaths).
        An exception raised by the frame function itself is not retried: the
        frame function is deterministic, so it would fail again.
        """
        from distributed import as_completed

        run = uuid.uuid4().hex[:8]
        futures: dict[Any, int] = {}  # distributed's futures, by their frame index
        for index, args in tasks:
            fut = self.client.submit(_shared_task, str(self.probe), self.token, fn, args,
                                     key=f"{key}-{index:05d}-{run}", pure=False)
            futures[fut] = index
        try:
            for fut in as_completed(list(futures), loop=self.client.loop):
                done = futures.pop(fut, None)
                if done is None:  # yielded once already
                    continue
                index = done
                # Not fut.status: a worker that dies holding a finished frame's result turns the future back
                # to pending (or lost) while the scheduler runs the frame again; result() waits for that.
                try:
                    value, worker, seconds = fut.result()
                except RunDirNotShared:
                    raise
                except (Exception, CancelledError) as exc:  # the frame's own error, or Dask's (KilledWorker...)
                    yield FrameResult(index, error=exc)
                else:
                    yield FrameResult(index, value, worker, seconds)
        finally:
            if futures:
                self.client.cancel(list(futures))

    def close(self) -> None:
        """Disconnect (and stop a cluster this executor started); print each stage's per-worker summary."""
        from .progress import console

        for summary in self.summaries:
            if summary.per_worker or summary.failed:
                for line in summary.lines():
                    console.print(line, highlight=False)
        self.summaries = []
        self.probe.unlink(missing_ok=True)
        try:
            self.client.close()
        finally:
            for obj in self._owns:
                obj.close()


def _probe(path: str, token: str) -> bool | str:
    """On a worker: does it read the probe file the client wrote into the shared directory?"""
    try:
        return True if Path(path).read_text() == token else "it reads another file at that path"
    except OSError as exc:
        return f"{exc.strerror or exc}"


# ============================================================================ Dask's own log lines
class DaskLogs:
    """While a cluster run is on, Dask's log lines in this process become whitecap's one-line messages.

    The scheduler of ``--cluster local``, slurm or pbs, its nannies and the
    client live in this process, and Dask gives its loggers a handler of their
    own that prints timestamped lines (``2026-01-02 10:11:12,345 -
    distributed.scheduler - ERROR - ...``, tracebacks included) to stderr, in
    the middle of the progress bar when a worker dies. While this is started,
    those handlers are set aside: errors come out as ``dask: <first line>``
    through the progress console (above the bar), each once and at most
    :attr:`LIMIT` of them; anything below an error, and the errors of
    :attr:`QUIET`, are dropped (a frame whose worker died runs again, and one
    that cannot is named by whitecap's own summary and error line).
    :meth:`close` puts Dask's handlers back.
    """

    ROOTS = ("distributed", "tornado", "bokeh")
    LIMIT = 5
    #: errors Dask recovers from by itself, or that whitecap reports in its own words (the frame's failure)
    QUIET = ("Couldn't gather keys", "workers died while trying to run it")

    def __init__(self) -> None:
        self._saved: list[tuple[logging.Logger, list[logging.Handler], bool]] = []
        self._seen: set[str] = set()
        self._lock = threading.Lock()
        self.handler = _ToConsole(self)

    def start(self) -> "DaskLogs":
        names = [n for n in list(logging.Logger.manager.loggerDict)
                 if n.split(".", 1)[0] in self.ROOTS]
        for name in sorted(set(names) | set(self.ROOTS)):
            log = logging.getLogger(name)
            if name in self.ROOTS or log.handlers:  # the loggers Dask gave a handler (they do not propagate)
                self._saved.append((log, log.handlers[:], log.propagate))
                log.handlers = [self.handler]
                log.propagate = False
        return self

    def emit(self, record: logging.LogRecord) -> None:
        from rich.markup import escape

        from .progress import console

        text = (record.getMessage().strip().splitlines() or [""])[0].strip()
        if any(q in text for q in self.QUIET):
            return
        with self._lock:
            if not text or text in self._seen or len(self._seen) > self.LIMIT:
                return
            self._seen.add(text)
            line = f"dask: {text}" if len(self._seen) <= self.LIMIT else "dask: (further messages not shown)"
        console.print(f"[dim]{escape(line)}[/dim]", highlight=False, soft_wrap=True)

    def close(self) -> None:
        for log, handlers, propagate in reversed(self._saved):
            log.handlers = handlers
            log.propagate = propagate
        self._saved = []


class _ToConsole(logging.Handler):
    def __init__(self, owner: DaskLogs):
        super().__init__(level=logging.ERROR)
        self.owner = owner

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.owner.emit(record)
        except Exception:  # never let a log line break the run
            pass


# ============================================================================ connecting
def connect(spec: str, shared: Path, cfg=None, jobs: int | None = None) -> DaskExecutor:
    """A :class:`DaskExecutor` for ``--cluster SPEC``: a scheduler address, or local, slurm or pbs.

    ``cfg`` is the scene's ``[cluster]`` section (:class:`whitecap.config.Cluster`);
    ``jobs`` sets the number of local workers or batch jobs when given.
    An address that does not answer within ``cfg.connect_timeout`` seconds is a
    one-line :class:`ClusterError`; so is a worker that cannot see ``shared``.
    """
    spec = str(spec).strip()
    address = scheduler_address(spec)  # a malformed one is refused before anything starts
    require_distributed()
    import distributed

    from .config import Cluster

    cfg = cfg or Cluster()
    if spec in ("slurm", "pbs") and shutil.which(SUBMIT_COMMAND[spec]) is None:
        # else the jobs would fail in the background and the bar wait for ever
        raise ClusterError(f"--cluster {spec}: '{SUBMIT_COMMAND[spec]}' is not on the PATH; run whitecap where "
                           f"{spec} jobs are submitted from (a login node)")
    logs = DaskLogs().start()
    owns: list = []

    def give_up() -> None:
        for obj in owns:
            obj.close()
        logs.close()

    try:
        if spec == "local":
            n = jobs or cfg.jobs or len(os.sched_getaffinity(0))
            # One thread per worker: a frame is one task at a time. No dashboard (it needs bokeh, and
            # its HTTP server on a fixed port warned when another cluster held it), no worker log lines.
            try:
                cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                   dashboard_address=None, silence_logs=logging.CRITICAL,
                                                   scheduler_kwargs=NO_DASHBOARD)
            except Exception as exc:  # most often: workers are spawned, and the calling script re-ran itself
                raise ClusterError(f"--cluster local: the local Dask cluster did not start ({_one_line(exc)}); "
                                   "from a Python script, call whitecap under `if __name__ == '__main__':`, "
                                   "since each worker process imports the script again") from None
            owns.append(cluster)
            address = cluster.scheduler_address
        elif spec in ("slurm", "pbs"):
            cluster = batch_cluster(spec, cfg)
            owns.append(cluster)
            cluster.scale(jobs=jobs or cfg.jobs)
            address = cluster.scheduler_address
        else:
            assert address is not None  # scheduler_address gives one for any spec but local, slurm, pbs
            check_scheduler(spec, address, cfg.connect_timeout)
    except BaseException:
        give_up()
        raise
    try:
        client = distributed.Client(address, timeout=f"{cfg.connect_timeout}s", set_as_default=False)
    except Exception as exc:  # the probe passed, so this is rare: a scheduler that went away meanwhile
        give_up()
        raise ClusterError(f"--cluster {spec}: no Dask scheduler answered at {address} within "
                           f"{cfg.connect_timeout:g} s ({type(exc).__name__}); start one with `dask scheduler` "
                           "or check the address") from None
    except BaseException:
        give_up()
        raise
    owns.append(logs)  # closed last, after the cluster, so its closing lines stay quiet too
    threads = 0
    if spec == "local":
        threads = max(1, len(os.sched_getaffinity(0)) // n)
    elif spec in ("slurm", "pbs"):
        threads = max(1, cfg.cores // cfg.processes)
    try:
        ex = DaskExecutor(client, shared, owns=tuple(owns), frame_threads=threads)
    except BaseException:
        client.close()
        give_up()
        raise
    try:
        if spec == "local":
            client.wait_for_workers(1)
        if ex.workers():
            ex.check_shared()
    except BaseException:
        ex.close()
        raise
    return ex


def scheduler_address(spec: str) -> str | None:
    """The scheduler address ``--cluster SPEC`` names (None for local, slurm, pbs), or a one-line InputError.

    Checked before any connection is tried: a known protocol (tcp:// when none
    is given), a host and a port number; a bare word is taken for a misspelt
    local, slurm or pbs.
    """
    if spec in CLUSTER_KINDS:
        return None
    if not spec:
        raise InputError(f"--cluster: empty; {ADDRESS_HINT}")
    scheme, sep, rest = spec.partition("://")
    if not sep:
        scheme, rest = "tcp", spec
        if not any(c in spec for c in ":./") and spec.lower() != "localhost":  # a word: a misspelt kind
            near = difflib.get_close_matches(spec.lower(), CLUSTER_KINDS, n=1, cutoff=0.6)
            guess = f" (did you mean '{near[0]}'?)" if near else ""
            raise InputError(f"--cluster {spec}: not a cluster kind or a scheduler address{guess}; {ADDRESS_HINT}")
    if scheme.lower() not in SCHEMES:
        raise InputError(f"--cluster {spec}: unknown protocol '{scheme}' (Dask speaks {', '.join(SCHEMES[:-1])}); "
                         f"{ADDRESS_HINT}")
    scheme = scheme.lower()
    if scheme == "inproc":  # a scheduler in this very process (tests, notebooks)
        if not rest:
            raise InputError(f"--cluster {spec}: no address after inproc://; {ADDRESS_HINT}")
        return f"{scheme}://{rest}"
    host, port = _host_port(rest)
    if not host or any(c.isspace() for c in host) or "/" in rest:
        raise InputError(f"--cluster {spec}: not a scheduler address; {ADDRESS_HINT}")
    if port is None:
        raise InputError(f"--cluster {spec}: no port; give {scheme}://{rest.rstrip(':')}:PORT "
                         "(a scheduler listens on 8786 unless told otherwise), or local, slurm, pbs")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"--cluster {spec}: port '{port}' is not a number from 1 to 65535; {ADDRESS_HINT}")
    return f"{scheme}://{rest}"


def _host_port(rest: str) -> tuple[str, str | None]:
    """('host', 'port' or None) of HOST:PORT, [IPv6]:PORT, HOST or [IPv6]."""
    if rest.startswith("["):
        host, _, tail = rest[1:].partition("]")
        return host, (tail[1:] if tail.startswith(":") else None if not tail else tail)
    host, sep, port = rest.rpartition(":")
    return (host, port) if sep else (rest, None)


def check_scheduler(spec: str, address: str, timeout: float) -> None:
    """Fail in one line unless a Dask scheduler completes its handshake at ``address`` within ``timeout`` s.

    ``distributed.Client`` bounds only the TCP connection by its timeout: a
    listener that accepts and never answers holds it for ever, and a service
    that answers something else makes it read a message as long as the first
    eight bytes say (exabytes). Here the whole exchange has one deadline: for
    tcp:// a plain socket first reads the scheduler's greeting and checks its
    length, then Dask's own handshake runs under ``asyncio.wait_for``.
    """
    if address.startswith("inproc://"):
        return
    deadline = time.monotonic() + timeout
    where = address.split("://", 1)[1]
    not_dask = (f"--cluster {spec}: the service at {where} answered, but not as a Dask scheduler does; "
                "check the address and port (a scheduler listens on 8786 unless told otherwise)")
    silent = (f"--cluster {spec}: something at {where} accepted the connection but did not answer as a Dask "
              f"scheduler within {timeout:g} s; check the address and port, or raise [cluster] connect_timeout")
    if address.startswith("tcp://"):
        greeting = _tcp_greeting(spec, address, deadline, timeout)
        if greeting is None:
            raise ClusterError(silent)
        if not 0 < greeting <= MAX_HANDSHAKE:
            raise ClusterError(not_dask)
    outcome: list = []

    async def handshake() -> None:
        from distributed.comm import connect as dask_connect
        from distributed.security import Security

        # the client's TLS settings, as distributed.Client passes them (Dask's config)
        args = Security().get_connection_args("client")
        comm = await dask_connect(address, timeout=max(0.1, deadline - time.monotonic()), **args)
        try:
            await comm.write({"op": "identity", "reply": True})
            reply = await comm.read()
        finally:
            comm.abort()
        outcome.append(str(reply.get("type")) if isinstance(reply, dict) else "")

    def run() -> None:
        try:
            asyncio.run(asyncio.wait_for(handshake(), max(0.1, deadline - time.monotonic())))
        except BaseException as exc:  # noqa: BLE001 -- every failure becomes one line below
            outcome.append(exc)

    # In a thread of its own, so that a caller inside an event loop (a notebook) can connect too.
    t = threading.Thread(target=run, name="whitecap-scheduler-probe", daemon=True)
    t.start()
    t.join(max(0.1, deadline - time.monotonic()) + 5.0)
    result = outcome[0] if outcome else TimeoutError()
    if result == "Scheduler":
        return
    if result in ("Worker", "Nanny"):
        raise ClusterError(f"--cluster {spec}: {where} is a Dask worker, not the scheduler; give the scheduler's "
                           "address (tcp://HOST:PORT, 8786 unless told otherwise)")
    if isinstance(result, (TimeoutError, asyncio.TimeoutError)):
        raise ClusterError(silent)
    if isinstance(result, OSError) and not isinstance(result, TimeoutError):
        raise ClusterError(f"--cluster {spec}: no Dask scheduler answered at {address} within {timeout:g} s "
                           f"({type(result).__name__}); start one with `dask scheduler` or check the address")
    raise ClusterError(not_dask)


def _tcp_greeting(spec: str, address: str, deadline: float, timeout: float) -> int | None:
    """The length a tcp:// peer announces for its first message, None if it sends nothing before ``deadline``.

    A refused connection is tried again until the deadline (a scheduler may be
    starting); an unknown host fails at once.
    """
    host, port = _host_port(address.split("://", 1)[1])
    assert port is not None  # scheduler_address refused an address without one
    last: OSError | None = None
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise ClusterError(f"--cluster {spec}: no Dask scheduler answered at {address} within {timeout:g} s "
                               f"({type(last or TimeoutError()).__name__}); start one with `dask scheduler` or "
                               "check the address")
        try:
            sock = socket.create_connection((host, int(port)), timeout=left)
            break
        except socket.gaierror:
            raise ClusterError(f"--cluster {spec}: host '{host}' not found; check the address "
                               "(tcp://HOST:PORT), or give local, slurm or pbs") from None
        except (socket.timeout, TimeoutError) as exc:
            last = exc
        except OSError as exc:  # refused, unreachable: try again until the deadline
            last = exc
            time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))
    with sock:
        head = b""
        try:
            while len(head) < 8:
                sock.settimeout(max(0.01, deadline - time.monotonic()))
                chunk = sock.recv(8 - len(head))
                if not chunk:  # closed without a word
                    return 0
                head += chunk
        except (socket.timeout, TimeoutError):
            return None
        except OSError:
            return 0
    return struct.unpack("<Q", head)[0]


def batch_cluster(kind: str, cfg):
    """A dask-jobqueue ``SLURMCluster`` or ``PBSCluster`` from the ``[cluster]`` section (no job started yet)."""
    try:
        import dask_jobqueue
    except ImportError:
        raise MissingDependency(
            f"--cluster {kind} needs 'dask-jobqueue', which is not installed; {CLUSTER_HINT}"
        ) from None
    cls = dask_jobqueue.SLURMCluster if kind == "slurm" else dask_jobqueue.PBSCluster
    return cls(**batch_options(cfg))


def batch_options(cfg) -> dict[str, Any]:
    """dask-jobqueue's keyword arguments for one batch job described by the ``[cluster]`` section."""
    kw: dict[str, Any] = dict(
        cores=cfg.cores, processes=cfg.processes, memory=cfg.memory, walltime=cfg.walltime,
        job_name="whitecap", scheduler_options=dict(NO_DASHBOARD),
        # One frame at a time per worker: the frame itself uses the job's cores
        # (splashsurf's threads, Cycles' threads), as a local run does.
        worker_extra_args=["--nthreads", "1"],
    )
    if cfg.queue:
        kw["queue"] = cfg.queue
    if cfg.account:
        kw["account"] = cfg.account
    if cfg.interface:
        kw["interface"] = cfg.interface
    if cfg.job_extra:
        kw["job_extra_directives"] = list(cfg.job_extra)
    if cfg.setup:
        kw["job_script_prologue"] = list(cfg.setup)
    if cfg.local_directory:
        kw["local_directory"] = cfg.local_directory
    return kw


def cluster_settings(run_dir: str | Path | None = None, scene_file: str | Path | None = None):
    """The ``[cluster]`` section: of ``scene_file`` when given, else of the run's scene.toml, else defaults."""
    from .config import Cluster, load_scene

    for f in (scene_file, Path(run_dir) / "scene.toml" if run_dir is not None else None):
        if f is not None and Path(f).is_file():
            return load_scene(f).cluster
    return Cluster()


def executor(cluster: str | None, shared: Path, jobs: int = 1, cfg=None) -> LocalExecutor | DaskExecutor:
    """The executor for a stage: the local pool without ``cluster``, else :func:`connect`."""
    if not cluster:
        return LocalExecutor(jobs)
    return connect(cluster, shared, cfg=cfg, jobs=jobs if jobs and jobs > 1 else None)


# ============================================================================ the frame loop
@dataclass
class Summary:
    """Frames and time per worker of one stage (printed at the end of a cluster run)."""

    stage: str
    per_worker: dict[str, list[float]] = field(default_factory=dict)
    failed: dict[int, str] = field(default_factory=dict)
    wall: float = 0.0

    def add(self, r: FrameResult) -> None:
        self.per_worker.setdefault(r.worker, []).append(r.seconds)

    def lines(self) -> list[str]:
        n = sum(len(v) for v in self.per_worker.values())
        out = [f"{self.stage}: {n} frames on {len(self.per_worker)} workers in {self.wall:.1f} s"
               + (f" ({n / self.wall:.2f} frames/s)" if self.wall > 0 and n else "")]
        for w, ts in sorted(self.per_worker.items()):
            out.append(f"  {w}: {len(ts)} frame{'s' if len(ts) > 1 else ''}, {sum(ts) / len(ts):.2f} s per frame")
        for i, msg in sorted(self.failed.items()):
            out.append(f"  frame {i} failed: {msg}")
        return out


def _failed_info(summary: Summary) -> str:
    return f"[red]failed: frame {', '.join(map(str, sorted(summary.failed)))}[/red]"


def _one_line(exc: BaseException) -> str:
    """'Type: last line of the message' (a message that cannot be made into text is left out)."""
    try:
        text = str(exc).strip().splitlines()
    except Exception:
        text = []
    return f"{type(exc).__name__}: {text[-1] if text else ''}".rstrip(": ")


def map_frames(ex, stage: str, fn: Callable, tasks: list[tuple[int, tuple]], bar, bar_task,
               on_done: Callable[[FrameResult], str | None], report: bool = True) -> Summary:
    """Run ``fn`` over ``tasks`` on ``ex``, advancing the progress bar and calling ``on_done`` per frame.

    ``on_done`` (in this process) records the frame and returns the bar's info
    text. Frames that fail on a cluster are named on the bar and at the end, and
    a :class:`FrameFailed` is raised once every other frame is done; locally the
    first error is raised at once, as before. A cluster executor prints the
    per-worker summary when it is closed (after the progress bar) unless ``report`` is False.
    """
    summary = Summary(stage)
    if ex.cluster and report:
        ex.summaries.append(summary)
    t0 = time.perf_counter()
    try:
        for r in ex.map(fn, tasks):
            if r.error is not None:
                summary.failed[r.index] = _one_line(r.error)
                bar.update(bar_task, info=_failed_info(summary))
                continue
            summary.add(r)
            info = on_done(r)
            if summary.failed:  # the failed frames stay named on the bar
                info = f"{info or ''}  {_failed_info(summary)}".strip()
            bar.update(bar_task, advance=1, **({"info": info} if info is not None else {}))
    finally:
        summary.wall = time.perf_counter() - t0
    if summary.failed:
        i, msg = min(summary.failed.items())
        raise FrameFailed(f"{stage}: {len(summary.failed)} of {len(tasks)} frames failed on the cluster "
                          f"(frame {i}: {msg}); rerun to retry them, finished frames are kept")
    return summary
