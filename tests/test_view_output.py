"""`view --headless --out D` writes only over what an earlier view wrote there, and leaves one
view's frames in D (issue 30: nothing of the user's overwritten, no frames of two runs mixed)."""

from __future__ import annotations

from .test_view import H, W, _cli, _render


def test_headless_view_keeps_the_users_files_and_one_views_frames(tiny_run, tmp_path):
    out = tmp_path / "pics"
    out.mkdir()
    (out / "view_00001.png").write_bytes(b"my holiday picture")
    r = _cli(tiny_run, "--headless", "--out", out, "--size", W, H, "--no-legend")
    assert r.returncode == 2 and "view_00001.png: not written by whitecap" in r.stderr.strip().splitlines()[-1]
    assert (out / "view_00001.png").read_bytes() == b"my holiday picture"

    (out / "view_00001.png").unlink()
    assert [p.name for p in _render(tiny_run, out)] == [f"view_{k:05d}.png" for k in range(4)]
    # A shorter view into the same folder: no frame of the first one is left beside it.
    assert [p.name for p in _render(tiny_run, out, "--frames", "2")] == ["view_00000.png", "view_00001.png"]


def test_the_addon_zip_never_replaces_a_users_file(tmp_path, capsys):
    from whitecap.cli import main

    mine = tmp_path / "notes.txt"
    mine.write_text("my notes")
    assert main(["blender-addon", "--out", str(mine)]) == 2
    assert "not a whitecap add-on zip" in capsys.readouterr().err
    assert mine.read_text() == "my notes"
    assert main(["blender-addon", "--out", str(tmp_path)]) == 0  # a folder: the zip goes inside
    assert main(["blender-addon", "--out", str(tmp_path / "whitecap_blender_addon.zip")]) == 0  # its own: rebuilt


def test_outputs_never_land_inside_another_run(tiny_run, tmp_path, capsys):
    """mesh, export and view write outside their own run only into folders of no other run."""
    import shutil

    from whitecap.cli import main

    other = tmp_path / "other"
    shutil.copytree(tiny_run, other)
    before = sorted(p.relative_to(other) for p in other.rglob("*"))
    for args in (["mesh", str(tiny_run), "-o", str(other / "fluid"), "--jobs", "1"],
                 ["mesh", str(tiny_run), "-o", str(other / "extra"), "--jobs", "1"],
                 ["export", str(tiny_run), "--out", str(other / "export")],
                 ["view", str(tiny_run), "--headless", "--out", str(other / "pics")]):
        assert main(args) == 2, args
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert f"lies in the run directory {other.resolve()} of another simulation" in err, err
    assert sorted(p.relative_to(other) for p in other.rglob("*")) == before
