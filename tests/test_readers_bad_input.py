"""Bad input to the particle readers and the case readers (issue 30, items 9 and 10, and
folder names holding brackets).

- A file cut short is refused by every reader with one line that names the file, says
  ``truncated`` and names the array (VTK read such files back with made-up velocities).
- ``import``/``mesh``/``foam`` stop with that line (exit code non-zero), and ``import``
  checks every frame before it writes anything.
- A DualSPHysics folder with several case XML files is refused: the XML decides the frame
  rate, so taking the first by name gave 20 fps for a 50 fps case.
- Paths that exist are never glob patterns: a folder named ``run[1]`` is that folder.

The cut files are made here from tests/data or whitecap's own writers.
"""

from __future__ import annotations

import gzip
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from whitecap import io
from whitecap.cli import main
from whitecap.errors import InputError

from .conftest import DATA, write_partio_bgeo

DSPH = DATA / "dualsphysics"
SPLISH = DATA / "splishsplash_rigid"
PART = DSPH / "PartFluid_0012.vtk"  # binary legacy VTK, 9600 particles: POINTS, VERTICES, Vel, FIELD Rhop


def one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg, msg
    return msg


def cut(src: Path, dst: Path, at: int | float) -> Path:
    """``dst``: the first bytes of ``src`` (``at`` bytes, or that fraction of the file)."""
    data = Path(src).read_bytes()
    n = at if isinstance(at, int) else int(len(data) * at)
    dst.write_bytes(data[:n])
    return dst


def ascii_copy(src: Path, dst: Path) -> Path:
    """The same data set as an ASCII legacy VTK file (VTK's own writer)."""
    import vtk

    r = vtk.vtkGenericDataObjectReader()
    r.SetFileName(str(src))
    r.ReadAllScalarsOn()
    r.ReadAllVectorsOn()
    r.ReadAllFieldsOn()
    r.Update()
    w = vtk.vtkGenericDataObjectWriter()
    w.SetFileName(str(dst))
    w.SetInputData(r.GetOutput())
    w.SetFileTypeToASCII()
    assert w.Write() == 1
    return dst


def inside_block(path: Path, header: bytes, fraction: float = 0.5, nbytes: int | None = None) -> int:
    """A byte offset ``fraction`` of the way through the data block after the line starting with
    ``header``: ``nbytes`` long (binary), or up to the next header line (ASCII)."""
    data = path.read_bytes()
    start = data.index(b"\n", data.index(b"\n" + header) + 1) + 1
    if data[start:].startswith(b"LOOKUP_TABLE"):
        start = data.index(b"\n", start) + 1
    if nbytes is None:
        nxt = re.compile(rb"\n[A-Za-z]").search(data, start)
        nbytes = (nxt.start() if nxt else len(data)) - start
    return start + int(nbytes * fraction)


def frame(n=200, seed=0) -> io.ParticleFrame:
    rng = np.random.default_rng(seed)
    return io.ParticleFrame(rng.random((n, 3)), rng.normal(size=(n, 3)), np.arange(n), density=rng.random(n) * 1000)


# ============================================================================ legacy VTK
@pytest.mark.parametrize("form", ["binary", "ascii"])
def test_vtk_cut_inside_vel_is_truncated_not_read_with_wrong_velocities(tmp_path, form):
    src = PART if form == "binary" else ascii_copy(PART, tmp_path / "full.vtk")
    full = io.read(src)
    assert len(full) == 9600 and np.isfinite(full.velocities).all()
    at = inside_block(PART, b"SCALARS Vel", nbytes=9600 * 12) if form == "binary" else inside_block(src, b"SCALARS Vel")
    bad = cut(src, tmp_path / "PartFluid_0013.vtk", at)
    with pytest.raises(InputError) as err:
        io.read(bad)
    msg = one_line(err)
    assert re.fullmatch(rf"{re.escape(str(bad))}: truncated: array 'Vel' declares 28800 values, "
                        r"the file holds (\d+)", msg), msg
    held = int(msg.rsplit(" ", 1)[1])
    assert 0 < held < 28800


def test_vtk_cut_inside_the_points_says_truncated_not_missing_arrays(tmp_path):
    bad = cut(PART, tmp_path / "PartFluid_0012.vtk", 0.3)  # inside POINTS: VTK then finds no arrays at all
    with pytest.raises(InputError) as err:
        io.read(bad)
    msg = one_line(err)
    assert msg.startswith(f"{bad}: truncated: block 'POINTS' declares 28800 values"), msg
    assert "missing" not in msg


