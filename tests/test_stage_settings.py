"""Each stage's settings are defined once, in its scene section (config.Foam, config.Mesh), and every
field of that section reaches the parameters the stage runs on (FoamParams, MeshParams): a field
added to [foam] or [mesh] without a counterpart fails here."""

from __future__ import annotations

import types
from dataclasses import MISSING, fields
from typing import Literal, Union, get_args, get_origin

import pytest
from pydantic import ValidationError

from whitecap.config import Foam, Mesh
from whitecap.diffuse.params import MADE_FROM, PRESET_BASE, PRESETS, FoamParams, resolve
from whitecap.errors import InputError
from whitecap.surface.driver import settings_key
from whitecap.surface.reconstruct import MeshParams, params_from_config

R = 0.01  # particle radius [m]


def _candidates(annotation, current) -> list:
    """Values of a field's type other than ``current``, to try one by one (some may be out of bounds)."""
    args = get_args(annotation)
    if get_origin(annotation) in (Union, types.UnionType):
        annotation = next(a for a in args if a is not type(None))
        args = get_args(annotation)
    if get_origin(annotation) is Literal:
        return [a for a in args if a != current]
    if annotation is bool:
        return [not current]
    if get_origin(annotation) is list:
        return [[0.5, 1.0], [1.0, 2.0, 3.0], [2.0, 1.0, 1.0]]
    if annotation is int:
        return [1, 2] if current is None else [current + 1, current - 1]
    if annotation is float:
        return [0.5, 1.0] if current is None else [current * 2, current / 2, current + 1]
    raise AssertionError(f"no test values for a field of type {annotation}: add them to _candidates")


def _changed(section: type, name: str, current, build):
    """The first value of ``name`` that the section accepts and ``build`` turns into other parameters."""
    base = build(section())
    for v in _candidates(section.model_fields[name].annotation, current):
        if v == current:
            continue
        try:
            made = build(section(**{name: v}))
        except (ValidationError, InputError):
            continue
        if made != base:
            return v, base, made
    return None, base, base


@pytest.mark.parametrize("name", list(Foam.model_fields))
def test_every_foam_field_reaches_the_params(name):
    default = resolve(Foam())
    current = Foam.model_fields[name].default
    current = getattr(default, name, None) if current is None else current  # unset: the preset's
    v, base, made = _changed(Foam, name, current, resolve)
    if MADE_FROM.get(name) == ():
        assert v is None, f"[foam] {name} is declared no parameter (MADE_FROM) but changes FoamParams"
        return
    assert v is not None, (f"[foam] {name} changes nothing in FoamParams: give it a field of the same name, "
                           "or say in diffuse.params.MADE_FROM what it makes")
    diff = {f.name for f in fields(FoamParams) if getattr(base, f.name) != getattr(made, f.name)} - {"explicit"}
    if name != "preset":  # a preset changes any value it sets
        assert diff == set(MADE_FROM.get(name, (name,))), f"[foam] {name} = {v!r} changed {diff}"
    if name not in MADE_FROM:
        assert getattr(made, name) == (tuple(v) if isinstance(v, list) else v)


def test_foam_params_take_their_defaults_from_the_scene_section_and_the_presets():
    """FoamParams has no defaults of its own; an unset [foam] field is the preset's value, and every other
    field keeps config.Foam's default."""
    assert [f.name for f in fields(FoamParams) if f.default is not MISSING or f.default_factory is not MISSING] == []
    made_from = {out for outs in MADE_FROM.values() for out in outs}
    for f in fields(FoamParams):
        assert f.name in Foam.model_fields or f.name in made_from or f.name == "explicit", \
            f"FoamParams.{f.name} comes from no [foam] field"
    for preset in PRESETS:
        p = resolve(Foam(preset=preset))
        for name, field in Foam.model_fields.items():
            if name in MADE_FROM:
                continue
            want = dict(PRESET_BASE, **PRESETS[preset]).get(name) if field.default is None else field.default
            want = tuple(want) if isinstance(want, list) else want
            assert getattr(p, name) == want, f"{preset}: {name} = {getattr(p, name)!r}, expected {want!r}"
        assert p.explicit == frozenset()


