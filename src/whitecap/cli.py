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

from .config import ARCHES, DEFAULT_ARCH, DEFAULT_UP, UP_AXES, Foam, Mesh, View, choices
from .errors import WhitecapError
from .pipeline import RUN_STAGES

CLUSTER_HELP = ("run the frames on Dask: a scheduler address (tcp://host:8786), local (a local cluster of --jobs "
                "workers), or slurm / pbs (batch jobs described by the scene's [cluster] section); needs "
                "pip install 'whitecap[cluster]'")


def _from_args(cls, a):
    """A stage's options object (a dataclass) from the parsed arguments named like its fields;
    the fields the command has no option for keep their defaults."""
    import dataclasses

    return cls(**{f.name: getattr(a, f.name) for f in dataclasses.fields(cls) if hasattr(a, f.name)})


def _add_cluster_option(p, scope: str = "", default: str | None = None) -> None:
    """The --cluster option shared by the per-frame commands (mesh, export, render, run);
    ``scope`` prefixes the help when the option applies to only some of a command's modes."""
    p.add_argument("--cluster", metavar="WHERE", default=default, help=scope + CLUSTER_HELP)


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
    p.add_argument("--arch", default=DEFAULT_ARCH, choices=ARCHES, help=f"Taichi backend (default {DEFAULT_ARCH})")
    p.add_argument("--no-foam", dest="foam", action="store_false", help="do not generate diffuse particles")
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
    info = pipeline.simulate(a.scene, _simulate_job(a), out=a.out)
    print(f"wrote {len(info.frames)} frames to {info.extra['out']}")
    return 0


def _simulate_job(a):
    """The SimulateJob of `whitecap simulate`'s arguments (built here, after parsing: the solver's
    driver loads Taichi, which `--help` should not wait for)."""
    from .sim.driver import SimulateJob

    return _from_args(SimulateJob, a)


# ============================================================================ foam
def _add_foam(sub) -> None:
    p = sub.add_parser(
        "foam",
        help="diffuse particles (spray, foam, bubbles) over any particle sequence",
        description="Generate spray, foam and air bubbles (Ihmsen et al. 2012) for INPUT: a whitecap run "
        "directory, a DualSPHysics PartVTK folder (its case XML is read when beside the files), "
        "SPlisHSPlasH VTK or partio (.bgeo) output, or numbered PLY/VTU/NPZ files. "
        "Writes diffuse/diffuse_NNNNN.ply and diffuse/counts.csv. A pass stopped half-way continues after its last "
        "complete frame when run again with the same settings.",
    )
    p.add_argument("input", nargs="?", help="run directory, sequence directory or glob ('frames/*.vtk'); "
                   "may be left out when --params names it ([PATHS] InputDataPath)")
    p.add_argument("--out", "-o", help="output run directory (default: the input run itself)")
    p.add_argument("--preset", choices=choices(Foam, "preset"),
                   help="parameter preset (splishsplash: FoamGenerator's default, automatic mode; "
                   "splishsplash-box: the same run with the domain as its --bbsize box)")
    p.add_argument("--params", help="parameter .ini: the VisualSPHysics foam simulator's file DualSPHysics users have "
                   "(its [PATHS], [TIMESTEPS] and [DOMAIN] give the job: `whitecap foam --params FILE` runs it), "
                   "or DiffuseCalculator-style keys (TaMin, KTa...)")
    p.add_argument("--case", help="DualSPHysics case XML (spacing, mass, time step, domain)")
    p.add_argument("--up", default=DEFAULT_UP, choices=UP_AXES, help="up axis of the input (y for Y-up solvers)")
    p.add_argument("--dt", type=float, help="time between frames [s] when the input does not say")
    p.add_argument("--radius", type=float, help="fluid particle radius [m] (half the spacing) when unknown")
    p.add_argument("--seed", type=int, help="random seed (default: the run's)")
    p.add_argument("--force", action="store_true", help="replace a run of another simulation at --out (whole)")
    p.add_argument("--arch", default=DEFAULT_ARCH, choices=ARCHES, help=f"Taichi backend (default {DEFAULT_ARCH})")
    p.add_argument("--profile", action="store_true", help="print time spent per phase")
    p.set_defaults(func=_cmd_foam)


