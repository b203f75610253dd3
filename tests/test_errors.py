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
