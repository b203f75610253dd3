"""`whitecap export`: ParaView series (.pvd + .vtp, or PLY + .series) read back with vtk."""

from __future__ import annotations

import json
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

from whitecap import io as wio
from whitecap.cli import main
from whitecap.io.frame import ParticleFrame
from whitecap.io.mesh import read_mesh
from whitecap.io.run import RunInfo, frame_name
from whitecap.pipeline import export, mesh


def synthetic_diffuse(run: Path, seed: int = 0) -> dict[int, ParticleFrame]:
    """Diffuse PLYs following the run-directory contract, recorded in run.json."""
    rng = np.random.default_rng(seed)
    info = RunInfo.load(run)
    frames = {}
    for i, _ in info.files("fluid"):
        n = 0 if i == 0 else 50 + 10 * i  # frame 0: no diffuse particles yet
        f = ParticleFrame(
            positions=rng.uniform(0, 0.2, (n, 3)),
            velocities=rng.normal(0, 1, (n, 3)),
            ids=np.arange(n, dtype=np.uint32) + 1000,
            arrays={
                "type": rng.integers(0, 3, n).astype(np.uint8),
                "lifetime": rng.uniform(0, 2, n).astype(np.float32),
                "radius": np.full(n, 0.002, np.float32),
            },
        )
        wio.write(run / frame_name("diffuse", i), f)
        info.set_file(i, "diffuse", frame_name("diffuse", i))
        frames[i] = f
    info.save(run)
    return frames


def read_vtp(path: Path):
    r = vtkXMLPolyDataReader()
    r.SetFileName(str(path))
    r.Update()
    poly = r.GetOutput()
    pd = poly.GetPointData()
    arrays = {pd.GetArrayName(k): vtk_to_numpy(pd.GetArray(k)) for k in range(pd.GetNumberOfArrays())}
    pts = vtk_to_numpy(poly.GetPoints().GetData()) if poly.GetPoints() else np.zeros((0, 3))
    tris = vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3)
    return pts, arrays, tris, poly


def read_pvd(path: Path) -> list[tuple[float, str]]:
    root = ET.parse(path).getroot()
    assert root.get("type") == "Collection"
    return [(float(d.get("timestep")), d.get("file")) for d in root.iter("DataSet")]


@pytest.fixture(scope="module")
def meshed_run(tiny_run, tmp_path_factory) -> tuple[Path, dict[int, ParticleFrame]]:
    run = tmp_path_factory.mktemp("export") / "run"
    shutil.copytree(tiny_run, run)
    mesh(run, jobs=1, show_progress=False)
    return run, synthetic_diffuse(run)


def test_vtk_series_read_back_with_arrays_and_times(meshed_run, tmp_path):
    run, diffuse = meshed_run
    out = tmp_path / "vtk"
    written = export(run, to="vtk", out=out, split_types=True, show_progress=False)
    assert set(written) == {"fluid", "diffuse", "diffuse_spray", "diffuse_foam", "diffuse_bubble", "mesh"}
    info = RunInfo.load(run)
    times = {f.index: f.time for f in info.frames}

    # Every collection lists the frames with their simulated time.
    for name, pvd in written.items():
        entries = read_pvd(pvd)
        assert [t for t, _ in entries] == pytest.approx([times[i] for i in sorted(times)])
        assert all((pvd.parent / rel).is_file() for _, rel in entries)
    assert times[3] == pytest.approx(3 / info.frame_rate)

    # Fluid particles: positions and velocity match the source frame.
    src = wio.read(run / "fluid" / "fluid_00002.ply")
    pts, arrays, _, poly = read_vtp(out / read_pvd(written["fluid"])[2][1])
    np.testing.assert_array_equal(pts, src.positions)
    np.testing.assert_array_equal(arrays["velocity"], src.velocities)
    np.testing.assert_array_equal(arrays["id"], src.ids)
    assert poly.GetNumberOfVerts() == len(src)

    # Diffuse particles carry type, lifetime and velocity, and the split series partition them.
    d = diffuse[1]
    pts, arrays, _, _ = read_vtp(out / "diffuse" / "diffuse_00001.vtp")
    np.testing.assert_array_equal(arrays["type"], d.arrays["type"])
    np.testing.assert_array_equal(arrays["lifetime"], d.arrays["lifetime"])
    np.testing.assert_array_equal(arrays["velocity"], d.velocities)
    assert arrays["type"].dtype == np.uint8
    total = 0
    for code, label in enumerate(("spray", "foam", "bubble")):
        sp, sa, _, _ = read_vtp(out / f"diffuse_{label}" / f"diffuse_{label}_00001.vtp")
        keep = d.arrays["type"] == code
        assert (sa["type"] == code).all() and len(sp) == keep.sum()
        np.testing.assert_array_equal(sp, d.positions[keep])
        total += len(sp)
    assert total == len(d)
    # A frame without diffuse particles is an empty, readable dataset.
    for name in ("diffuse", "diffuse_bubble"):
        pts, arrays, _, _ = read_vtp(out / name / f"{name}_00000.vtp")
        assert len(pts) == 0 and len(arrays.get("type", [])) == 0

    # Meshes: the same triangles, normals and velocities as mesh/fluid_NNNNN.ply.
    m = read_mesh(run / "mesh" / "fluid_00003.ply")
    pts, arrays, tris, poly = read_vtp(out / "mesh" / "mesh_00003.vtp")
    np.testing.assert_array_equal(pts, m.vertices)
    np.testing.assert_array_equal(tris, m.faces)
    np.testing.assert_array_equal(arrays["Normals"], m.normals)
    np.testing.assert_array_equal(arrays["velocity"], m.arrays["velocity"])
    assert poly.GetNumberOfPolys() == len(m.faces) > 0


def test_ply_series_and_cli_default_location(meshed_run, capsys):
    run, diffuse = meshed_run
    assert main(["export", str(run), "--to", "ply"]) == 0
    out = run / "export"
    series = json.loads((out / "diffuse.series").read_text())
    assert series["file-series-version"] == "1.0"
    assert [f["name"] for f in series["files"]] == [f"diffuse/diffuse_{i:05d}.ply" for i in range(4)]
    back = wio.read(out / "diffuse" / "diffuse_00002.ply")
    np.testing.assert_array_equal(back.arrays["type"], diffuse[2].arrays["type"])
    m = read_mesh(out / "mesh" / "mesh_00001.ply")
    assert len(m.faces) == len(read_mesh(run / "mesh" / "fluid_00001.ply").faces)
    assert not (out / "diffuse_foam.series").exists()  # only with --split-types


def test_export_errors(tmp_path, tiny_run, capsys):
    assert main(["export", str(tmp_path / "missing")]) == 2
    assert "missing: no such run directory" in capsys.readouterr().err
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    (run / "fluid" / "fluid_00001.ply").write_bytes(b"not a ply")
    assert main(["export", str(run)]) == 2
    err = capsys.readouterr().err
    assert "fluid_00001.ply" in err and err.count("\n") == 1