def _cmd_foam(a) -> int:
    from . import pipeline

    info = pipeline.foam(a.input, _foam_job(a), out=a.out, ini=a.params, case=a.case)
    made, listed = info.extra.get("made"), len(info.files("diffuse"))
    if made != 0:  # 0: a complete pass, which said so
        some = f"{made} of {listed}" if made is not None and made != listed else f"{listed}"
        print(f"wrote diffuse particles for {some} frames to {info.extra.get('out', a.out or a.input)}")
    return 0


def _foam_job(a):
    """The FoamJob of `whitecap foam`'s arguments (built here, after parsing: the diffuse stage
    loads Taichi, which `--help` should not wait for)."""
    from .diffuse import FoamJob

    return _from_args(FoamJob, a)


# ============================================================================ import
def _add_import(sub) -> None:
    p = sub.add_parser(
        "import",
        help="a whole case from DualSPHysics or SPlisHSPlasH (fluid, tank, obstacles, bodies) as a run directory",
        description="Convert CASE_OUTPUT, a DualSPHysics output folder (PartFluid_/PartAll_ VTK and the case XML) "
        "or a SPlisHSPlasH output folder, into the run directory OUT: the fluid frames, one mesh per "
        "boundary shape under OUT/geometry (the tank as the container) and the poses of moving bodies. "
        "Any other folder or glob of numbered frames is a bare sequence (fluid only; --dt and --radius). "
        "Then `whitecap foam OUT`, `mesh OUT` and `render OUT` continue from there. Resumable.",
    )
    from .cases import ImportJob

    default = ImportJob()  # the one definition of import's defaults
    p.add_argument("case_output", help="the solver's output folder")
    p.add_argument("--out", "-o", required=True, help="run directory to write")
    p.add_argument("--up", default=default.up, choices=UP_AXES,
                   help="up axis of the case (default: z for DualSPHysics, y for SPlisHSPlasH)")
    p.add_argument("--xml", default=default.xml, help="DualSPHysics case XML (default: the one in CASE_OUTPUT)")
    p.add_argument("--floating-csv", default=default.floating_csv,
                   help="DualSPHysics FloatingInfo CSV (FloatingMotion_mkNN.csv) whose motion "
                   "places the floating body, in place of fitting it to its particles")
    p.add_argument("--scene", dest="scene_json", metavar="SCENE", default=default.scene_json,
                   help="SPlisHSPlasH scene JSON that was run (default: the only *.json in "
                   "CASE_OUTPUT or CASE_OUTPUT/Scenes)")
    p.add_argument("--fluid-model", default=default.fluid_model,
                   help="SPlisHSPlasH fluid model id (ParticleData_<id>_<k>.vtk) when there are several")
    p.add_argument("--dt", type=float, default=default.dt,
                   help="a bare sequence's time between frames [s] (when no case XML says)")
    p.add_argument("--radius", type=float, default=default.radius,
                   help="a bare sequence's particle radius [m] (half the spacing)")
    p.add_argument("--force", action="store_true", default=default.force,
                   help="start over in a directory that holds another run")
    p.set_defaults(func=_cmd_import)


def _cmd_import(a) -> int:
    from . import pipeline
    from .cases import ImportJob

    info = pipeline.import_case(a.case_output, a.out, _from_args(ImportJob, a))
    roles = ", ".join(f"{o.name} ({o.role})" for o in info.obstacles) or "no shapes"
    print(f"imported {len(info.files('fluid'))} frames and {roles} into {a.out}")
    return 0