@pytest.mark.parametrize("where", ["field array", "header line", "last value", "after DATASET"])
def test_vtk_cut_at_other_places_is_truncated(tmp_path, where):
    """Cuts in the FIELD block (binary), inside a header line (binary), in the last value of an
    ASCII file (no end of line after it) and right after the DATASET line."""
    src, at = PART, None
    data = PART.read_bytes()
    if where == "field array":
        at = inside_block(PART, b"Rhop 1 9600 float", 0.9, nbytes=9600 * 4)
    elif where == "header line":
        at = data.index(b"\nSCALARS Vel") + len(b"\nSCALARS V")
    elif where == "last value":
        src = ascii_copy(PART, tmp_path / "full.vtk")
        at = len(src.read_bytes().rstrip()) - 2  # "... 999.9" -> "... 999"
    else:
        at = data.index(b"\nPOINTS") + 1
    bad = cut(src, tmp_path / "f_0001.vtk", at)
    with pytest.raises(InputError, match=rf"^{re.escape(str(bad))}: truncated: ") as err:
        io.read(bad)
    one_line(err)


def test_complete_vtk_files_with_metadata_nan_and_new_cells_read_without_complaint(tmp_path):
    """No false alarm: VTK 5.1 ASCII with OFFSETS/CONNECTIVITY cells, component-name METADATA
    after an array and NaN values at the very end reads back whole."""
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    pos = np.arange(30, dtype=np.float32).reshape(10, 3)
    poly = vtk.vtkPolyData()
    pts = vtk.vtkPoints()
    pts.SetData(numpy_to_vtk(pos, deep=True))
    poly.SetPoints(pts)
    verts = vtk.vtkCellArray()
    for i in range(10):
        verts.InsertNextCell(1, [i])
    poly.SetVerts(verts)
    vel = numpy_to_vtk(np.ones((10, 3), np.float32), deep=True)
    vel.SetName("Vel")
    for k, c in enumerate("xyz"):
        vel.SetComponentName(k, f"v{c}")
    poly.GetPointData().AddArray(vel)
    rho = np.full(10, 1000.0, np.float32)
    rho[-3:] = np.nan
    a = numpy_to_vtk(rho, deep=True)
    a.SetName("Rhop")
    poly.GetPointData().AddArray(a)
    for kind in ("ASCII", "Binary"):
        w = vtk.vtkPolyDataWriter()
        w.SetFileName(str(tmp_path / f"p_{kind}.vtk"))
        w.SetInputData(poly)
        getattr(w, f"SetFileTypeTo{kind}")()
        assert w.Write() == 1
        text = (tmp_path / f"p_{kind}.vtk").read_bytes()
        assert b"OFFSETS" in text and b"METADATA" in text
        f = io.read(tmp_path / f"p_{kind}.vtk")
        assert np.array_equal(f.positions, pos) and np.isnan(f.density[-3:]).all()
        io.registry.check(tmp_path / f"p_{kind}.vtk")


# ============================================================================ every particle reader
def _write(fmt: str, path: Path) -> Path:
    f = frame()
    if fmt == "bgeo":
        write_partio_bgeo(path, f.positions, {"id": f.ids.astype(np.int32), "velocity": f.velocities,
                                              "density": f.density})
    elif fmt == "ply-ascii":
        from plyfile import PlyData

        binary = path.parent / f"binary_{path.name}"
        io.write(binary, f)
        ply = PlyData.read(str(binary), mmap=False)
        ply.text = True
        ply.write(str(path))
    elif fmt == "vtk":
        shutil.copy(PART, path)
    else:
        io.write(path, f)
    return path


FORMATS = {"vtk": ".vtk", "ply": ".ply", "ply-ascii": ".ply", "npz": ".npz", "vtu": ".vtu", "bgeo": ".bgeo"}