def _mesh(cfg: Mesh) -> MeshParams:
    return params_from_config(R, cfg)


@pytest.mark.parametrize("name", list(Mesh.model_fields))
def test_every_mesh_field_reaches_the_params_and_the_settings_key(name):
    v, base, made = _changed(Mesh, name, Mesh.model_fields[name].default, _mesh)
    assert v is not None and getattr(made, name) == v, f"[mesh] {name} does not reach MeshParams"
    same_key = settings_key(made) == settings_key(base)
    assert same_key == (name in MeshParams.NOT_RECONSTRUCTION), \
        f"[mesh] {name} = {v!r}: the settings key {'did not change' if same_key else 'changed'}"


def test_mesh_params_are_the_mesh_section_with_the_runs_numbers():
    """MeshParams inherits every [mesh] field and its default rather than declaring it again."""
    assert issubclass(MeshParams, Mesh)
    assert not set(MeshParams.__annotations__) & set(Mesh.model_fields), "MeshParams declares a [mesh] field again"
    p = MeshParams(particle_radius=R)
    for name, field in Mesh.model_fields.items():
        assert getattr(p, name) == field.default
    assert params_from_config(R) == p


# ---------------------------------------------------------------------------- render: one RenderJob
def test_render_options_are_one_render_job_whose_defaults_the_cli_shows(tmp_path, capsys):
    """`whitecap render` and pipeline.render build the same RenderJob: every field is a CLI option
    whose default is the job's, bad values are refused on construction (before any run is read),
    and keyword options replace fields of a given job."""
    from whitecap import pipeline
    from whitecap.cli import build_parser, main
    from whitecap.render import RenderJob

    default = RenderJob()
    args = build_parser().parse_args(["render", str(tmp_path)])
    for f in fields(RenderJob):
        if f.name != "show_progress":  # the CLI always shows progress
            assert getattr(args, f.name) == getattr(default, f.name), f.name
    help_text = build_parser()._subparsers._group_actions[0].choices["render"].format_help()
    assert f"default: {default.quality}" in help_text and f"default: {default.jobs}" in help_text
    for bad in ({"quality": "draft"}, {"device": "tpu"}, {"jobs": 0}):
        with pytest.raises(InputError, match="--" + next(iter(bad))):
            RenderJob(**bad)
        with pytest.raises(InputError):  # refused before the (missing) run is looked at
            pipeline.render(tmp_path / "no such run", **bad)
    assert main(["render", str(tmp_path), "--quality", "final", "--jobs", "0"]) == 2
    assert "--jobs must be at least 1" in capsys.readouterr().err
    with pytest.raises(InputError, match="run directory not found"):
        pipeline.render(tmp_path / "no such run", RenderJob(quality="final"), frames="0:1")


# ---------------------------------------------------------------------------- mesh: one MeshRun
def test_mesh_run_options_are_one_mesh_run_whose_defaults_the_cli_takes(tiny_run, tmp_path, capsys, monkeypatch):
    """`whitecap mesh` and pipeline.mesh build the same MeshRun: its fields that are CLI options have
    the run's defaults there, --jobs 0 is refused on construction (before any input is read), and
    keyword options reach the MeshRun while the other keywords stay [mesh] settings."""
    import shutil

    from whitecap import pipeline
    from whitecap.cli import build_parser, main
    from whitecap.surface import driver
    from whitecap.surface.driver import MeshRun

    default = MeshRun()
    args = build_parser().parse_args(["mesh", str(tmp_path)])
    for name in ("jobs", "force", "cluster"):
        assert getattr(args, name) == getattr(default, name), name
    with pytest.raises(InputError, match="mesh: --jobs must be at least 1"):
        MeshRun(jobs=0)
    with pytest.raises(InputError, match="--jobs"):  # refused before the (missing) input is looked at
        pipeline.mesh(tmp_path / "no such run", jobs=0)
    assert main(["mesh", str(tmp_path / "no such run"), "--jobs", "0"]) == 2
    assert "--jobs must be at least 1" in capsys.readouterr().err
    assert MeshRun(jobs=3).workers() == 3 and MeshRun().workers() >= 1

    seen = []
    run = tmp_path / "R"
    shutil.copytree(tiny_run, run)
    real = driver.run_mesh

    def spy(job, options):
        seen.append((job.params.mesh_smoothing_iters, options))
        return real(job, options)

    monkeypatch.setattr(driver, "run_mesh", spy)
    pipeline.mesh(run, MeshRun(force=True), jobs=1, show_progress=False, mesh_smoothing_iters=0)
    assert seen == [(0, MeshRun(jobs=1, force=True, show_progress=False))]


