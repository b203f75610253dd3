"""Real-time viewer (Taichi GGUI): live simulation, playback of runs and
particle sequences, and headless PNG/MP4 output; and the same in a web browser
or a Jupyter notebook (viser, :mod:`.web`).

    from whitecap.view import view, web
    view("scenes/dam_break.toml")                       # live window
    view("out/dam_break", headless=True, out="frames")  # PNGs, no display needed
    web("out/dam_break")                                # in a notebook: shown inline
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..config import DEFAULT_ARCH, DEFAULT_UP, with_options
from ..errors import InputError
from .web import DEFAULT_HOST, DEFAULT_PORT, MAX_POINTS


@dataclass(frozen=True)
class ViewJob:
    """What one ``view`` does: the options of ``whitecap view`` and of
    :func:`whitecap.pipeline.view`, with their defaults, defined here once (the CLI and the
    pipeline build one; :func:`view` takes it). Checked on construction.

    ``headless`` renders OUT/view_NNNNN.png offscreen (``frames`` of them; live: simulated
    frames), and OUT/view.mp4 with ``mp4``; ``web`` serves the viewer to a browser on ``host``:
    ``port`` instead of a window (``max_points`` particles per kind at most, drawn where
    ``points`` says: browser, server or auto; None: ``[view] web_points``). ``size`` (W, H) and
    ``color_mode`` replace the scene's ``[view]``; ``up`` is a sequence's up axis; ``arch`` the
    Taichi backend of a live simulation; ``panel`` and ``legend`` are drawn in headless pictures.
    """

    headless: bool = False
    frames: int | None = None
    mp4: bool = False
    arch: str = DEFAULT_ARCH
    web: bool = False
    size: tuple[int, int] | None = None
    color_mode: str | None = None
    up: str = DEFAULT_UP
    panel: bool = False
    legend: bool = True
    show_progress: bool = True
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    max_points: int = MAX_POINTS
    points: str | None = None

    def __post_init__(self) -> None:
        if self.web and self.headless:
            raise InputError("view: --web and --headless exclude each other")
        if self.size is not None:  # argparse gives a list
            object.__setattr__(self, "size", tuple(self.size))


def view(target, job: ViewJob | None = None, out=None, **options):
    """Show TARGET (scene TOML = live, run directory or sequence = playback) as ``job`` says
    (``options``, its field names, build one or replace its fields).

    Headless returns the written PNG paths; interactive returns None when the window closes;
    ``web`` serves until interrupted, after printing the URL.
    """
    job = with_options(ViewJob, job, options)
    if job.web:
        from .web import serve

        return serve(target, host=job.host, port=job.port, arch=job.arch, up=job.up, color_mode=job.color_mode,
                     max_points=job.max_points, points=job.points)
    from .app import run_headless, run_interactive

    if job.headless:
        if out is None:
            raise InputError("view --headless: --out DIR is required")
        return run_headless(target, out, frames=job.frames, mp4=job.mp4, arch=job.arch, size=job.size,
                            color_mode=job.color_mode, up=job.up, panel=job.panel, legend=job.legend,
                            show_progress=job.show_progress)
    return run_interactive(target, arch=job.arch, out=Path(out) if out else Path("view_out"), up=job.up,
                           size=job.size, color_mode=job.color_mode)


# The browser viewer's entry point. Imported here, after the submodule of the same name,
# so that ``whitecap.view.web`` is this function (``from whitecap.view.web import
# WebViewer`` still reaches the module through the import system).
from .web import web  # noqa: E402

__all__ = ["ViewJob", "view", "web"]
