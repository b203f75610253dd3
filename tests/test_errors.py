"""Operating-system errors and interrupts reach the user as one line, never a traceback."""

from __future__ import annotations

import errno
import os
import shutil

from whitecap.cli import main


def test_output_path_under_a_regular_file_is_one_line_naming_it(tiny_run, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory\n")
    code = main(["export", str(tiny_run), "--out", str(blocker / "export")])
    err = capsys.readouterr().err.strip()
    assert code == 5 and len(err.splitlines()) == 1, err
    assert err.startswith("error: ") and str(blocker) in err and "Not a directory" in err


def test_disk_full_names_the_file_being_written(tiny_run, tmp_path, monkeypatch, capsys):
    # A full disk fails the write into the temporary file (or its rename) with ENOSPC and
    # no file name of its own; the message must still say which output could not be written.
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)

    def full(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "replace", full)
    code = main(["export", str(run)])
    err = capsys.readouterr().err.strip()
    assert code == 5 and len(err.splitlines()) == 1, err
    assert err == f"error: {run / 'export' / 'fluid' / 'fluid_00000.vtp'}: No space left on device"
    assert not list((run / "export").rglob("*.tmp*"))  # no temporary file left behind


def test_interrupt_suggests_only_options_the_command_has(monkeypatch, capsys, tmp_path):
    import re

    from whitecap import pipeline
    from whitecap.cli import build_parser

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    sub = next(a for a in build_parser()._actions if a.dest == "command").choices
    for cmd, fn in (("simulate", "simulate"), ("mesh", "mesh"), ("run", "run"), ("render", "render"),
                    ("foam", "foam"), ("export", "export")):
        monkeypatch.setattr(pipeline, fn, interrupted)
        code = main([cmd, str(tmp_path / "x")])
        err = capsys.readouterr().err.strip()
        assert code == 130 and err.startswith("interrupted") and len(err.splitlines()) == 1, (cmd, err)
        known = {o for action in sub[cmd]._actions for o in action.option_strings}
        assert set(re.findall(r"--[a-z-]+", err)) <= known, (cmd, err)
        if cmd in ("mesh", "render", "run"):  # these skip finished frames when run again
            assert "rerun the same command" in err, (cmd, err)
    monkeypatch.setattr(pipeline, "simulate", interrupted)
    main(["simulate", str(tmp_path / "x")])
    assert "--resume" in capsys.readouterr().err


def _scene_file(tmp_path, text: str):
    path = tmp_path / "scene.toml"
    path.write_text('[solver]\nparticle_radius = 0.01\n' + text)
    return str(path)


def test_a_fluid_block_without_particles_is_named_with_the_reason(tmp_path, capsys):
    import trimesh

    thin = _scene_file(tmp_path, "[[fluid]]\nlower = [0, 0, 0]\nupper = [0.1, 0.1, 0.1]\n"
                                 "[[fluid]]\nlower = [0.2, 0, 0]\nupper = [0.3, 0.1, 0.015]\n")
    code = main(["simulate", thin, "--out", str(tmp_path / "a")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1, err
    assert err.startswith("error: fluid[1] (from [0.2, 0.0, 0.0] to [0.3, 0.1, 0.015]): holds no particle")
    assert "2r = 0.02 m" in err and "no fluid" not in err
    box = tmp_path / "box.stl"
    trimesh.creation.box(extents=[0.2, 0.2, 0.2]).export(str(box))
    buried = _scene_file(tmp_path, "[[fluid]]\nlower = [0.25, 0.05, 0.05]\nupper = [0.35, 0.15, 0.15]\n"
                                   f'[[obstacle]]\nmesh = "{box}"\ntranslate = [0.3, 0.1, 0.1]\n')
    code = main(["simulate", buried, "--out", str(tmp_path / "b")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1, err
    assert err.startswith("error: fluid[0] (from [0.25, 0.05, 0.05] to [0.35, 0.15, 0.15]): lies entirely inside")


def test_unreadable_checkpoint_in_run_suggests_what_run_can_do(tiny_run, tmp_path, capsys):
    import re

    from whitecap.cli import build_parser

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    (run / "checkpoint.npz").write_bytes(b"not a zip")
    code = main(["run", str(run / "scene.toml"), "--out", str(run), "--until", "simulate", "--frames", "5"])
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert code != 0 and len(errors) == 1 and "checkpoint.npz" in errors[0], errors
    err = errors[0]
    suggested = re.search(r"`whitecap (\w+)([^`]*)`", err)
    assert suggested, err  # a command the user can type, with options that command has
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices[suggested[1]]
    known = {o for action in sub._actions for o in action.option_strings}
    assert set(re.findall(r"--[a-z-]+", suggested[2])) <= known and "without --resume" not in err
