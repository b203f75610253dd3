"""One writer per run directory: an exclusive ``flock`` on ``RUN/.whitecap.lock``.

Every stage that writes into a run (simulate, foam, mesh, render, export)
holds the lock for its whole duration. A second writer does not wait: it
fails at once with a one-line error naming the holder, whose process id and
command line are written into the lock file. The kernel drops the lock when
its holder exits, however it exits (kill -9 included), so a stale lock file
never blocks anyone. Nested use within one process (``whitecap run`` calling
each stage) is reentrant.

A stage that only reads a run (an export whose output goes elsewhere) takes
:func:`read_lock` instead: a shared ``flock`` on the same file, so readers run
side by side and a writer (or a reader, while a writer works) is refused at
once. A run the reader cannot write into (read-only files, a read-only mount)
is read without a lock file when none exists: nobody without write access can
create one, so there is no writer to exclude that this process could see.
"""

from __future__ import annotations

import contextlib
import errno
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
    return text or "a process that reads it, or has not written its name yet"


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


#: errors that mean "this process may not create or open the lock file for writing"
_NO_WRITE = (errno.EACCES, errno.EPERM, errno.EROFS)


def _open_for_reading(path: Path) -> int | None:
    """A descriptor of the lock file to take a shared lock on, or None when there is no
    lock file and none can be created (a read-only run)."""
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        if exc.errno not in _NO_WRITE:
            raise
    try:  # a read-only run that a writer once locked: flock works on a read-only descriptor
        return os.open(path, os.O_RDONLY)
    except OSError as exc:
        if exc.errno in _NO_WRITE or exc.errno == errno.ENOENT:
            return None
        raise


@contextlib.contextmanager
def read_lock(run_dir: str | Path, stage: str) -> Iterator[Path]:
    """Hold a shared (reader) lock on the run directory while the block runs.

    Readers coexist; a writer holding :func:`run_lock` makes this fail at once with
    :class:`RunLocked`, and a writer arriving later is refused while readers hold it.
    Nothing is written into the run: the lock file is created when it can be (so a
    later writer sees the readers) and left out when the run is read-only. Inside this
    process's own :func:`run_lock` of the same run (``whitecap run``) it holds nothing more.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(run_dir))
    if run_dir.resolve() in _held:  # this process writes the run: it may read it too
        yield run_dir
        return
    fd = _open_for_reading(run_dir / LOCK_FILE)
    if fd is None:
        yield run_dir
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RunLocked(
                f"{run_dir}: another whitecap process is writing into this run ({_holder(fd)}); "
                f"{stage} reads it: wait for the writer to finish"
            ) from None
        yield run_dir
    finally:
        os.close(fd)


def is_inside(path: str | Path, directory: str | Path) -> bool:
    """Whether ``path`` is ``directory`` or lies under it (after resolving links)."""
    p, d = Path(path).resolve(), Path(directory).resolve()
    return p == d or d in p.parents


# Output directories outside any run this process is exporting into: resolved path -> depth.
_out_held: dict[Path, int] = {}


@contextlib.contextmanager
def output_lock(out_dir: str | Path, stage: str) -> Iterator[Path]:
    """Hold an exclusive ``flock`` on the output directory itself (creates it) while the block
    runs: two stages writing into one place outside a run exclude each other, and no lock
    file is left among the user's files. Reentrant within this process."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    key = out_dir.resolve()
    if key in _out_held:
        _out_held[key] += 1
        try:
            yield out_dir
        finally:
            _out_held[key] -= 1
        return
    fd = os.open(out_dir, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RunLocked(f"{out_dir}: another whitecap process is writing into this directory; "
                            f"wait for it to finish or give {stage} another --out") from None
        _out_held[key] = 1
        try:
            yield out_dir
        finally:
            del _out_held[key]
    finally:
        os.close(fd)


@contextlib.contextmanager
def export_locks(run_dir: str | Path, out: str | Path, stage: str) -> Iterator[None]:
    """The locks of a stage that reads ``run_dir`` and writes ``out``: the run's writer lock
    when ``out`` is inside the run; otherwise a reader lock on the run (which may then be
    read-only) and :func:`output_lock` on ``out``."""
    if is_inside(out, run_dir):
        with run_lock(run_dir, stage):
            yield
        return
    from .run import refuse_inside_other_run

    refuse_inside_other_run(out, run_dir, stage)
    with read_lock(run_dir, stage), output_lock(out, stage):
        yield
