"""The ``whitecap`` command line: one subcommand per stage.

The CLI sits on top of everything: it parses arguments, calls the library
function of the stage (in :mod:`whitecap.pipeline` or the stage package) and
turns :class:`~whitecap.errors.WhitecapError` into a one-line message and a
non-zero exit.
"""

from __future__ import annotations

import argparse
import os
import sys

from .errors import WhitecapError


# ============================================================================ simulate
def _add_simulate(sub) -> None:
    p = sub.add_parser(
        "simulate",
        help="run the PBF solver on a scene and write particle frames",
        description="Simulate SCENE.toml with Position Based Fluids and write a run directory "
        "(scene.toml, run.json, fluid/fluid_NNNNN.ply, and diffuse particles when [foam] is on).",
    )
    p.add_argument("scene", nargs="?", help="scene TOML file")
    p.add_argument("--out", "-o", help="run directory to write (default: out/<scene name>)")
    p.add_argument("--frames", type=int, help="number of frames (overrides output.frames)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run from its last checkpoint")
    p.add_argument("--force", action="store_true", help="start over in a directory that already holds a run")
    p.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"], help="Taichi backend (default cpu)")
    p.add_argument("--no-foam", action="store_true", help="do not generate diffuse particles")
    p.add_argument("--profile", action="store_true", help="print time spent per phase")
    p.add_argument("--print-defaults", action="store_true", help="print the fully resolved scene and exit")
    p.set_defaults(func=_cmd_simulate)


def _cmd_simulate(a) -> int:
    from . import pipeline
    from .config import default_scene, load_scene

    if a.print_defaults:
        scene = load_scene(a.scene) if a.scene else default_scene()
        print(scene.to_toml(), end="")
        return 0
    if not a.scene:
        raise WhitecapError("simulate: a scene file is required (see --print-defaults for a template)")
    info = pipeline.simulate(
        a.scene, out=a.out, frames=a.frames, resume=a.resume, force=a.force, arch=a.arch,
        foam=not a.no_foam, profile=a.profile,
    )
    print(f"wrote {len(info.frames)} frames to {info.extra['out']}")
    return 0


# ============================================================================ foam
def _add_foam(sub) -> None:
    p = sub.add_parser("foam", help="diffuse particles (spray, foam, bubbles) over any particle sequence")
    p.set_defaults(func=_not_yet("foam"))


# ============================================================================ mesh
def _add_mesh(sub) -> None:
    p = sub.add_parser("mesh", help="reconstruct fluid surfaces with splashsurf")
    p.set_defaults(func=_not_yet("mesh"))


# ============================================================================ export
def _add_export(sub) -> None:
    p = sub.add_parser("export", help="write ParaView series (.pvd + VTK XML) of a run")
    p.set_defaults(func=_not_yet("export"))


# ============================================================================ view
def _add_view(sub) -> None:
    p = sub.add_parser(
        "view", help="real-time GGUI viewer, live or playback, or headless PNGs",
        description="Show a scene while it simulates (TARGET is a scene .toml), or play back a run "
        "directory or a numbered particle sequence. --headless writes OUT/view_NNNNN.png without a display.",
    )
    p.add_argument("target", help="scene .toml (live), run directory, or particle sequence (dir, file or glob)")
    p.add_argument("--headless", action="store_true", help="render offscreen to PNGs instead of opening a window")
    p.add_argument("--frames", type=int, help="frames to render headless (live: simulated frames; default: all / 1)")
    p.add_argument("--out", "-o", help="output directory for PNGs, screenshots and recordings")
    p.add_argument("--mp4", action="store_true", help="with --headless, also encode OUT/view.mp4")
    p.add_argument("--color", choices=["speed", "density"], help="colour fluid by speed or density")
    p.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="image size in pixels")
    p.add_argument("--panel", action="store_true", help="with --headless, draw the side panel too")
    p.add_argument("--no-legend", action="store_true", help="with --headless, leave out the colour legend")
    p.add_argument("--up", default="z", choices=["z", "y"], help="up axis of a sequence's files (default z)")
    p.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"], help="Taichi backend for live simulation")
    p.set_defaults(func=_cmd_view)


def _cmd_view(a) -> int:
    from . import pipeline

    if a.headless:
        if not a.out:
            raise WhitecapError("view --headless: --out DIR is required")
        paths = pipeline.view(
            a.target, headless=True, out=a.out, frames=a.frames, mp4=a.mp4, arch=a.arch,
            size=tuple(a.size) if a.size else None, color_mode=a.color, up=a.up, panel=a.panel,
            legend=not a.no_legend,
        )
        print(f"wrote {len(paths)} images to {a.out}" + (" and view.mp4" if a.mp4 else ""))
        return 0
    pipeline.view(a.target, out=a.out, arch=a.arch, up=a.up)
    return 0


# ============================================================================ render
def _add_render(sub) -> None:
    p = sub.add_parser("render", help="render a run in Blender (Cycles) to PNGs and an MP4")
    p.set_defaults(func=_not_yet("render"))


def _add_blender_addon(sub) -> None:
    p = sub.add_parser("blender-addon", help="build the Blender add-on zip")
    p.set_defaults(func=_not_yet("blender-addon"))


# ============================================================================ run
def _add_run(sub) -> None:
    p = sub.add_parser(
        "run",
        help="scene to movie: simulate (with foam), mesh, render, MP4",
        description="Run every stage on SCENE.toml into one run directory. Rerunning resumes at any "
        "stage without redoing finished frames.",
    )
    p.add_argument("scene", help="scene TOML file")
    p.add_argument("--out", "-o", help="run directory (default: out/<scene name>)")
    p.add_argument("--until", default="render", choices=["simulate", "mesh", "render"], help="stop after this stage")
    p.add_argument("--preview", action="store_true", help="preview quality throughout (small, few samples)")
    p.add_argument("--frames", type=int, help="number of frames (overrides output.frames)")
    p.add_argument("--jobs", "-j", type=int, help="parallel worker processes for per-frame stages")
    p.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"], help="Taichi backend for the solver")
    p.set_defaults(func=_cmd_run)


def _cmd_run(a) -> int:
    from . import pipeline

    r = pipeline.run(a.scene, out=a.out, until=a.until, preview=a.preview, arch=a.arch, jobs=a.jobs, frames=a.frames)
    print(f"run directory: {r['run']}")
    for key in ("movie", "blend"):
        if r.get(key):
            print(f"{key}: {r[key]}")
    return 0


# ============================================================================ main
def _not_yet(name: str):
    def f(a) -> int:
        raise WhitecapError(f"'{name}' is not available in this build yet")

    return f


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="whitecap", description="Particle fluids from simulation to film-quality water."
    )
    parser.add_argument("--version", action="version", version=f"whitecap {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_simulate, _add_foam, _add_mesh, _add_export, _add_view, _add_render, _add_blender_addon, _add_run):
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    a = parser.parse_args(argv)
    if not getattr(a, "func", None):
        parser.print_help()
        return 1
    try:
        return int(a.func(a) or 0)
    except WhitecapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("interrupted; rerun with --resume to continue from the last complete frame", file=sys.stderr)
        return 130
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
