"""Real-time viewer (Taichi GGUI): live simulation, playback of runs and
particle sequences, and headless PNG/MP4 output.

    from whitecap.view import view
    view("scenes/dam_break.toml")                       # live window
    view("out/dam_break", headless=True, out="frames")  # PNGs, no display needed
"""

from __future__ import annotations

from pathlib import Path


def view(target, headless: bool = False, out=None, frames=None, mp4: bool = False, arch: str = "cpu", **opts):
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


__all__ = ["view"]
