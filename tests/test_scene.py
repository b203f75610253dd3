"""Scene file: validation, defaults, one-line errors with file and key."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from whitecap.cli import main
from whitecap.config import default_scene, load_scene, scene_from_dict
from whitecap.errors import InputError


def write(tmp_path, text: str):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return p


def test_defaults_round_trip(capsys):
    assert main(["simulate", "--print-defaults"]) == 0
    text = capsys.readouterr().out
    data = tomllib.loads(text)
    assert data["solver"]["particle_radius"] == default_scene().solver.particle_radius
    assert data["domain"]["gravity"] == [0.0, 0.0, -9.81]  # z is up
    again = scene_from_dict(data)
    assert again.model_dump() == default_scene().model_dump()


ROOT = Path(__file__).resolve().parents[1]
STATED = re.compile(r"([\d,.]+)(k?) particles")


def stated_count(text: str) -> float:
    """The particle count a comment or README line states: '10,044 particles', 'about 15k particles'."""
    m = STATED.search(text)
    assert m, f"no particle count in {text!r}"
    return float(m.group(1).replace(",", "")) * (1000 if m.group(2) else 1)


def test_shipped_scenes_validate():
    """Each shipped scene resolves to fluid inside its domain, its obstacle files exist, and the
    particle count its header and the README state is the one the solver starts with (within 5 %)."""
    from whitecap.sim import runtime
    from whitecap.sim.obstacles import load_obstacles
    from whitecap.sim.pbf import lattice_points

    scenes = sorted((ROOT / "scenes").glob("*.toml"))
    assert {p.stem for p in scenes} >= {"dam_break", "bunny", "wave_tank"}
    readme = (ROOT / "README.md").read_text()
    runtime.init("cpu")
    for path in scenes:
        scene = load_scene(path)
        assert scene.name == path.stem
        pos, _ = lattice_points(scene)
        lo, hi = np.asarray(scene.domain.lower), np.asarray(scene.domain.upper)
        assert len(pos) > 0 and (pos >= lo).all() and (pos <= hi).all(), path.name
        for o in scene.obstacle:
            for f in (o.mesh, o.render_mesh):
                assert f is None or scene.resolve(f).is_file(), f"{path.name}: {f} missing"
        if scene.obstacle:
            pos = pos[load_obstacles(scene).outside_mask(pos)]
        n = len(pos)
        header = "\n".join(ln for ln in path.read_text().splitlines() if ln.startswith("#"))
        assert stated_count(header) == pytest.approx(n, rel=0.05), f"{path.name} header vs {n} particles"
        row = [ln for ln in readme.splitlines() if ln.startswith(f"| `scenes/{path.name}`")]
        if row and "particles" in row[0]:
            assert stated_count(row[0]) == pytest.approx(n, rel=0.05), f"README row for {path.name} vs {n}"
    # The validation scene's count, exactly.
    assert len(lattice_points(load_scene(ROOT / "scenes" / "dam_break.toml"))[0]) == 10_044


@pytest.mark.parametrize(
    "text, expect",
    [
        ("[solver\nparticle_radius = 1", "malformed TOML"),
        ("[solver]\nparticle_radus = 0.01", "solver.particle_radus: unknown key; did you mean 'particle_radius'?"),
        ("[solver]\nparticle_radius = -0.01", "solver.particle_radius: Input should be greater than 0"),
        ("[domain]\nupper = [1, 2]", "domain.upper"),
        ("[[fluid]]\nlower = [0, 0, 0]\nupper = [5, 0.2, 0.2]", "outside the domain"),
        ("[[fluid]]\nshape = 'sphere'\ncenter = [0.5, 0.2, 0.3]", "a sphere needs 'center' and 'radius'"),
        ("[output]\nframes = 'many'", "output.frames"),
    ],
)
def test_bad_scene_one_line_error(tmp_path, capsys, text, expect):
    p = write(tmp_path, text)
    with pytest.raises(InputError) as e:
        load_scene(p)
    msg = str(e.value)
    assert str(p) in msg and expect in msg and "\n" not in msg
    # Through the CLI: non-zero exit and the same single line on stderr.
    code = main(["simulate", str(p), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and err.startswith("error: ") and expect in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_missing_scene_file(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "o")]) == 2
    assert "nope.toml: scene file not found" in capsys.readouterr().err


def test_too_many_particles_refused_before_allocating(tmp_path, capsys):
    p = write(
        tmp_path,
        "[domain]\nupper = [10, 10, 10]\n[solver]\nparticle_radius = 0.0005\n"
        "[[fluid]]\nlower = [0, 0, 0]\nupper = [10, 10, 5]\n",
    )
    code = main(["simulate", str(p), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code != 0 and "more than this machine has free" in err and "particles" in err


def test_cli_choices_are_the_scene_models():
    from whitecap.cli import build_parser
    from whitecap.config import Foam, Mesh, choices
    from whitecap.diffuse.params import resolve
    from whitecap.pipeline import RUN_STAGES

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices
    opt = {(cmd, o.dest): o.choices for cmd, p in sub.items() for o in p._actions if o.choices}
    assert tuple(opt[("foam", "preset")]) == choices(Foam, "preset")
    assert tuple(opt[("mesh", "format")]) == choices(Mesh, "format") == ("ply", "obj")
    assert tuple(opt[("run", "until")]) == RUN_STAGES
    for name in choices(Foam, "preset"):  # every preset the scene and CLI accept has values
        assert resolve(preset=name).spray_below > 0