# ---------------------------------------------------------------------------- foam: one FoamJob
def test_foam_options_are_one_foam_job_that_the_cli_builds_with_its_defaults(tmp_path, monkeypatch):
    """`whitecap foam` builds the FoamJob its defaults make (so the CLI states none of its own), and
    pipeline.foam hands postprocess one FoamJob whose fields its keyword options replace."""
    from whitecap import diffuse, pipeline
    from whitecap.cli import _foam_job, build_parser
    from whitecap.diffuse import FoamJob

    args = build_parser().parse_args(["foam", str(tmp_path)])
    assert _foam_job(args) == FoamJob()
    args = build_parser().parse_args(["foam", str(tmp_path), "--up", "y", "--dt", "0.02", "--seed", "3", "--force"])
    assert _foam_job(args) == FoamJob(up="y", dt=0.02, seed=3, force=True)

    seen = []
    monkeypatch.setattr(diffuse, "postprocess", lambda src, out=None, case=None, job=None: seen.append(job))
    pipeline.foam(tmp_path, FoamJob(preset="auto", seed=5), seed=7, show_progress=False)
    assert seen == [FoamJob(preset="auto", seed=7, show_progress=False)]


# ---------------------------------------------------------------------------- --arch and --up: one default each
def test_every_command_defaults_to_the_one_arch_and_up_axis(tmp_path):
    """--arch and --up default, in every command that has them, to config's DEFAULT_ARCH and DEFAULT_UP,
    as do the pipeline functions and the stage options built from them."""
    import inspect

    from whitecap import pipeline
    from whitecap.cli import build_parser
    from whitecap.config import ARCHES, DEFAULT_ARCH, DEFAULT_UP, UP_AXES
    from whitecap.diffuse import FoamJob

    parser = build_parser()
    commands = parser._subparsers._group_actions[0].choices
    seen = {"arch": 0, "up": 0}
    for name, sub in commands.items():
        for action in sub._actions:
            if action.dest == "arch":
                assert (action.default, tuple(action.choices)) == (DEFAULT_ARCH, ARCHES), name
                seen["arch"] += 1
            elif action.dest == "up" and name != "import":  # import's default depends on the solver
                assert (action.default, tuple(action.choices)) == (DEFAULT_UP, UP_AXES), name
                seen["up"] += 1
    assert seen["arch"] >= 4 and seen["up"] >= 3
    for fn in (pipeline.simulate, pipeline.run, pipeline.mesh, pipeline.view):
        params = inspect.signature(fn).parameters
        for opt, default in (("arch", DEFAULT_ARCH), ("up", DEFAULT_UP)):
            if opt in params:
                assert params[opt].default == default, (fn.__name__, opt)
    from whitecap.sim.driver import SimulateJob
    from whitecap.view import ViewJob

    for job in (FoamJob(), SimulateJob(), ViewJob()):
        assert job.arch == DEFAULT_ARCH and getattr(job, "up", DEFAULT_UP) == DEFAULT_UP, job


# ---------------------------------------------------------------------------- simulate, export, import, view
def _job_classes():
    from whitecap.cases import ImportJob
    from whitecap.export import ExportJob
    from whitecap.sim.driver import SimulateJob
    from whitecap.view import ViewJob

    return {"simulate": (SimulateJob, ["scene.toml"]), "export": (ExportJob, ["run"]),
            "import": (ImportJob, ["case", "--out", "run"]), "view": (ViewJob, ["run"])}