# ============================================================================ mesh
def _add_mesh(sub) -> None:
    p = sub.add_parser(
        "mesh",
        help="reconstruct fluid surfaces with splashsurf",
        description="Reconstruct a surface per frame of a run directory (RUN/mesh/fluid_NNNNN.ply, recorded in "
        "run.json) or of any particle sequence (a directory or a quoted glob of numbered files). Defaults come "
        "from the run's particle radius and its [mesh] section; every value can be overridden here.",
    )
    p.add_argument("input", help="run directory, directory of numbered particle files, or a quoted glob")
    p.add_argument("--out", "-o", help="mesh directory (default RUN/mesh, or <sequence dir>/mesh)")
    p.add_argument("--radius", type=float, help="simulation particle radius r [m], half the spacing "
                   "(default: the run's; required for plain sequences)")
    p.add_argument("--config", help="scene TOML whose [mesh] section to use (default: the run's scene.toml)")
    d = {name: f.default for name, f in Mesh.model_fields.items()}  # [mesh]'s defaults, defined once there
    p.add_argument("--radius-factor", type=float,
                   help=f"surface radius as a multiple of r (default {d['radius_factor']})")
    p.add_argument("--smoothing-length", type=float,
                   help=f"smoothing length, multiple of the surface radius ({d['smoothing_length']})")
    p.add_argument("--cube-size", type=float,
                   help=f"marching-cubes cell, multiple of the surface radius ({d['cube_size']})")
    p.add_argument("--iso", dest="iso_surface_threshold", type=float,
                   help=f"iso-surface threshold ({d['iso_surface_threshold']})")
    p.add_argument("--smoothing-iters", dest="mesh_smoothing_iters", type=int,
                   help=f"mesh smoothing passes ({d['mesh_smoothing_iters']})")
    p.add_argument("--weights-normalization", dest="mesh_smoothing_weights_normalization", type=float,
                   help="neighbour count at which a vertex is smoothed fully; lower smooths thin films "
                   f"({d['mesh_smoothing_weights_normalization']:g})")
    p.add_argument("--normals-smoothing-iters", type=int,
                   help=f"normal smoothing passes ({d['normals_smoothing_iters']})")
    p.add_argument("--no-cleanup", dest="mesh_cleanup", action="store_const", const=False, help="skip mesh cleanup")
    p.add_argument("--no-weights", dest="mesh_smoothing_weights", action="store_const", const=False,
                   help="unweighted Laplacian smoothing")
    p.add_argument("--no-velocity", dest="interpolate_velocity", action="store_const", const=False,
                   help="do not interpolate particle velocity onto vertices")
    p.add_argument("--format", choices=choices(Mesh, "format"),
                   help=f"mesh file format (default {d['format']}; obj has no velocity)")
    p.add_argument("--up", default=DEFAULT_UP, choices=UP_AXES,
                   help=f"up axis of the input files (default {DEFAULT_UP})")
    from .surface.driver import MeshRun

    run = MeshRun()  # the one definition of how mesh runs by default
    p.add_argument("--jobs", "-j", type=int, default=run.jobs, help="frames in parallel (default: the core count)")
    p.add_argument("--force", action="store_true", default=run.force, help="redo frames that already have a mesh")
    _add_cluster_option(p, default=run.cluster)
    p.add_argument("--profile", action="store_true", help="print time spent per phase")
    p.set_defaults(func=_cmd_mesh)


_MESH_OVERRIDES = ("radius_factor", "smoothing_length", "cube_size", "iso_surface_threshold", "mesh_smoothing_iters",
                   "normals_smoothing_iters", "mesh_cleanup", "mesh_smoothing_weights", "interpolate_velocity",
                   "mesh_smoothing_weights_normalization", "format")


def _cmd_mesh(a) -> int:
    import warnings

    from . import pipeline
    from .surface.driver import MeshRun

    warnings.simplefilter("default")
    warnings.formatwarning = lambda msg, *args, **kw: f"warning: {msg}\n"
    overrides = {k: getattr(a, k) for k in _MESH_OVERRIDES}
    stats = pipeline.mesh(a.input, _from_args(MeshRun, a), out=a.out,
                          radius=a.radius, config=a.config, up=a.up, profile=a.profile, **overrides)
    made = [s for s in stats if not s["skipped"]]
    tris = sum(s["faces"] for s in made)
    print(f"meshed {len(made)} frames ({tris} triangles), skipped {len(stats) - len(made)} already done")
    return 0


# ============================================================================ export
def _add_export(sub) -> None:
    p = sub.add_parser(
        "export",
        help="write a run as ParaView series (VTK XML, PLY) or as one USD stage or Alembic archive",
        description="Write the fluid particles, diffuse particles and meshes of RUN as ParaView series in "
        "RUN/export: one file per frame plus a collection with each frame's simulated time (.pvd for vtk, "
        ".series for ply); or the whole run as one animated scene for other tools (usd: RUN/export/usd/scene.usd, "
        "abc: RUN/export/abc/scene.abc) with the fluid surface, diffuse particles, obstacles and camera.",
    )
    p.add_argument("run", help="run directory")
    from .export import ExportJob

    default = ExportJob()  # the one definition of export's defaults
    p.add_argument("--to", default=default.to, metavar="FORMAT",
                   help=f"vtk: .vtp + .pvd; ply: PLY + .series; usd: USD stage; abc: Alembic archive "
                   f"(default {default.to})")
    p.add_argument("--out", "-o", help="output directory (default RUN/export, or RUN/export/usd|abc)")
    p.add_argument("--split-types", action="store_true", default=default.split_types,
                   help="also write diffuse spray, foam and bubbles as separate series (usd and abc always "
                   "split them)")
    p.add_argument("--jobs", "-j", type=int, default=default.jobs,
                   help=f"vtk, ply: frames in parallel (default {default.jobs}: export is mostly disk)")
    _add_cluster_option(p, "vtk, ply: ", default=default.cluster)
    p.set_defaults(func=_cmd_export)


