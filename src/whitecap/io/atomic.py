"""Write-then-rename, so that a crash never leaves a half-written file.

A reader sees either the previous complete file or the new complete file.
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from pathlib import Path
from typing import Iterator


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    The temporary file keeps the target's suffix so that libraries choosing a
    format by extension (plyfile, meshio, bpy, imageio) still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp makes 0600; outputs should read like normal files
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except OSError as exc:
        if exc.filename is None or exc.filename == str(tmp_path):
            # A write into the temporary file (disk full...) names no path or only the
            # temporary one: name the file the user asked for.
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str) -> None:
    write_bytes(path, text.encode())


def write_arrays(path: str | Path, arrays: dict) -> None:
    """``arrays`` as an .npz archive (what :func:`numpy.load` reads), written atomically.

    Not ``np.savez``: when a write fails (disk full) it leaves its ZipFile open, and that
    object's ``__del__`` prints a second traceback after the one-line error. Here the archive
    is closed on every path, so the OSError, naming ``path``, is all the user sees."""
    import zipfile

    import numpy as np

    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name, value in arrays.items():
                with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)


#: a temporary file of :func:`atomic_path`: ".STEM.XXXXXXXX.tmpSUFFIX" (mkstemp's 8 random characters)
_TEMP_NAME = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[^.]+)?$")


def sweep_temps(directory: str | Path) -> list[Path]:
    """Remove the temporary files a killed writer left in ``directory``; returns them.

    A process killed inside :func:`atomic_path` (kill -9, a Dask worker that
    died) cannot remove its temporary file. Call this only while holding the
    run's writer lock (:mod:`whitecap.io.lock`), when no writer of this stage
    is still running, so no temporary file in use is removed.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    gone = []
    for p in directory.iterdir():
        if _TEMP_NAME.match(p.name) and p.is_file():
            p.unlink(missing_ok=True)
            gone.append(p)
    return gone
