"""Where per-frame work runs: a local process pool, or a Dask cluster.

The per-frame stages (``mesh``, ``render``, ``export``) are pure functions of
their frame: each reads its inputs from the run directory and writes its
output file there atomically (:mod:`whitecap.io.atomic`). They hand their
frames to an executor through one interface, :func:`map_frames`:

- :class:`LocalExecutor` (the default) runs them in this process (one job) or
  in a pool of spawned worker processes that die with their parent. No Dask
  is needed.
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

import os
import shutil
import time
import uuid
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable, Iterator

from .errors import MissingDependency, WhitecapError
from .workers import die_with_parent

CLUSTER_HINT = "install it with: pip install 'whitecap[cluster]' (dask, distributed, dask-jobqueue)"
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


# ============================================================================ dask
def require_distributed():
    try:
        import distributed
    except ImportError:
        raise MissingDependency(f"--cluster needs Dask's 'distributed', which is not installed; {CLUSTER_HINT}") from None
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
                f"(first: {blind[0]}: {seen[blind[0]]}); it must be on a filesystem shared by the client and every worker"
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
        futures = {}
        for index, args in tasks:
            fut = self.client.submit(_shared_task, str(self.probe), self.token, fn, args, key=f"{key}-{index:05d}-{run}",
                                     pure=False)
            futures[fut] = index
        try:
            for fut in as_completed(list(futures), loop=self.client.loop):
                index = futures.pop(fut)
                if fut.status == "finished":
                    value, worker, seconds = fut.result()
                    yield FrameResult(index, value, worker, seconds)
                else:
                    exc = fut.exception()
                    if isinstance(exc, RunDirNotShared):
                        raise exc
                    yield FrameResult(index, error=exc)
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


# ============================================================================ connecting
def connect(spec: str, shared: Path, cfg=None, jobs: int | None = None) -> DaskExecutor:
    """A :class:`DaskExecutor` for ``--cluster SPEC``: a scheduler address, or local, slurm or pbs.

    ``cfg`` is the scene's ``[cluster]`` section (:class:`whitecap.config.Cluster`);
    ``jobs`` sets the number of local workers or batch jobs when given.
    An address that does not answer within ``cfg.connect_timeout`` seconds is a
    one-line :class:`ClusterError`; so is a worker that cannot see ``shared``.
    """
    require_distributed()
    import distributed

    from .config import Cluster

    cfg = cfg or Cluster()
    spec = str(spec).strip()
    owns: list = []
    if spec == "local":
        n = jobs or cfg.jobs or len(os.sched_getaffinity(0))
        # One thread per worker: the frame functions use their own threads (splashsurf, Cycles).
        cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=40)
        owns.append(cluster)
        address = cluster.scheduler_address
    elif spec in ("slurm", "pbs"):
        submit = SUBMIT_COMMAND[spec]
        if shutil.which(submit) is None:  # else the jobs would fail in the background and the bar wait for ever
            raise ClusterError(f"--cluster {spec}: '{submit}' is not on the PATH; run whitecap where {spec} jobs are "
                               "submitted from (a login node)")
        cluster = batch_cluster(spec, cfg)
        owns.append(cluster)
        cluster.scale(jobs=jobs or cfg.jobs)
        address = cluster.scheduler_address
    else:
        address = spec if "://" in spec else f"tcp://{spec}"
    try:
        client = distributed.Client(address, timeout=f"{cfg.connect_timeout}s", set_as_default=False)
    except (OSError, TimeoutError) as exc:
        for obj in owns:
            obj.close()
        raise ClusterError(f"--cluster {spec}: no Dask scheduler answered at {address} within "
                           f"{cfg.connect_timeout:g} s ({type(exc).__name__}); start one with `dask scheduler` "
                           "or check the address") from None
    threads = 0
    if spec == "local":
        threads = max(1, len(os.sched_getaffinity(0)) // n)
    elif spec in ("slurm", "pbs"):
        threads = max(1, cfg.cores // cfg.processes)
    try:
        ex = DaskExecutor(client, shared, owns=tuple(owns), frame_threads=threads)
    except BaseException:
        client.close()
        for obj in owns:
            obj.close()
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


def batch_cluster(kind: str, cfg):
    """A dask-jobqueue ``SLURMCluster`` or ``PBSCluster`` from the ``[cluster]`` section (no job started yet)."""
    try:
        import dask_jobqueue
    except ImportError:
        raise MissingDependency(f"--cluster {kind} needs 'dask-jobqueue', which is not installed; {CLUSTER_HINT}") from None
    cls = dask_jobqueue.SLURMCluster if kind == "slurm" else dask_jobqueue.PBSCluster
    return cls(**batch_options(cfg))


def batch_options(cfg) -> dict[str, Any]:
    """dask-jobqueue's keyword arguments for one batch job described by the ``[cluster]`` section."""
    kw: dict[str, Any] = dict(
        cores=cfg.cores, processes=cfg.processes, memory=cfg.memory, walltime=cfg.walltime,
        job_name="whitecap", scheduler_options={"dashboard_address": ":0"},
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
    text = str(exc).strip().splitlines()
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
