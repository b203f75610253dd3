"""Per-frame stages on a Dask cluster (issue 17): a LocalCluster of 2 worker processes.

The frames made on the cluster are the bytes a serial local run makes; a
worker killed in the middle of a frame costs nothing but a retry; an address
where no scheduler answers fails in one line; the [cluster] section becomes
the batch job script dask-jobqueue submits.
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
import tomllib
from pathlib import Path

import pytest

distributed = pytest.importorskip("distributed")

import tomli_w  # noqa: E402
from plyfile import PlyData  # noqa: E402

from whitecap import pipeline  # noqa: E402
from whitecap.cli import main  # noqa: E402
from whitecap.config import Cluster  # noqa: E402
from whitecap.executor import NO_DASHBOARD  # noqa: E402
from whitecap.io.run import RunInfo  # noqa: E402

FRAMES = 3  # frames 0, 1, 2 of the tiny run


@pytest.fixture(scope="module")
def cluster():
    """Two worker processes, one thread each (the frame functions bring their own threads)."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=50, scheduler_kwargs=NO_DASHBOARD) as c:
        yield c


def _small_run(tiny_run: Path, dest: Path, **scene_extra) -> Path:
    """A copy of the tiny run with a small preview (so Cycles is quick) and extra scene sections."""
    shutil.copytree(tiny_run, dest)
    scene = tomllib.loads((dest / "scene.toml").read_text())
    scene.setdefault("render", {}).update(preview_resolution=[64, 48], preview_samples=2)
    for k, v in scene_extra.items():
        scene.setdefault(k, {}).update(v)
    (dest / "scene.toml").write_text(tomli_w.dumps(scene))
    return dest


def _files(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(d.iterdir()) if p.is_file()}


@pytest.fixture(scope="module")
def serial_run(tiny_run, tmp_path_factory) -> Path:
    """The reference: meshed with --jobs 1 and rendered by one local Blender worker, no Dask."""
    run = _small_run(tiny_run, tmp_path_factory.mktemp("serial") / "run")
    pipeline.mesh(run, jobs=1, show_progress=False)
    pipeline.render(run, quality="preview", frames=f"0:{FRAMES}", movie=False, show_progress=False)
    pipeline.export(run, show_progress=False)
    return run


