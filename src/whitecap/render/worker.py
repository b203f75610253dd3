"""Worker process entry: ``python -m whitecap.render.worker RUN QUALITY FRAMES THREADS SAVE_BLEND DEVICE``.

FRAMES is a comma-separated list, ``-`` for none, or ``serve``: then the
frames come one a line on standard input (:func:`~whitecap.render.driver.serve_worker`).

bpy is a whole Blender in one process; rendering in a child keeps it out of
the caller (which may hold a Taichi runtime) and lets frames spread over
several processes.

An operating-system error (a full disk, a read-only folder) ends the worker
with status ``OS_ERROR_EXIT`` and, as the last line of standard error, the
error as JSON after ``OS_ERROR_TAG`` (:func:`whitecap.executor.exit_on_os_error`),
so the parent (:class:`whitecap.executor.ProcessWorkers`) raises the same OSError.
"""

import sys
from pathlib import Path

from ..executor import exit_on_os_error
from ..workers import die_with_parent, run_then_end
from .driver import render_worker, serve_worker


def main() -> None:
    die_with_parent()  # a killed `whitecap render` takes its Blender workers with it
    run_then_end(_work, exit_on_os_error)  # ends without Blender's teardown (workers.end_process)


def _work() -> None:
    run, quality, frames, threads, save, device = sys.argv[1:7]
    if frames == "serve":
        serve_worker(Path(run), quality, int(threads) or None, device)
        return
    idx = [] if frames == "-" else [int(v) for v in frames.split(",")]
    render_worker(Path(run), quality, idx, int(threads) or None, save == "1", device)


if __name__ == "__main__":
    main()
