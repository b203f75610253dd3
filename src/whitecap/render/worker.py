"""Worker process entry: ``python -m whitecap.render.worker RUN QUALITY FRAMES THREADS SAVE_BLEND DEVICE``.

FRAMES is a comma-separated list, ``-`` for none, or ``serve``: then the
frames come one a line on standard input (:func:`~whitecap.render.driver.serve_worker`).

bpy is a whole Blender in one process; rendering in a child keeps it out of
the caller (which may hold a Taichi runtime) and lets frames spread over
several processes.
"""

import sys
from pathlib import Path

from ..workers import die_with_parent
from .driver import render_worker, serve_worker


def main() -> None:
    die_with_parent()  # a killed `whitecap render` takes its Blender workers with it
    run, quality, frames, threads, save, device = sys.argv[1:7]
    if frames == "serve":
        serve_worker(Path(run), quality, int(threads) or None, device)
        return
    idx = [] if frames == "-" else [int(v) for v in frames.split(",")]
    render_worker(Path(run), quality, idx, int(threads) or None, save == "1", device)


if __name__ == "__main__":
    main()