def _cmd_export(a) -> int:
    from . import pipeline
    from .export import ExportJob

    written = pipeline.export(a.run, _from_args(ExportJob, a), out=a.out)
    for name, path in written.items():
        print(f"{name}: {path}")
    return 0


# ============================================================================ view
def _add_view(sub) -> None:
    p = sub.add_parser(
        "view", help="real-time viewer (GGUI window or --web browser), live or playback, or headless PNGs",
        description="Show a scene while it simulates (TARGET is a scene .toml), or play back a run "
        "directory or a numbered particle sequence. --headless writes OUT/view_NNNNN.png without a display; "
        "--web serves the viewer to a browser (prints the URL).",
    )
    from .view import ViewJob

    default = ViewJob()  # the one definition of view's defaults
    p.add_argument("target", help="scene .toml (live), run directory, or particle sequence (dir, file or glob)")
    p.add_argument("--headless", action="store_true", default=default.headless,
                   help="render offscreen to PNGs instead of opening a window")
    p.add_argument("--frames", type=int, default=default.frames,
                   help="frames to render headless (live: simulated frames; default: all / 1)")
    p.add_argument("--out", "-o", help="output directory for PNGs, screenshots and recordings")
    p.add_argument("--mp4", action="store_true", default=default.mp4, help="with --headless, also encode OUT/view.mp4")
    p.add_argument("--color", dest="color_mode", default=default.color_mode, choices=choices(View, "color_mode"),
                   help="colour fluid by speed or density")
    p.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), default=default.size, help="image size in pixels")
    p.add_argument("--panel", action="store_true", default=default.panel,
                   help="with --headless, draw the side panel too")
    p.add_argument("--no-legend", dest="legend", action="store_false", default=default.legend,
                   help="with --headless, leave out the colour legend")
    p.add_argument("--up", default=default.up, choices=UP_AXES,
                   help=f"up axis of a sequence's files (default {default.up})")
    p.add_argument("--arch", default=default.arch, choices=ARCHES, help="Taichi backend for live simulation")
    p.add_argument("--web", action="store_true", default=default.web,
                   help="serve the viewer to a web browser instead of a window (pip install 'whitecap[web]')")
    p.add_argument("--port", type=int, default=default.port,
                   help=f"with --web, the port to serve on (default {default.port})")
    p.add_argument("--host", default=default.host,
                   help=f"with --web, the address to serve on (default {default.host}; 0.0.0.0 for all)")
    p.add_argument("--max-points", type=int, default=default.max_points,
                   help="with --web --points browser, particles drawn at most per kind; more are subsampled")
    p.add_argument("--points", default=default.points, choices=choices(View, "web_points"),
                   help="with --web, where particles are drawn: browser (WebGL points), server (pictures drawn here, "
                   "for large runs and slow browsers), auto (server above 30,000 particles; "
                   "default: [view] web_points)")
    p.set_defaults(func=_cmd_view)


def _cmd_view(a) -> int:
    from . import pipeline
    from .view import ViewJob

    job = _from_args(ViewJob, a)
    paths = pipeline.view(a.target, job, out=a.out)
    if job.headless:
        print(f"wrote {len(paths)} images to {a.out}" + (" and view.mp4" if job.mp4 else ""))
    return 0


# ============================================================================ render
def _add_render(sub) -> None:
    p = sub.add_parser(
        "render",
        help="render a run in Blender (Cycles) to PNGs and an MP4",
        description="Render RUN's meshes and diffuse particles with Blender's Cycles (on a GPU where one exists). "
        "Writes render/frame_NNNNN.png, render/movie.mp4 and render/scene.blend; finished frames are skipped.",
    )
    from .render import RenderJob
    from .render.driver import DEVICES, QUALITIES

    default = RenderJob()  # the one definition of render's defaults
    p.add_argument("run", help="run directory (with mesh/ from `whitecap mesh`)")
    p.add_argument("--quality", default=default.quality, choices=QUALITIES,
                   help=f"preview: small and fast (default: {default.quality})")
    p.add_argument("--frames", default=default.frames, help="range a:b of frames to render (b excluded; default: all)")
    p.add_argument("--jobs", "-j", type=int, default=default.jobs,
                   help=f"worker processes (Cycles already uses all cores; default: {default.jobs})")
    p.add_argument("--force", action="store_true", default=default.force, help="render frames again even if they exist")
    p.add_argument("--no-movie", dest="movie", action="store_false", default=default.movie,
                   help="do not encode render/movie.mp4")
    p.add_argument("--device", default=default.device, choices=DEVICES,
                   help="Cycles device (default: [render].device, auto)")
    _add_cluster_option(p)
    p.set_defaults(func=_cmd_render)


