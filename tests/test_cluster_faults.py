"""Cluster runs as users meet them when something is off (issue 30).

- A frame is the same bytes whichever executor meshes it: this process, a
  local pool worker, a Dask worker (splashsurf's threads used to change the
  last bits of a large frame from run to run).
- ``--cluster`` with a malformed address, a listener that never answers, or
  a service that answers junk: one line, within the connect timeout.
- ``--cluster local`` starts no dashboard and prints no socket warning; a
  worker's death prints no raw Dask log line.
- A partly done cluster run resumes with each result recorded as the frame it
  belongs to, when frames finish out of order.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shutil
import signal
import socket
import sys
import threading
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

import tomli_w  # noqa: E402

from whitecap import pipeline  # noqa: E402
from whitecap.cli import main  # noqa: E402
from whitecap.io import ParticleFrame  # noqa: E402
from whitecap.io import write as write_particles  # noqa: E402
from whitecap.io.run import RunInfo  # noqa: E402


def _run_copy(tiny_run: Path, dest: Path, **scene_extra) -> Path:
    """A copy of the tiny run (fluid frames 0..3) with extra scene sections."""
    shutil.copytree(tiny_run, dest)
    scene = tomllib.loads((dest / "scene.toml").read_text())
    for k, v in scene_extra.items():
        scene.setdefault(k, {}).update(v)
    (dest / "scene.toml").write_text(tomli_w.dumps(scene))
    return dest


def _files(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(d.iterdir()) if p.is_file()}


@pytest.fixture(scope="module")
def worker_processes():
    """One Dask worker in its own process, as on a real cluster (one thread: frames bring their own)."""
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=logging.CRITICAL) as c:
        yield c


# ============================================================================ item 13: the same bytes anywhere
R = 0.004  # particle radius [m]: spacing 8 mm


def dam_break_frame(seed: int = 3) -> ParticleFrame:
    """About 30k particles a moment after a dam break: a leaning column, a tongue along the floor, spray."""
    rng = np.random.default_rng(seed)
    s = 2 * R
    g = np.stack(np.meshgrid(np.arange(0, 0.24, s), np.arange(0, 0.20, s), np.arange(0, 0.32, s), indexing="ij"),
                 -1).reshape(-1, 3)
    g[:, 0] += 0.6 * g[:, 2] ** 2  # the column's top leans downstream
    tongue = np.stack(np.meshgrid(np.arange(0.24, 0.50, s), np.arange(0, 0.20, s), np.arange(0, 2 * s, s),
                                  indexing="ij"), -1).reshape(-1, 3)
    spray = rng.uniform([0.35, 0.0, 0.02], [0.55, 0.20, 0.15], (600, 3))
    pos = np.concatenate([g, tongue, spray]) + R
    pos[: len(g) + len(tongue)] += rng.normal(0, 0.1 * s, (len(g) + len(tongue), 3))
    vel = np.zeros_like(pos)
    vel[:, 0] = 2.5 * np.sqrt(np.clip(0.35 - pos[:, 2], 0, None) / 0.35) + rng.normal(0, 0.05, len(pos))
    vel[:, 2] = -1.5 * pos[:, 2] / 0.3 + rng.normal(0, 0.05, len(pos))
    return ParticleFrame(positions=pos, velocities=vel, density=np.full(len(pos), 1000.0))


def mesh_and_digest(src: str, out: str, params) -> tuple[str, bytes, int]:
    """Mesh one frame here (whichever process this is) and say what splashsurf handed back.

    Returns a digest of splashsurf's own arrays (vertex order, positions,
    triangles, normals, velocities: before whitecap rounds anything), the mesh
    file's bytes, and the particle count.
    """
    import pysplashsurf

    from whitecap.surface.reconstruct import mesh_frame

    real, raw = pysplashsurf.reconstruction_pipeline, []

    def spy(*args, **kw):
        result = real(*args, **kw)
        raw.append(result[0])
        return result

    pysplashsurf.reconstruction_pipeline = spy
    try:
        stats = mesh_frame(src, out, params)
    finally:
        pysplashsurf.reconstruction_pipeline = real
    assert len(raw) == 1, "mesh_frame no longer calls pysplashsurf.reconstruction_pipeline: update this test"
    m, h = raw[0], hashlib.sha256()
    for a in [m.mesh.vertices, m.mesh.triangles] + [m.point_attributes[k] for k in sorted(m.point_attributes)]:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest(), Path(out).read_bytes(), stats["particles"]


def test_a_large_frame_is_the_same_bytes_whatever_meshes_it(tmp_path, worker_processes, monkeypatch):
    """The settings a cluster worker gets (pipeline.mesh plans it as one frame per machine) and those a
    local pool gets, in this process, in spawned pool workers and in a Dask worker process, several times:
    every mesh file is the same bytes, and so is what splashsurf itself returned, so the files agree
    because the computation does, not because the rounding happened to hide a difference this time."""
    import cloudpickle

    from whitecap.executor import LocalExecutor
    from whitecap.surface.driver import plan

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    # A site or user environment that asks rayon (splashsurf's thread pool) for several threads.
    monkeypatch.setenv("RAYON_NUM_THREADS", "4")
    seq = tmp_path / "seq"
    write_particles(seq / "fluid_00000.ply", dam_break_frame())
    src = str(seq / "fluid_00000.ply")
    on_worker = plan(src, radius=R, jobs=1).params  # what pipeline.mesh plans for a remote worker
    local = plan(src, radius=R, jobs=2).params  # ... and for a local pool of 2
    out = tmp_path / "out"
    out.mkdir()
    runs = {f"here-{k}": mesh_and_digest(src, str(out / f"here{k}.ply"), p)
            for k, p in enumerate([on_worker, local])}
    for r in LocalExecutor(2).map(mesh_and_digest, [(0, (src, str(out / "pool0.ply"), on_worker)),
                                                    (1, (src, str(out / "pool1.ply"), local))]):
        runs[f"pool-{r.index}"] = r.value
    with distributed.Client(worker_processes.scheduler_address, set_as_default=False) as client:
        runs["dask"] = client.submit(mesh_and_digest, src, str(out / "dask.ply"), on_worker, pure=False).result()
    assert min(n for _, _, n in runs.values()) > 30_000  # large enough to show splashsurf's thread noise
    digests = {k: d for k, (d, _, _) in runs.items()}
    assert len(set(digests.values())) == 1, f"splashsurf's output differs between runs: {digests}"
    files = {k: hashlib.sha256(b).hexdigest()[:12] for k, (_, b, _) in runs.items()}
    assert len(set(files.values())) == 1, f"mesh files differ: {files}"
