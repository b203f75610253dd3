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

import ctypes
import os
import signal
import sys
import threading
import time

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
