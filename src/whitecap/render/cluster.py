"""The render stage on a Dask cluster: one Blender process per Dask worker, kept between frames.

:class:`BlenderWorkers` is a Dask worker plugin. On each worker it starts,
at the first frame, one ``python -m whitecap.render.worker RUN ... serve``
process: it imports ``bpy`` and builds the run's scene once, then renders
the frames it is sent on its standard input, exactly as the local render
workers do (the same :class:`~whitecap.render.driver.SceneRenderer`), so the
frames are the same bytes. The Blender process dies with its Dask worker
(:func:`whitecap.workers.die_with_parent`); the scheduler then runs the
worker's frame again elsewhere. Imported only when ``--cluster`` is given.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import IO, cast

from distributed import WorkerPlugin, get_worker

from ..workers import child_env


class BlenderWorkers(WorkerPlugin):
    """Keeps one Blender process with the run's scene built on each Dask worker."""

    def __init__(self, run_dir: str, quality: str, device: str, threads: int = 0):
        self.run_dir, self.quality, self.device, self.threads = str(run_dir), quality, device, int(threads)
        self.proc: subprocess.Popen | None = None

    def setup(self, worker=None) -> None:
        self.proc = None
        self.log: IO[str] | None = None  # the Blender process's stderr
        self.lock = threading.Lock()

    def teardown(self, worker=None) -> None:
        proc = getattr(self, "proc", None)
        if proc is not None and proc.poll() is None:
            proc.stdin.close()  # the server ends at the end of its input
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self.proc = None

    def _start(self) -> subprocess.Popen:
        self.log = tempfile.TemporaryFile(mode="w+")
        cmd = [sys.executable, "-m", "whitecap.render.worker", self.run_dir, self.quality, "serve",
               str(self.threads), "0", self.device]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.log, text=True,
                                     bufsize=1, env=child_env())
        self._expect("ready")
        return self.proc

    def _expect(self, word: str) -> str:
        proc, log = self.proc, self.log
        assert proc is not None and proc.stdout is not None and log is not None  # _start made them, piped
        for line in proc.stdout:
            if line.startswith(word):
                return line.strip()
        proc.wait()
        log.seek(0)
        last = (log.read().strip().splitlines() or [f"exit status {proc.returncode}"])[-1]
        self.proc = None
        raise RuntimeError(f"Blender render failed: {last}")

    def ask(self, request: str, answer: str) -> int:
        """Send one request to this worker's Blender process (started at the first); returns its pid."""
        with self.lock:
            proc = self.proc if self.proc is not None and self.proc.poll() is None else self._start()
            assert proc.stdin is not None  # piped
            proc.stdin.write(request + "\n")
            proc.stdin.flush()
            self._expect(answer)
            return proc.pid


def _blender(plugin: str) -> BlenderWorkers:
    """This Dask worker's BlenderWorkers plugin of that name (Dask types its plugins as WorkerPlugin)."""
    return cast(BlenderWorkers, get_worker().plugins[plugin])


def render_frame(plugin: str, index: int) -> dict:
    """A Dask task: render frame ``index`` with this worker's Blender process."""
    pid = _blender(plugin).ask(f"frame {index}", f"rendered {index}")
    return {"blender_pid": pid}


def save_blend(plugin: str) -> dict:
    """A Dask task: save render/scene.blend with this worker's Blender process."""
    return {"blender_pid": _blender(plugin).ask("blend", "saved blend")}


def render_on_cluster(ex, run_dir: Path, quality: str, device: str, todo: list[int], need_blend: bool,
                      bar, task, on_frame, report: bool = True) -> set[int]:
    """Render ``todo`` (and scene.blend when ``need_blend``) on the Dask executor ``ex``.

    ``on_frame(index)`` records a finished frame (in this process). Cycles in
    each Blender process uses the worker's cores, split between the workers
    when a local cluster puts several on this machine. Returns the process ids
    of the Blender processes that rendered (one per worker that took frames).
    """
    import uuid

    from ..executor import ClusterError, _one_line, map_frames

    name = f"whitecap-blender-{uuid.uuid4().hex[:8]}"
    ex.register(BlenderWorkers(str(Path(run_dir).resolve()), quality, device, ex.frame_threads), name)
    pids: set[int] = set()

    def done(r) -> None:
        pids.add(r.value["blender_pid"])
        on_frame(r.index)

    try:
        if todo:
            map_frames(ex, "render", render_frame, [(i, (name, i)) for i in todo], bar, task, done, report=report)
        if need_blend:
            try:
                ex.client.submit(save_blend, name, pure=False).result()
            except Exception as exc:  # its worker died (KilledWorker), or Blender failed
                raise ClusterError(f"render: saving render/scene.blend on the cluster failed ({_one_line(exc)}); "
                                   "the rendered frames are kept, rerun to save it") from None
    finally:
        ex.unregister(name)
    return pids
