"""A background writer: threads that write files while the caller goes on, in the order that matters.

``simulate`` hands each frame's files, its ``run.json`` and its checkpoints to a
:class:`FrameWriter` and goes on stepping while they are written::

    with FrameWriter() as w:
        w.submit(functools.partial(write, path, frame), "fluid", lane="fluid")
        w.submit(functools.partial(write_text, run_json, text), "run.json")
        w.flush()          # every file handed over is on disk (or its error is raised here)

- **In order, where it matters.** A job handed over without a ``lane`` (a ``run.json``,
  a checkpoint) runs once every job handed over before it is done, on one thread,
  one after another: a ``run.json`` handed over after a frame's files never lists
  a file that is not complete, and a checkpoint handed over after frame k's
  ``run.json`` is written once every frame up to k is on disk and recorded.
- **Files side by side.** A job handed over with a ``lane`` (a frame's fluid file,
  its diffuse file) runs on one of that lane's threads at once, beside the other
  lanes' jobs, and beside the jobs without a lane handed over before it: frame k+1's
  files are written while frame k's run.json waits for frame k's. A lane runs up to
  ``depth`` (:data:`LANE_DEPTH`) jobs at once, frame k's file and frame k+1's, so each
  lane's jobs must write files of their own (counts.csv, rewritten every frame, is
  written without a lane). A file system takes one write to a file at a time (ext4
  holds the file's inode lock through each) but writes to different files side by
  side: on 2 cores, 64 MB written to one file took 13 ms from one thread and 14-16
  from two, but 9-12 ms as two files of 32 MB from two threads (tmpfs: 26, 28-37,
  19-22 ms); two files of 100 MB on tmpfs 78-85 ms one after the other and 46-54 ms
  from two threads. A 1 M-particle `whitecap foam` frame's fluid and diffuse files (91 MB,
  new files on tmpfs) took 61 ms one after the other, 49 ms side by side
  (``benchmarks/bench_writer.py``). A frame's diffuse file on an H200's RAM disk took
  34 ms, more than a frame at 30 frames/s: one lane thread could not keep up there.
- **Bounded.** The queue holds at most ``maxsize`` jobs; :meth:`submit` blocks
  while it is full, so a slow disk slows the caller down instead of letting
  copies of frames pile up in memory: a lane with ``depth`` jobs running holds the
  next one back, and the queue fills behind it. The time spent blocked is the phase
  timer ``output.wait``, counted inside the caller's own phase (``output`` or
  ``checkpoint``), not beside it.
- **Errors are not lost.** The first exception of a job (a full disk: an OSError
  naming the file) is raised in the caller's thread by the next :meth:`submit`
  or :meth:`flush`. Jobs that have not started by then are skipped: a later
  ``run.json`` must not list a file that was not written. (A later frame's file
  already being written beside the failed one is finished, and listed nowhere.)
- Jobs must own what they write: hand over arrays the caller will not change.
  The writer's threads never call Taichi (no ``ti.sync``); their time is
  recorded as ``writer.<label>`` in :data:`whitecap.timing.TIMERS` (a dotted
  name: it overlaps the caller's phases, so it is not counted in the total).
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Sequence

from .. import timing

#: Jobs waiting in the queue at most (besides those handed out to the lanes and the ordered thread, and the one the
#: writer's thread holds while a lane is full): each may hold a copy of a frame or of the state.
DEFAULT_QUEUE = 2
#: Jobs a lane runs at once, each on a thread of its own (see the module's docstring).
LANE_DEPTH = 2
#: Jobs without a lane handed out at most, waiting for the jobs before them or running (a frame's counts.csv,
#: run.json and the foam pass's resume record: a frame's, so that the lanes can go on with the next frame's files).
ORDERED_AHEAD = 4
WAIT_TIMER = "output.wait"
#: The interpreter's switch interval while a writer runs [s] (Python's default is 5 ms). The writer's thread
#: takes the GIL back after each call that let it go (a numpy copy, a write to the file), some 20 times a
#: file, and waited up to the whole interval each time while the loop's thread ran Python (launching
#: kernels): a 1 M-particle PLY took 110 ms against 37 ms at 0.2 ms (2 cores, the loop as fast either way).
SWITCH_INTERVAL = 2e-4
_switch_lock = threading.Lock()
_switch_users = 0
_switch_saved = 0.005


def _short_switch(on: bool) -> None:
    """SWITCH_INTERVAL while any writer runs; the interval there was before, after the last one."""
    global _switch_users, _switch_saved
    with _switch_lock:
        if on:
            if _switch_users == 0:
                _switch_saved = sys.getswitchinterval()
                sys.setswitchinterval(min(_switch_saved, SWITCH_INTERVAL))
            _switch_users += 1
        else:
            _switch_users -= 1
            if _switch_users == 0:
                sys.setswitchinterval(_switch_saved)


class FrameWriter:
    def __init__(self, maxsize: int = DEFAULT_QUEUE, name: str = "whitecap-writer", depth: int = LANE_DEPTH) -> None:
        if maxsize < 1:
            raise ValueError("maxsize must be at least 1")
        if depth < 1:
            raise ValueError("depth must be at least 1")
        self._queue: queue.Queue = queue.Queue(maxsize)
        self._error: BaseException | None = None
        self._raised = False
        self._closed = False
        self._name = name
        self._depth = depth
        self._lanes: dict[str, tuple[ThreadPoolExecutor, deque[Future]]] = {}  # lane -> (its threads, its jobs)
        self._ordered: ThreadPoolExecutor | None = None  # the jobs without a lane, one after the other
        self._ordered_jobs: deque[Future] = deque()  # those handed out, not yet seen done
        self._lock = threading.Lock()  # the first error and the timers, set from the lanes' threads too
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        _short_switch(True)

    # ------------------------------------------------------------------ caller's side
    def submit(self, job: Callable[[], object], label: str = "output", lane: str | None = None) -> None:
        """Hand ``job`` to the writer; blocks while the queue is full. Raises the error of an earlier job, if one
        failed. With ``lane``, the job runs on one of that lane's threads, beside the jobs handed over before and
        after it (give each file of a frame a lane of its kind; jobs on a lane must write files of their own).
        Without one, it runs once every job handed over before it is done, and before the next job without one
        (what lists a frame's files: run.json, a checkpoint)."""
        if self._closed:
            raise RuntimeError("FrameWriter: submit after close")
        self._raise()
        try:
            self._queue.put_nowait((job, label, lane))
        except queue.Full:
            with timing.timer(WAIT_TIMER):
                self._queue.put((job, label, lane))
        self._raise()

    def flush(self) -> None:
        """Wait until every job handed over is done; raise the first error of one."""
        self._raise()
        if self._queue.unfinished_tasks:
            with timing.timer(WAIT_TIMER):
                self._queue.join()
        self._raise()

    def close(self) -> None:
        """Write what is still queued (unless a job failed), then stop the threads. Raises nothing:
        call :meth:`flush` first to hear of errors. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._thread.join()
        _short_switch(False)

    @property
    def error(self) -> BaseException | None:
        return self._error

    def __enter__(self) -> "FrameWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                self.flush()
        finally:
            self.close()

    def _raise(self) -> None:
        if self._error is not None and not self._raised:
            self._raised = True  # raised once: the caller unwinds, and close() must not raise it again
            raise self._error
        if self._error is not None:
            raise RuntimeError(f"the background writer failed earlier: {self._error}")

    # ------------------------------------------------------------------ writer thread: hands the jobs out
    def _run(self) -> None:
        try:
            while True:
                item = self._queue.get()
                if item is None:
                    for fut in self._in_flight():
                        fut.exception()
                    self._queue.task_done()
                    return
                job, label, lane = item
                item = None
                box = [job]  # in a list the job's thread empties: see _job
                job = None
                try:
                    if lane is None:
                        fut = self._submit_ordered(box, label)
                    else:
                        fut = self._submit_to_lane(box, label, lane)
                except BaseException as exc:  # noqa: BLE001 - no thread to be had: the job fails as a write would
                    box.clear()
                    self._fail(exc)
                    self._queue.task_done()
                    continue
                fut.add_done_callback(lambda _f: self._queue.task_done())
        finally:
            for pool, _ in self._lanes.values():
                pool.shutdown(wait=True)
            if self._ordered is not None:
                self._ordered.shutdown(wait=True)

    def _in_flight(self) -> list[Future]:
        """Every job handed out and not yet known to be done: the lanes' and the last job without one."""
        futs = [f for _, jobs in self._lanes.values() for f in jobs]
        return futs + list(self._ordered_jobs)[-1:]  # (the ordered thread runs them one after the other)

    def _submit_to_lane(self, box: list, label: str, lane: str) -> Future:
        """The job on one of ``lane``'s threads, once the lane has fewer than ``depth`` jobs running."""
        pool, jobs = self._lanes.get(lane) or (None, deque())
        _make_room(jobs, self._depth)
        if pool is None:
            pool = ThreadPoolExecutor(self._depth, thread_name_prefix=f"{self._name}-{lane}")
            self._lanes[lane] = (pool, jobs)
        fut = pool.submit(self._job, box, label, ())
        jobs.append(fut)
        return fut

    def _submit_ordered(self, box: list, label: str) -> Future:
        """The job on the ordered thread, after every job handed out before it, once fewer than ORDERED_AHEAD
        such jobs are handed out (they hold what they write, a checkpoint's state say: the bound on memory)."""
        _make_room(self._ordered_jobs, ORDERED_AHEAD)
        before = self._in_flight()
        if self._ordered is None:
            self._ordered = ThreadPoolExecutor(1, thread_name_prefix=f"{self._name}-ordered")
        fut = self._ordered.submit(self._job, box, label, before)
        self._ordered_jobs.append(fut)
        return fut

    def _job(self, box: list, label: str, after: Sequence[Future]) -> None:
        """The job in ``box``, taken out first (a pool's work item keeps its arguments until after the future is
        done, when flush() may already have returned and the caller reuse the arrays' blocks: io.array_pool),
        once the jobs ``after`` are done; skipped when a job has failed (a file after a failed one, or what would
        list it, is not written)."""
        job = box.pop()
        for fut in after:
            fut.exception()
        if self._error is None:  # else skipped
            self._timed(job, label)

    def _fail(self, exc: BaseException) -> None:
        """Record ``exc`` for the caller, unless another job's error came first."""
        with self._lock:
            if self._error is None:
                self._error = exc

    def _timed(self, job: Callable[[], object], label: str) -> None:
        """Run ``job``; its time to ``writer.<label>``, its exception (the first of any thread) to the caller's."""
        t0 = time.perf_counter()
        try:
            job()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            self._fail(exc)
        finally:
            if timing.ENABLED:
                with self._lock:
                    rec = timing.TIMERS[timing.BACKGROUND_PREFIX + label]
                    rec[0] += time.perf_counter() - t0
                    rec[1] += 1


def _make_room(jobs: deque[Future], most: int) -> None:
    """Drop the jobs at the front that are done, and wait for the oldest while ``most`` or more are not: after it,
    fewer than ``most`` jobs of ``jobs`` are handed out (a lane's threads, the ordered thread's backlog)."""
    while jobs and (jobs[0].done() or len(jobs) >= most):
        jobs.popleft().exception()
