"""A background writer: one thread that writes files in the order they are handed to it.

``simulate`` hands each frame's files, its ``run.json`` and its checkpoints to a
:class:`FrameWriter` and goes on stepping while they are written::

    with FrameWriter() as w:
        w.submit(functools.partial(write, path, frame), "output")
        w.flush()          # every file handed over is on disk (or its error is raised here)

- **In order.** One thread, one FIFO queue: a ``run.json`` handed over after a
  frame's files is written after them, so it never lists a file that is not
  complete; a checkpoint handed over after frame k's ``run.json`` is written
  once every frame up to k is on disk and recorded.
- **A frame's files side by side.** A job handed over with a ``lane`` (a frame's
  fluid file, its diffuse file) runs on that lane's own thread, beside the jobs
  after it, until the next job without a lane (its ``run.json``), which waits for
  every lane. A file system takes one write to a file at a time (ext4 holds
  the file's inode lock through each): on 2 cores, 64 MB written to one file
  took 13 ms from one thread and 14-16 from two, but 9-12 ms as two files of
  32 MB from two threads (tmpfs: 26, 28-37, 19-22 ms); a 1 M-particle
  `whitecap foam` frame's fluid and diffuse files (91 MB, new files on tmpfs)
  61 ms one after the other, 49 ms side by side (``benchmarks/bench_writer.py``).
  A lane holds one job at a time; the next waits for it (memory stays bounded).
- **Bounded.** The queue holds at most ``maxsize`` jobs; :meth:`submit` blocks
  while it is full, so a slow disk slows the caller down instead of letting
  copies of frames pile up in memory. The time spent blocked is the phase
  timer ``output.wait``, counted inside the caller's own phase (``output`` or
  ``checkpoint``), not beside it.
- **Errors are not lost.** The first exception of a job (a full disk: an OSError
  naming the file) is raised in the caller's thread by the next :meth:`submit`
  or :meth:`flush`. Jobs after a failed one are skipped: a later ``run.json``
  must not list a file that was not written.
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
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

from .. import timing

#: Jobs waiting at most (besides the one being written): each may hold a copy of a frame or of the state.
DEFAULT_QUEUE = 2
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
    def __init__(self, maxsize: int = DEFAULT_QUEUE, name: str = "whitecap-writer") -> None:
        if maxsize < 1:
            raise ValueError("maxsize must be at least 1")
        self._queue: queue.Queue = queue.Queue(maxsize)
        self._error: BaseException | None = None
        self._raised = False
        self._closed = False
        self._name = name
        self._lanes: dict[str, tuple[ThreadPoolExecutor, Future | None]] = {}  # lane -> (its thread, its job)
        self._lock = threading.Lock()  # the first error and the timers, set from the lanes' threads too
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        _short_switch(True)

    # ------------------------------------------------------------------ caller's side
    def submit(self, job: Callable[[], object], label: str = "output", lane: str | None = None) -> None:
        """Hand ``job`` to the writer thread; blocks while the queue is full. Raises the error of an
        earlier job, if one failed. With ``lane``, the job runs on that lane's thread beside the jobs after
        it, up to the next job handed over without one (which waits for it): give a frame's files, each of
        its own kind, lanes, and what lists them (run.json) none."""
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
        """Write what is still queued (unless a job failed), then stop the thread. Raises nothing:
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

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        try:
            while True:
                item = self._queue.get()
                if item is None:
                    self._join_lanes()
                    self._queue.task_done()
                    return
                job, label, lane = item
                item = None
                if lane is None:
                    self._join_lanes()  # what lists a frame's files comes after every one of them
                    try:
                        if self._error is None:  # else skipped: what follows a failed write must not be recorded
                            self._timed(job, label)
                    finally:
                        job = None  # the arrays it held go now, not when the next job arrives
                        self._queue.task_done()
                    continue
                pool, last = self._lanes.get(lane) or (None, None)
                if last is not None:
                    last.exception()  # one job a lane at a time
                if self._error is not None:
                    job = None
                    self._queue.task_done()
                    continue
                try:
                    if pool is None:
                        pool = ThreadPoolExecutor(1, thread_name_prefix=f"{self._name}-{lane}")
                    fut = pool.submit(self._lane_job, [job], label)  # in a list the lane empties: see _lane_job
                except BaseException as exc:  # noqa: BLE001 - no thread to be had: the job fails as a write would
                    self._fail(exc)
                    self._queue.task_done()
                    continue
                finally:
                    job = None
                fut.add_done_callback(lambda _f: self._queue.task_done())
                self._lanes[lane] = (pool, fut)
        finally:
            for pool, _ in self._lanes.values():
                pool.shutdown(wait=True)

    def _lane_job(self, box: list, label: str) -> None:
        """The job in ``box``, taken out first: the pool's work item keeps its arguments until after the future is
        done, when flush() may already have returned and the caller reuse the arrays' blocks (io.array_pool)."""
        job = box.pop()
        self._timed(job, label)

    def _join_lanes(self) -> None:
        """Wait until every lane's job is done (its error, if any, recorded by :meth:`_timed`)."""
        for lane, (pool, last) in list(self._lanes.items()):
            if last is not None:
                last.exception()
                self._lanes[lane] = (pool, None)

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