@pytest.mark.parametrize("fmt", list(FORMATS))
@pytest.mark.parametrize("fraction", [0.4, 0.7, 0.97])
def test_every_particle_reader_says_truncated_in_one_line(tmp_path, fmt, fraction):
    full = _write(fmt, tmp_path / f"full_0001{FORMATS[fmt]}")
    assert len(io.read(full)) in (200, 9600)
    bad = cut(full, tmp_path / f"cut_0001{FORMATS[fmt]}", fraction)
    with pytest.raises(InputError) as err:  # SystemExit (meshio) would escape this
        io.read(bad)
    msg = one_line(err)
    assert str(bad) in msg and "truncated" in msg, msg


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_the_cheap_check_agrees_with_the_reader(tmp_path, fmt):
    """io.registry.check (headers and sizes, used to check a whole case before writing) passes
    a whole file and refuses one cut anywhere past its first bytes, as the reader does."""
    from whitecap.io.registry import check

    full = _write(fmt, tmp_path / f"full_0001{FORMATS[fmt]}")
    check(full)
    data = full.read_bytes()
    for at in np.linspace(0.05, 0.995, 23):
        bad = cut(full, tmp_path / f"cut_0001{FORMATS[fmt]}", int(len(data) * at))
        with pytest.raises(InputError, match="truncated"):
            check(bad)


