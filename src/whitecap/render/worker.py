"""Worker process entry: ``python -m whitecap.render.worker RUN QUALITY FRAMES THREADS SAVE_BLEND DEVICE``.

bpy is a whole Blender in one process; rendering in a child keeps it out of
the caller (which may hold a Taichi runtime) and lets frames spread over
several processes.
"""

import sys
from pathlib import Path

from ..workers import die_with_parent
from .driver import render_worker


def main() -> None:
    die_with_parent()  # a killed `whitecap render` takes its Blender workers with it
    run, quality, frames, threads, save, device = sys.argv[1:7]
    idx = [] if frames == "-" else [int(v) for v in frames.split(",")]
    render_worker(Path(run), quality, idx, int(threads) or None, save == "1", device)


if __name__ == "__main__":
    main()
