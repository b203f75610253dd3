"""Worker processes that never outlive the process that started them.

``mesh --jobs N`` and ``render`` start worker processes. If the parent is
killed (SIGTERM, kill -9, an out-of-memory kill) nothing shuts them down:
a process-pool worker then waits for work for ever on a queue it holds
itself, and a Blender worker renders on to the end, each holding hundreds
of megabytes. A worker therefore calls :func:`die_with_parent` first thing:

- on Linux the kernel sends it SIGKILL when its parent dies
  (``prctl(PR_SET_PDEATHSIG)``, see prctl(2));
- everywhere, a daemon thread checks every ``WATCH_INTERVAL`` seconds that
  its parent is still the one that started it (an orphan is re-parented to
  init or a subreaper) and ends the process if not.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import shutil
import signal
import sys
import threading
import time
import traceback
from typing import Callable, NoReturn

#: environment variable that tells a worker started with subprocess its parent's pid
PARENT_PID_ENV = "WHITECAP_PARENT_PID"
#: option number of PR_SET_PDEATHSIG in <linux/prctl.h>
PR_SET_PDEATHSIG = 1
#: seconds between the watchdog's checks of the parent pid [s]
WATCH_INTERVAL = 0.5


def die_with_parent(parent_pid: int | None = None) -> None:
    """Make this process end when ``parent_pid`` (default: from the environment) ends."""
    if parent_pid is None:
        parent_pid = int(os.environ.get(PARENT_PID_ENV) or os.getppid())
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):
            pass  # the watchdog below still works
    if os.getppid() != parent_pid:  # the parent died before we got here
        os._exit(1)
    threading.Thread(target=_watch, args=(parent_pid,), name="whitecap-parent-watch", daemon=True).start()


def _watch(parent_pid: int) -> None:
    while True:
        time.sleep(WATCH_INTERVAL)
        if os.getppid() != parent_pid:
            os._exit(1)


def child_env() -> dict[str, str]:
    """The environment for a worker started with subprocess: ours plus our pid."""
    return {**os.environ, PARENT_PID_ENV: str(os.getpid())}


def end_process(code: int) -> NoReturn:
    """End this worker process at once with status ``code``: its standard streams flushed, then ``os._exit``,
    which skips the interpreter's teardown and with it bpy's (a whole Blender, torn down at exit). That teardown
    crashed now and then after the work was done (glibc's "tcache_thread_shutdown(): unaligned tcache chunk
    detected", SIGABRT, met in the test suite's bpy scripts), and a parent that reads the exit status took a
    render whose frames were all written for a failed one. Nothing is lost by skipping it: a worker's files are
    complete (written atomically) before it reports them. What the teardown would have removed, Blender's
    temporary folder of this process, is removed here (:func:`remove_blender_session_dir`)."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed pipe: the status still says how the work went
            stream.flush()
    remove_blender_session_dir()
    os._exit(code)


#: The name Blender gives the temporary folder it makes for itself when it starts (BLI_temp_dir_session: mkdtemp
#: with the template "blender_XXXXXX", in the system's or the user's temporary folder).
BLENDER_SESSION_DIR = re.compile(r"blender_[A-Za-z0-9]{6}")


def remove_blender_session_dir() -> None:
    """Remove the temporary folder bpy made for this process when it was imported (``bpy.app.tempdir``), as
    Blender's own teardown does, which :func:`end_process` skips: each Blender worker left an empty
    ``/tmp/blender_XXXXXX`` behind (2,448 on the development machine after a day of test runs). Only a folder
    with the name Blender gives its own is removed, and never a base folder it makes them in (where Blender cannot
    make its own, bpy.app.tempdir names the base itself: a user's folder); nothing where bpy was never imported."""
    bpy = sys.modules.get("bpy")
    if bpy is None:
        return
    with contextlib.suppress(Exception):  # (a bpy without app.tempdir, a folder already gone: nothing to do)
        path = os.path.normpath(bpy.app.tempdir)
        if (BLENDER_SESSION_DIR.fullmatch(os.path.basename(path)) and path not in _temp_bases(bpy)
                and os.path.isdir(path)):
            shutil.rmtree(path, ignore_errors=True)


def _temp_bases(bpy) -> set[str]:
    """The folders Blender may make its session folder in (its preference, the environment's, the system's)."""
    import tempfile

    prefs = getattr(getattr(getattr(bpy, "context", None), "preferences", None), "filepaths", None)
    named = [getattr(prefs, "temporary_directory", ""), *(os.environ.get(v) for v in ("TMPDIR", "TMP", "TEMP")),
             tempfile.gettempdir(), "/tmp"]
    return {os.path.normpath(os.path.abspath(b)) for b in named if b}


def run_then_end(work: Callable[[], object], on_os_error: Callable[[OSError], NoReturn] | None = None) -> NoReturn:
    """A worker process's main: ``work()``, then :func:`end_process`: 0 when it returned, and when it raised,
    1 after its traceback on standard error (the error on the last line, which the parent shows), or
    ``on_os_error(exc)`` for an OSError (the parent's protocol for a full disk or a read-only folder). A
    SystemExit keeps its status (its message, if any, printed as the interpreter would)."""
    try:
        work()
    except SystemExit as exc:
        if exc.code is None or isinstance(exc.code, int):
            end_process(exc.code or 0)
        print(exc.code, file=sys.stderr)
        end_process(1)
    except OSError as exc:
        if on_os_error is None:
            traceback.print_exc()
            end_process(1)
        on_os_error(exc)
    except BaseException:
        traceback.print_exc()
        end_process(1)
    end_process(0)
