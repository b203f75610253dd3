"""A full disk while `simulate` writes its checkpoint: one line naming the file, and nothing after
it (np.savez left its ZipFile open, whose __del__ printed a traceback later)."""

from __future__ import annotations

import builtins
import gc
import sys

import numpy as np
import pytest

from whitecap.io import atomic


def test_a_full_disk_is_one_oserror_naming_the_archive_and_nothing_after(tmp_path, monkeypatch):
    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    real_open = builtins.open
    monkeypatch.setattr(atomic, "open", lambda p, mode="r", **kw: real_open("/dev/full", mode), raising=False)
    target = tmp_path / "checkpoint.npz"
    with pytest.raises(OSError) as err:
        atomic.write_arrays(target, {"x": np.zeros(100_000), "frame": np.int64(3)})
    gc.collect()
    assert err.value.filename == str(target) and "No space left" in str(err.value)
    assert unraisable == [] and not target.exists() and list(tmp_path.iterdir()) == []


def test_written_arrays_read_back_with_numpy(tmp_path):
    a = {"positions": np.arange(12, dtype=np.float32).reshape(4, 3), "frame": np.int64(7)}
    atomic.write_arrays(tmp_path / "a.npz", a)
    z = np.load(tmp_path / "a.npz")
    assert sorted(z.files) == ["frame", "positions"] and (z["positions"] == a["positions"]).all()
    assert int(z["frame"]) == 7
