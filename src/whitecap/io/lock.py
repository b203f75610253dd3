"""One writer per run directory: an exclusive ``flock`` on ``RUN/.whitecap.lock``.

Every stage that writes into a run (simulate, foam, mesh, render, export)
holds the lock for its whole duration. A second writer does not wait: it
fails at once with a one-line error naming the holder, whose process id and
command line are written into the lock file. The kernel drops the lock when
its holder exits, however it exits (kill -9 included), so a stale lock file
never blocks anyone. Nested use within one process (``whitecap run`` calling
each stage) is reentrant.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import sys
from pathlib import Path
from typing import Iterator

from ..errors import WhitecapError

LOCK_FILE = ".whitecap.lock"

# Locks this process holds: resolved run directory -> [file descriptor, depth].
_held: dict[Path, list[int]] = {}


class RunLocked(WhitecapError):
    """Another process is writing into the run directory."""


def _holder(fd: int) -> str:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        text = os.read(fd, 4096).decode(errors="replace").strip()
    except OSError:
        text = ""
    return text or "a process that has not written its name yet"


def _command() -> str:
    argv = sys.argv or ["python"]
    name = Path(argv[0]).name
    if name in ("cli.py", "__main__.py", "whitecap", "-c", ""):
        name = "whitecap" if name != "-c" else "python -c"
    return " ".join([name, *argv[1:]])


@contextlib.contextmanager
def run_lock(run_dir: str | Path, stage: str) -> Iterator[Path]:
    """Hold the run directory's writer lock while the block runs (creates the directory)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    key = run_dir.resolve()
    if key in _held:
        _held[key][1] += 1
        try:
            yield run_dir
        finally:
            _held[key][1] -= 1
        return
    path = run_dir / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RunLocked(
                f"{run_dir}: another whitecap process is writing into this run ({_holder(fd)}); "
                "wait for it to finish or use another directory"
            ) from None
        cmd = _command()
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, f"pid {os.getpid()}: {stage}: {cmd}\n".encode())
        _held[key] = [fd, 1]
        try:
            yield run_dir
        finally:
            del _held[key]
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # closing the descriptor releases the flock
