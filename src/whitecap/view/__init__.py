"""Real-time viewer (Taichi GGUI): live simulation, playback of runs and
particle sequences, and headless PNG/MP4 output; and the same in a web browser
or a Jupyter notebook (viser, :mod:`.web`).

    from whitecap.view import view, web
    view("scenes/dam_break.toml")                       # live window
    view("out/dam_break", headless=True, out="frames")  # PNGs, no display needed
    web("out/dam_break")                                # in a notebook: shown inline
"""

from __future__ import annotations

from pathlib import Path

from ..config import DEFAULT_ARCH


def view(target, headless: bool = False, out=None, frames=None, mp4: bool = False, arch: str = DEFAULT_ARCH,
         **opts):
    """Show TARGET (scene TOML = live, run directory or sequence = playback).

    Headless returns the written PNG paths; interactive returns None when the window closes.
    """
    from .app import run_headless, run_interactive

    if headless:
        if out is None:
            from ..errors import InputError

            raise InputError("view --headless: --out DIR is required")
        return run_headless(target, out, frames=frames, mp4=mp4, arch=arch, **opts)
    return run_interactive(target, arch=arch, out=Path(out) if out else Path("view_out"), up=opts.get("up", "z"),
                           size=opts.get("size"), color_mode=opts.get("color_mode"))


# The browser viewer's entry point. Imported here, after the submodule of the same name,
# so that ``whitecap.view.web`` is this function (``from whitecap.view.web import
# WebViewer`` still reaches the module through the import system).
from .web import web  # noqa: E402

__all__ = ["view", "web"]