def _cmd_render(a) -> int:
    from . import pipeline
    from .render import RenderJob

    r = pipeline.render(a.run, _from_args(RenderJob, a))
    print(f"rendered {len(r['frames'])} frames to {a.run}/render")
    if r.get("movie"):
        print(f"movie: {r['movie']}")
    print(f"blend: {r['blend']}")
    return 0


def _add_blender_addon(sub) -> None:
    p = sub.add_parser(
        "blender-addon",
        help="build the Blender add-on zip",
        description="Build a Blender 4.2+ extension zip that loads whitecap runs and VTK/PLY/OBJ sequences.",
    )
    p.add_argument("--out", "-o", default="whitecap_blender_addon.zip", help="zip file to write")
    p.set_defaults(func=_cmd_blender_addon)


def _cmd_blender_addon(a) -> int:
    from . import pipeline

    print(f"wrote {pipeline.blender_addon(a.out)}; "
          "install it in Blender: Edit > Preferences > Get Extensions > Install from Disk")
    return 0


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
    p.add_argument("--until", default="render", choices=RUN_STAGES, help="stop after this stage")
    p.add_argument("--preview", action="store_true", help="preview quality throughout (small, few samples)")
    p.add_argument("--frames", type=int, help="number of frames (overrides output.frames)")
    p.add_argument("--jobs", "-j", type=int, help="parallel worker processes for per-frame stages")
    _add_cluster_option(p)
    p.add_argument("--arch", default=DEFAULT_ARCH, choices=ARCHES, help="Taichi backend for the solver")
    p.set_defaults(func=_cmd_run)


def _cmd_run(a) -> int:
    from . import pipeline

    r = pipeline.run(a.scene, out=a.out, until=a.until, preview=a.preview, arch=a.arch, jobs=a.jobs, frames=a.frames,
                     cluster=a.cluster)
    sec = r["stage_seconds"]
    print("time per stage: " + ", ".join(f"{k} {v:.1f} s" for k, v in sec.items())
          + f"; total {sum(sec.values()):.1f} s (in {r['profile']})")
    print(f"run directory: {r['run']}")
    for key in ("movie", "blend"):
        if r.get(key):
            print(f"{key}: {r[key]}")
    return 0


# ============================================================================ main
def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="whitecap", description="Particle fluids from simulation to film-quality water."
    )
    parser.add_argument("--version", action="version", version=f"whitecap {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_simulate, _add_foam, _add_import, _add_mesh, _add_export, _add_view, _add_render,
                _add_blender_addon, _add_run):
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
        print("interrupted" + _RESUME_HINT.get(a.command, ""), file=sys.stderr)
        return 130
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except OSError as exc:  # disk full, read-only directory, a file where a folder should be...
        print(f"error: {os_error_message(exc)}", file=sys.stderr)
        return OS_ERROR_EXIT


# How each command continues after Ctrl-C (only those that keep finished work).
_RESUME_HINT = {
    "simulate": "; rerun with --resume to continue from the last checkpoint",
    "run": "; rerun the same command to continue where it stopped",
    "mesh": "; rerun the same command: frames already meshed are skipped",
    "import": "; rerun the same command: frames already imported are skipped",
    "render": "; rerun the same command: frames already rendered are skipped",
}
OS_ERROR_EXIT = 5


def os_error_message(exc: OSError) -> str:
    """One line naming the path(s) and the cause of an operating-system error."""
    cause = exc.strerror or str(exc) or type(exc).__name__
    paths = [str(os.fsdecode(f)) for f in (exc.filename, exc.filename2) if f is not None]
    if isinstance(exc, FileExistsError) and paths and os.path.isfile(paths[0]):
        cause = "a file is in the way of a directory"  # mkdir onto a file says only 'File exists'
    if not paths:
        return cause.replace("\n", " ")
    return (" -> ".join(paths) + f": {cause}").replace("\n", " ")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