@pytest.mark.parametrize("command", ["simulate", "export", "import", "view"])
def test_each_commands_options_are_one_job_whose_defaults_the_cli_takes(command):
    """`whitecap COMMAND` states no default of its own: its arguments, read into the command's job, make
    the job's defaults, and every field but show_progress (the CLI always shows progress) is an option."""
    from whitecap.cli import _from_args, build_parser

    cls, argv = _job_classes()[command]
    args = build_parser().parse_args([command, *argv])
    assert _from_args(cls, args) == cls()
    missing = {f.name for f in fields(cls)} - set(vars(args)) - {"show_progress"}
    assert not missing, f"{command}: fields with no option: {missing}"


def test_options_given_on_the_command_line_reach_the_job():
    from whitecap.cases import ImportJob
    from whitecap.cli import _from_args, build_parser
    from whitecap.export import ExportJob
    from whitecap.sim.driver import SimulateJob
    from whitecap.view import ViewJob

    parse = build_parser().parse_args
    assert _from_args(SimulateJob, parse(["simulate", "s.toml", "--frames", "3", "--no-foam", "--resume"])) == \
        SimulateJob(frames=3, foam=False, resume=True)
    assert _from_args(ExportJob, parse(["export", "r", "--to", "ply", "-j", "2", "--split-types"])) == \
        ExportJob(to="ply", jobs=2, split_types=True)
    assert _from_args(ImportJob, parse(["import", "c", "-o", "r", "--scene", "s.json", "--dt", "0.1"])) == \
        ImportJob(scene_json="s.json", dt=0.1)
    assert _from_args(ViewJob, parse(["view", "r", "--size", "320", "240", "--color", "density", "--no-legend"])) \
        == ViewJob(size=(320, 240), color_mode="density", legend=False)
    with pytest.raises(InputError, match="--web and --headless"):
        ViewJob(web=True, headless=True)


def test_the_pipeline_hands_each_driver_one_job_whose_fields_its_options_replace(tmp_path, monkeypatch):
    """pipeline.simulate/export/import_case/view take the stage's job, keyword options build one or
    replace its fields, and the driver receives that one object."""
    from whitecap import cases, export, pipeline, view
    from whitecap.cases import ImportJob
    from whitecap.config import scene_from_dict
    from whitecap.export import ExportJob
    from whitecap.sim import driver
    from whitecap.sim.driver import SimulateJob
    from whitecap.view import ViewJob

    seen = []
    monkeypatch.setattr(driver, "run_simulation", lambda sc, out, job, hooks: seen.append(job) or
                        types.SimpleNamespace(extra={}))
    pipeline.simulate(scene_from_dict({}), SimulateJob(frames=2), out=tmp_path / "s", foam=False)
    assert seen.pop() == SimulateJob(frames=2, foam=False)
    with pytest.raises(TypeError, match="SimulateJob"):  # the output folder is a keyword
        pipeline.simulate(scene_from_dict({}), tmp_path / "s")

    monkeypatch.setattr(export, "export", lambda run, job, out: seen.append((job, out)) or {})
    pipeline.export(tmp_path, ExportJob(to="ply"), jobs=2)
    assert seen.pop() == (ExportJob(to="ply", jobs=2), None)

    monkeypatch.setattr(cases, "import_case", lambda src, out, job: seen.append(job))
    pipeline.import_case(tmp_path, tmp_path / "r", dt=0.5, show_progress=False)
    assert seen.pop() == ImportJob(dt=0.5, show_progress=False)

    monkeypatch.setattr(view, "view", lambda target, job, out: seen.append((job, out)))
    pipeline.view(tmp_path, ViewJob(headless=True), out=tmp_path / "v", size=[8, 6])
    assert seen.pop() == (ViewJob(headless=True, size=(8, 6)), tmp_path / "v")


def test_an_unknown_export_target_is_refused_with_the_targets(tmp_path):
    from whitecap import pipeline

    with pytest.raises(InputError, match=r"unknown target 'obj' \(choose from vtk, ply, usd, abc\)"):
        pipeline.export(tmp_path, to="obj")