def test_bgeo_cut_inside_its_gzip_stream_names_the_points(tmp_path):
    full = _write("bgeo", tmp_path / "ParticleData_Fluid_1.bgeo")
    body = gzip.decompress(full.read_bytes())
    (tmp_path / "ParticleData_Fluid_2.bgeo").write_bytes(gzip.compress(body[:len(body) // 2]))
    with pytest.raises(InputError, match=r"ParticleData_Fluid_2\.bgeo: .*truncated: the point data declares 200 "
                                         r"points, the file holds 9\d"):
        io.read(tmp_path / "ParticleData_Fluid_2.bgeo")


def test_vtp_cut_short_is_truncated_not_empty(tmp_path):
    from whitecap.io.vtk_xml import read_vtp, write_vtp

    f = frame()
    write_vtp(tmp_path / "a.vtp", f.positions, {"velocity": f.velocities})
    bad = cut(tmp_path / "a.vtp", tmp_path / "b.vtp", 0.6)
    with pytest.raises(InputError, match=rf"{re.escape(str(bad))}: truncated: .*array '\w+'") as err:
        read_vtp(bad)
    one_line(err)


# ============================================================================ the commands
def test_mesh_exits_nonzero_on_a_truncated_vtk(tmp_path, capsys):
    seq = tmp_path / "seq"
    seq.mkdir()
    cut(PART, seq / "PartFluid_0012.vtk", inside_block(PART, b"SCALARS Vel", nbytes=9600 * 12))
    assert main(["mesh", str(seq), "--radius", "0.01", "--out", str(tmp_path / "mesh")]) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and len(err.splitlines()) == 1, err
    assert "PartFluid_0012.vtk: truncated: array 'Vel'" in err


def test_foam_on_a_cut_binary_file_is_one_line_not_a_traceback(tmp_path, capsys):
    seq = tmp_path / "seq"
    seq.mkdir()
    for k in (12, 13):
        shutil.copy(DSPH / f"PartFluid_{k:04d}.vtk", seq)
    cut(DSPH / "PartFluid_0014.vtk", seq / "PartFluid_0014.vtk", 0.7)
    code = main(["foam", str(seq), "--out", str(tmp_path / "o"), "--dt", "0.02", "--radius", "0.01"])
    err = capsys.readouterr().err.strip()
    assert code != 0 and "Traceback" not in err
    assert "PartFluid_0014.vtk: truncated" in err.splitlines()[-1]


def _splishsplash_copy(tmp_path: Path) -> Path:
    d = tmp_path / "case"
    shutil.copytree(SPLISH, d, ignore=shutil.ignore_patterns("*.py", "__pycache__"))
    return d


def test_splishsplash_import_with_a_frame_cut_at_70_percent_fails_and_writes_nothing(tmp_path, capsys):
    d = _splishsplash_copy(tmp_path)
    f29 = d / "vtk" / "ParticleData_Fluid_29.vtk"
    cut(f29, f29, 0.7)
    out = tmp_path / "run"
    assert main(["import", str(d), "--out", str(out)]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "ParticleData_Fluid_29.vtk: truncated: array 'velocity'" in err, err
    assert not out.exists()  # checked before anything is written


def test_dualsphysics_import_with_a_cut_frame_fails_and_writes_nothing(tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(DSPH, case)
    cut(DSPH / "PartFluid_0014.vtk", case / "PartFluid_0014.vtk", 0.7)
    out = tmp_path / "run"
    assert main(["import", str(case), "--out", str(out)]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "PartFluid_0014.vtk: truncated" in err, err
    assert not out.exists()


def test_splishsplash_bin_cut_short_says_truncated(tmp_path):
    from whitecap.cases import splishsplash

    d = _splishsplash_copy(tmp_path)
    cut(d / "rigid_bodies" / "rb_data_30.bin", d / "rigid_bodies" / "rb_data_30.bin", 90)
    with pytest.raises(InputError, match=r"rb_data_30\.bin: pose block: 90 bytes, 96 expected .*truncated") as err:
        splishsplash.read_output(d)
    one_line(err)


# ============================================================================ several case XML files
def _two_xml_case(tmp_path: Path) -> Path:
    """The DualSPHysics sample (TimeOut 0.02 s: 50 fps) with a second case XML of TimeOut 0.05 s
    that sorts first by name."""
    case = tmp_path / "case"
    shutil.copytree(DSPH, case)
    text = (case / "CaseDambreak.xml").read_text()
    other = re.sub(r'(key="TimeOut" value=")0\.02"', r'\g<1>0.05"', text)
    assert other != text
    (case / "Aaa_Def.xml").write_text(other)
    return case


def test_import_refuses_two_case_xml_files_and_takes_the_one_named(tmp_path, capsys):
    from whitecap.io.run import RunInfo

    case = _two_xml_case(tmp_path)
    assert main(["import", str(case), "--out", str(tmp_path / "run")]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert str(case) in err and "Aaa_Def.xml" in err and "CaseDambreak.xml" in err and "--xml" in err
    assert not (tmp_path / "run").exists()
    assert main(["import", str(case), "--out", str(tmp_path / "run"), "--xml", str(case / "CaseDambreak.xml")]) == 0
    assert RunInfo.load(tmp_path / "run").frame_rate == pytest.approx(50.0)


def test_find_case_xml(tmp_path):
    from whitecap.cases.dualsphysics_xml import find_case_xml

    assert find_case_xml(tmp_path) is None
    (tmp_path / "B.xml").write_text("<case/>")
    assert find_case_xml(tmp_path) == tmp_path / "B.xml"
    (tmp_path / "A.xml").write_text("<case/>")
    with pytest.raises(InputError, match=rf"^{re.escape(str(tmp_path))}: 2 case XML files \(A\.xml, B\.xml\); "
                                         r"choose the one that was run with --case FILE$"):
        find_case_xml(tmp_path, option="--case")
    assert find_case_xml(tmp_path, tmp_path / "B.xml") == tmp_path / "B.xml"
    with pytest.raises(InputError, match="C.xml: case XML not found"):
        find_case_xml(tmp_path, tmp_path / "C.xml")


# ============================================================================ brackets in folder names
def test_a_folder_named_with_brackets_is_read_literally(tmp_path):
    from whitecap.io.sequence import find_sequence

    d = tmp_path / "run[1]"
    d.mkdir()
    (tmp_path / "run1").mkdir()  # what the pattern run[1] would match
    io.write(tmp_path / "run1" / "decoy_0000.npz", frame(seed=9))
    for k in range(3):
        io.write(d / f"fluid_{k:04d}.npz", frame(seed=k))
    names = [(i, p.name) for i, p in find_sequence(d)]
    assert names == [(0, "fluid_0000.npz"), (1, "fluid_0001.npz"), (2, "fluid_0002.npz")]
    assert [(i, p.name) for i, p in find_sequence(d / "fluid_*.npz")] == names
    assert [i for i, _ in find_sequence(d / "fluid_000[02].npz")] == [0, 2]  # a real pattern still works
    assert find_sequence(d / "fluid_0001.npz") == [(1, d / "fluid_0001.npz")]


def test_a_dualsphysics_case_in_a_folder_named_with_brackets_imports(tmp_path):
    from whitecap.cases import dualsphysics

    case = tmp_path / "dam[break]"
    shutil.copytree(DSPH, case)
    c = dualsphysics.read_output(case)
    assert [i for i, _ in c.fluid] == [12, 13, 14] and c.frame_dt == pytest.approx(0.02)
