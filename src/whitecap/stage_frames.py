"""The per-frame stage skeleton shared by mesh, render and export.

Each of these stages does the same four things around its own per-frame function:

1. plan: the frames to make and their outputs (``--jobs`` checked by :func:`check_jobs`);
2. skip what this simulation already made (:func:`todo`: a frame is redone when ``force``,
   or when the stage's own ``done`` test says its output is missing or stale);
3. map the per-frame function over the rest (:func:`map_over_frames`: an executor of
   :mod:`whitecap.executor`, a progress bar, temporary files swept afterwards);
4. record each finished frame at once, in this process, under the stage's lock (the
   ``on_done`` callback), so that an interrupted stage resumes after its last frame.

Floor: with ``io`` and ``executor`` (below every stage).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable, TypeVar

from .errors import InputError
from .executor import FrameResult, executor, map_frames
from .io.atomic import sweep_temps
from .progress import progress

T = TypeVar("T")


def check_jobs(stage: str, jobs: int | None) -> None:
    """``--jobs`` is a count of processes: None (the default) or at least 1."""
    if jobs is not None and jobs < 1:
        raise InputError(f"{stage}: --jobs must be at least 1 (got {jobs})")


def todo(frames: Iterable[T], done: Callable[[T], bool], force: bool = False) -> list[T]:
    """The frames still to make: all of them with ``force``, else those ``done`` does not accept."""
    return [f for f in frames if force or not done(f)]


def map_over_frames(stage: str, fn: Callable, tasks: list[tuple[int, tuple]],
                    on_done: Callable[[FrameResult], str | None], *, shared: Path, jobs: int = 1,
                    cluster: str | None = None, cfg=None, total: int | None = None,
                    completed: int = 0, show_progress: bool = True, sweep: Iterable[Path] = (),
                    around: Callable | None = None) -> None:
    """Run ``fn`` over ``tasks`` ((index, args) pairs) on an executor (here with ``jobs`` = 1, a
    local pool, or Dask with ``cluster``; ``shared`` is the folder its workers must see), with a
    progress bar of ``total`` frames of which ``completed`` were skipped. ``on_done`` records each
    finished frame (in this process) and returns the bar's text. The executor is closed and the
    folders ``sweep`` are cleared of temporary files however it ends. ``around``: a context
    manager factory the frames run inside (e.g. a stage timer)."""
    if not tasks:
        return
    ex = executor(cluster, shared, jobs=min(max(1, jobs), len(tasks)), cfg=cfg)
    try:
        with progress(disable=None if show_progress else True) as bar:
            task = bar.add_task(stage, total=len(tasks) + completed if total is None else total, completed=completed,
                                info="")
            if around is None:
                map_frames(ex, stage, fn, tasks, bar, task, on_done, report=show_progress)
            else:
                with around():
                    map_frames(ex, stage, fn, tasks, bar, task, on_done, report=show_progress)
    finally:
        ex.close()
        for d in sweep:
            sweep_temps(d)
