"""Input/output checks that catch realistic one-line bugs the other tests let through
(scripts/mutation_audit.py): a failed atomic write, the USD stage's frame rate, a DualSPHysics
floating body the XML does not declare, and a rigid fit on particles whose order changes."""

from __future__ import annotations

import errno
import shutil

import numpy as np
import pytest

from whitecap.io.atomic import atomic_path, write_bytes


# ---------------------------------------------------------------- atomic writes
def test_a_write_that_fails_half_way_leaves_the_old_file_and_no_temporary(tmp_path):
    """The failure happens inside the atomic write, after bytes went to the temporary file: the
    target keeps its old content, the temporary file is gone, and the error is the writer's."""
    target = tmp_path / "f.ply"
    write_bytes(target, b"old complete file")
    seen = []
    with pytest.raises(RuntimeError, match="writer broke"):
        with atomic_path(target) as tmp:
            seen.append(tmp)
            tmp.write_bytes(b"half a fi")
            assert tmp.parent == target.parent and tmp.is_file()
            raise RuntimeError("writer broke")
    assert seen and not seen[0].exists()
    assert target.read_bytes() == b"old complete file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.ply"]


def test_a_full_disk_inside_an_atomic_write_names_the_target_not_the_temporary(tmp_path):
    """An OSError from writing the temporary file (disk full) is raised naming the file the user
    asked for, with its errno; the temporary file is removed and the old file kept."""
    target = tmp_path / "frame.ply"
    write_bytes(target, b"old")
    with pytest.raises(OSError) as e:
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(target)
    assert target.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["frame.ply"]


def test_a_successful_atomic_write_replaces_the_file_and_leaves_nothing_else(tmp_path):
    target = tmp_path / "sub" / "run.json"
    write_bytes(target, b"one")
    write_bytes(target, b"two")
    assert target.read_bytes() == b"two" and [p.name for p in target.parent.iterdir()] == ["run.json"]


def test_a_full_disk_writing_npz_prints_no_zipfile_traceback(tmp_path):
    """A failed .npz write raises its one error and nothing more: no zip object left half open whose
    clean-up prints a second traceback later."""
    import gc
    import sys

    from whitecap import io

    from .test_io import cut_files_at, frame

    target = tmp_path / "checkpoint.npz"
    io.write(target, frame())
    late = []
    hook = sys.unraisablehook
    sys.unraisablehook = late.append
    try:
        with pytest.raises(OSError):
            with cut_files_at(target.stat().st_size // 2):
                io.write(target, frame(seed=1))
        gc.collect()
    finally:
        sys.unraisablehook = hook
    assert not late, [repr(u.exc_value) for u in late]


# ---------------------------------------------------------------- USD
def test_usd_stage_plays_at_the_runs_frame_rate(tiny_run, tmp_path):
    """Both time metadata of the stage are the run's frame rate (30 fps, not USD's default 24):
    timeCodesPerSecond maps the frame indices to seconds, framesPerSecond is what players use."""
    pxr = pytest.importorskip("pxr")
    from whitecap.io.run import RunInfo
    from whitecap.pipeline import export

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    written = export(run, to="usd", show_progress=False)
    stage = pxr.Usd.Stage.Open(str(written["usd"]))
    fps = RunInfo.load(run).frame_rate
    assert fps == 30.0
    assert stage.GetTimeCodesPerSecond() == fps
    assert stage.GetFramesPerSecond() == fps
    layer = stage.GetRootLayer()
    assert layer.HasFramesPerSecond() and layer.HasTimeCodesPerSecond()  # authored, not fallbacks


# ---------------------------------------------------------------- DualSPHysics cases
def _xml_without_bodies() -> str:
    """The synthetic case's XML, listing only the floor and the fluid: the floating cube (mk 50,
    Type 2) and the moving-type cube (mk 60, Type 1) are known from their particles' Type alone."""
    from .test_cases_dualsphysics import case_xml

    return case_xml("""
<fixed mkbound="0" mk="10" begin="0" count="1"/>
<fluid mkfluid="0" mk="1" begin="3" count="1"/>""")


def test_a_floating_body_the_xml_does_not_declare_is_fitted_from_its_type(tmp_path):
    """PartVTK Type 2 (floating) makes a shape a moving body even when the XML has no
    <floating> for it: its poses carry the rest particles onto every frame's within 0.1 dp."""
    from whitecap.cases import dualsphysics as D
    from whitecap.cases.rigid_fit import apply_pose

    from .test_cases_dualsphysics import DP, N_FRAMES, synthetic_case

    case = tmp_path / "case"
    s = synthetic_case(case)
    (case / "Case.xml").write_text(_xml_without_bodies())
    c = D.read_output(case)
    roles = {sh.name: sh.role for sh in c.shapes}
    assert roles["mk50"] == "body" and roles["mk60"] == "body", roles
    assert roles["mk10"] in ("obstacle", "container")
    cube = next(sh for sh in c.shapes if sh.name == "mk50")
    assert cube.poses is not None and len(cube.poses) == N_FRAMES
    for k, p in enumerate(cube.poses):
        err = np.linalg.norm(apply_pose(p, s["cube"]) - s["moved"][k], axis=1).max()
        assert err < 0.1 * DP, (k, err / DP)
    assert np.linalg.norm(s["moved"][-1].mean(0) - s["cube"].mean(0)) > 5 * DP  # control: it did move


def test_the_fit_matches_particles_by_idp_when_their_order_changes(tmp_path):
    """DualSPHysics reorders its particles between output frames; only Idp names a particle. With
    the rows of every PartAll file shuffled (Idp shuffled with them), the floating cube's fitted
    poses still carry its rest particles onto each frame's within 0.1 dp."""
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    from whitecap.cases import dualsphysics as D
    from whitecap.cases.rigid_fit import apply_pose

    from .test_cases_dualsphysics import DP, N_FRAMES, synthetic_case, write_part_vtk

    case = tmp_path / "case"
    s = synthetic_case(case)
    rng = np.random.default_rng(7)
    for k in range(N_FRAMES):
        path = case / f"PartAll_{k:04d}.vtk"
        r = vtk.vtkPolyDataReader()
        r.SetFileName(str(path))
        r.ReadAllScalarsOn()
        r.ReadAllVectorsOn()
        r.Update()
        ds = r.GetOutput()
        pos = vtk_to_numpy(ds.GetPoints().GetData())
        pd = ds.GetPointData()
        arrays = {pd.GetArrayName(i): vtk_to_numpy(pd.GetArray(i)) for i in range(pd.GetNumberOfArrays())}
        order = rng.permutation(len(pos)) if k > 0 else np.arange(len(pos))  # frame 0 keeps its order
        write_part_vtk(path, pos[order], {n: a[order] for n, a in arrays.items()})
    c = D.read_output(case)
    cube = next(sh for sh in c.shapes if sh.name == "mk50")
    for k, p in enumerate(cube.poses):
        err = np.linalg.norm(apply_pose(p, s["cube"]) - s["moved"][k], axis=1).max()
        assert err < 0.1 * DP, (k, err / DP)