def _tree(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_cluster_frames_are_the_bytes_of_a_serial_run(serial_run, tiny_run, tmp_path, cluster):
    run = _small_run(tiny_run, tmp_path / "run")
    pipeline.mesh(run, cluster=cluster.scheduler_address, show_progress=False)
    meshes = _files(run / "mesh")
    assert len(meshes) == len(RunInfo.load(run).files("fluid")) and meshes == _files(serial_run / "mesh")
    r = pipeline.render(run, quality="preview", frames=f"0:{FRAMES}", movie=False, show_progress=False,
                        cluster=cluster.scheduler_address)
    pngs = {k: v for k, v in _files(run / "render").items() if k.endswith(".png")}
    assert sorted(pngs) == [f"frame_{i:05d}.png" for i in range(FRAMES)]
    assert pngs == {k: v for k, v in _files(serial_run / "render").items() if k.endswith(".png")}
    # Each worker built its Blender scene once: 3 frames, at most one Blender process per worker.
    assert 1 <= r["blender_processes"] <= 2
    # The client recorded every frame as made from this simulation, so a rerun skips them all.
    info = RunInfo.load(run)
    assert [i for i, _ in info.files("render")] == list(range(FRAMES))
    assert (run / "render" / "scene.blend").is_file()
    # export: every series file and collection the same bytes as the serial export's
    pipeline.export(run, cluster=cluster.scheduler_address, show_progress=False)
    exported = _tree(run / "export")
    assert "fluid.pvd" in exported and "mesh/mesh_00002.vtp" in exported and exported == _tree(serial_run / "export")


class KillOnce(distributed.WorkerPlugin):
    """Test plugin: the first mesh written on the cluster is cut off half-way and its worker killed (SIGKILL)."""

    def __init__(self, marker: str):
        self.marker = marker

    def setup(self, worker=None):
        import importlib

        from whitecap.io.atomic import atomic_path

        rec = importlib.import_module("whitecap.surface.reconstruct")

        real, marker = rec.write_mesh, self.marker

        def write_mesh(path, surface):
            try:
                fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                return real(path, surface)
            os.write(fd, str(os.getpid()).encode())
            os.close(fd)
            with atomic_path(path) as tmp:
                real(tmp, surface)
                data = tmp.read_bytes()
                tmp.write_bytes(data[: len(data) // 2])  # half a file, then the worker dies
                os.kill(os.getpid(), signal.SIGKILL)

        rec.write_mesh = write_mesh


def test_a_worker_killed_mid_frame_is_retried_and_leaves_no_partial_file(serial_run, tiny_run, tmp_path, cluster,
                                                                          capsys):
    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    run = _small_run(tiny_run, tmp_path / "run")
    marker = tmp_path / "killed"
    with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
        client.register_plugin(KillOnce(str(marker)), name="kill-once")
        try:
            stats = pipeline.mesh(run, cluster=cluster.scheduler_address, show_progress=True)
        finally:
            client.unregister_worker_plugin("kill-once")
            client.wait_for_workers(2)
        alive = set(client.run(os.getpid).values())
    assert marker.is_file(), "no worker was killed: the test tested nothing"
    assert int(marker.read_text()) not in alive  # the worker that took the frame really died (and was replaced)
    made = sorted(s["index"] for s in stats if not s["skipped"])
    assert made == [i for i, _ in RunInfo.load(run).files("fluid")]
    files = sorted((run / "mesh").iterdir())
    assert [p.name for p in files] == sorted(_files(serial_run / "mesh")), "a temporary or partial file is left"
    for p in files:
        assert len(PlyData.read(str(p))["face"]) > 0
    assert _files(run / "mesh") == _files(serial_run / "mesh")
    # The summary: every frame counted once, on the workers that made it (the killed one made none).
    err = capsys.readouterr().err
    nframes = len(made)
    assert f"mesh: {nframes} frames on " in err
    per_worker = [int(ln.split(": ")[1].split()[0]) for ln in err.splitlines() if ln.startswith("  tcp://")]
    assert sum(per_worker) == nframes and 1 <= len(per_worker) <= 2
    # A rerun skips every finished frame.
    again = pipeline.mesh(run, cluster=cluster.scheduler_address, show_progress=False)
    assert all(s["skipped"] for s in again)


def test_a_scheduler_that_does_not_answer_is_a_one_line_error(tiny_run, tmp_path, capsys):
    run = _small_run(tiny_run, tmp_path / "run", cluster={"connect_timeout": 1.0})
    assert main(["mesh", str(run), "--cluster", "tcp://127.0.0.1:9"]) != 0
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("error: --cluster tcp://127.0.0.1:9: no Dask scheduler answered")
    assert "within 1 s" in err
    assert not (run / "mesh").exists() or not any((run / "mesh").iterdir())


def test_a_frame_that_fails_by_itself_is_named_and_the_others_are_kept(tiny_run, tmp_path, cluster, capsys):
    run = _small_run(tiny_run, tmp_path / "run")
    info = RunInfo.load(run)
    bad = dict(info.files("fluid"))[2]
    (run / bad).write_bytes((run / bad).read_bytes()[:300])  # a truncated input file
    assert main(["mesh", str(run), "--cluster", cluster.scheduler_address]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: mesh: 1 of 4 frames failed on the cluster (frame 2: ")
    assert bad.split("/")[-1] in err[-1] and "rerun to retry them" in err[-1]
    assert "  frame 2 failed: " in "\n".join(err)  # named in the summary too
    # the other frames are made and recorded, so a rerun does only frame 2
    assert [i for i, _ in RunInfo.load(run).files("mesh")] == [0, 1, 3]
    assert sorted(p.name for p in (run / "mesh").iterdir()) == ["fluid_00000.ply", "fluid_00001.ply", "fluid_00003.ply"]


class Elsewhere(distributed.WorkerPlugin):
    """Test plugin: the worker sees the client's paths under another root, as if the run were on a local disk."""

    def setup(self, worker=None):
        import whitecap.executor as ex

        real = ex._probe
        ex._probe = lambda path, token: real("/nonexistent-mount" + path, token)

    def teardown(self, worker=None):
        import importlib

        import whitecap.executor as ex

        importlib.reload(ex)


@pytest.mark.parametrize("joined_later", [False, True])
def test_workers_that_cannot_see_the_run_directory_fail_at_once(tiny_run, tmp_path, cluster, capsys, monkeypatch,
                                                                joined_later):
    """Checked before the first frame; a worker that joins after that check fails its first frame,
    which stops the run."""
    import cloudpickle

    from whitecap.executor import DaskExecutor

    if joined_later:
        monkeypatch.setattr(DaskExecutor, "check_shared", lambda self: None)

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    run = _small_run(tiny_run, tmp_path / "run")
    with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
        client.register_plugin(Elsewhere(), name="elsewhere")
        try:
            rc = main(["mesh", str(run), "--cluster", cluster.scheduler_address])
        finally:
            client.unregister_worker_plugin("elsewhere")
    err = capsys.readouterr().err.strip()
    assert rc != 0 and "\n" not in err
    if joined_later:
        assert err.startswith(f"error: {run.resolve()}: Dask worker tcp://") and "cannot see the run directory" in err
    else:
        assert err.startswith(f"error: {run.resolve()}: 2 of 2 Dask workers cannot see the run directory")
    assert not (run / "mesh").exists()
    assert not [p for p in run.iterdir() if p.name.startswith(".whitecap-probe")]


def test_slurm_section_becomes_the_job_script():
    from whitecap.executor import batch_cluster

    cfg = Cluster(jobs=50, cores=16, memory="64GB", walltime="04:00:00", queue="render", account="proj42",
                  job_extra=["--gres=gpu:1"], setup=["module load python/3.11"])
    c = batch_cluster("slurm", cfg)
    try:
        script = c.job_script()
    finally:
        c.close()
    lines = script.splitlines()
    for want in ("#SBATCH -p render", "#SBATCH -A proj42", "#SBATCH --cpus-per-task=16", "#SBATCH -t 04:00:00",
                 "#SBATCH --gres=gpu:1", "module load python/3.11"):
        assert want in lines, (want, script)
    assert "#SBATCH --mem=60G" in lines  # 64 GB = 59.6 GiB, which dask-jobqueue rounds to whole GiB
    worker = next(ln for ln in lines if "dask_worker" in ln)
    assert worker.endswith("--nthreads 1"), worker  # one frame at a time; the frame uses the job's 16 cores


def test_pbs_section_becomes_the_job_script():
    from whitecap.executor import batch_cluster

    c = batch_cluster("pbs", Cluster(cores=8, memory="32GB", walltime="02:30:00", queue="workq"))
    try:
        lines = c.job_script().splitlines()
    finally:
        c.close()
    for want in ("#PBS -q workq", "#PBS -l select=1:ncpus=8:mem=30GB", "#PBS -l walltime=02:30:00"):
        assert want in lines, (want, lines)


def test_slurm_without_sbatch_is_a_one_line_error(tiny_run, tmp_path, capsys, monkeypatch):
    run = _small_run(tiny_run, tmp_path / "run")
    monkeypatch.setenv("PATH", str(tmp_path))  # no sbatch here
    assert main(["mesh", str(run), "--cluster", "slurm"]) != 0
    err = capsys.readouterr().err.strip()
    assert err == ("error: --cluster slurm: 'sbatch' is not on the PATH; run whitecap where slurm jobs are submitted "
                   "from (a login node)")
    assert not (run / "mesh").exists()
