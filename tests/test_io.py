"""Particle readers and writers: round trips, foreign formats, axis conversion, bad files."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from whitecap import io
from whitecap.cli import main
from whitecap.errors import InputError
from whitecap.io import ParticleFrame


def frame(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return io.ParticleFrame(rng.random((n, 3)), rng.normal(size=(n, 3)), np.arange(n) * 3,
                            density=rng.random(n) * 1000)


@pytest.mark.parametrize("ext", ["ply", "npz", "vtu"])
def test_round_trip(tmp_path, ext):
    f = frame()
    io.write(tmp_path / f"a.{ext}", f)
    g = io.read(tmp_path / f"a.{ext}")
    assert np.array_equal(g.positions, f.positions) and np.array_equal(g.velocities, f.velocities)
    assert np.array_equal(g.ids, f.ids) and np.allclose(g.density, f.density)


def test_splishsplash_style_vtk_with_y_up(tmp_path):
    # SPlisHSPlasH writes legacy binary VTK unstructured grids with 'velocity' and 'id', y up.
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    pos = np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]], np.float32)
    vel = np.array([[0.0, -1.0, 0.0], [2.0, 0.0, 0.0]], np.float32)
    grid = vtk.vtkUnstructuredGrid()
    pts = vtk.vtkPoints()
    pts.SetData(numpy_to_vtk(pos, deep=True))
    grid.SetPoints(pts)
    for name, arr in (("velocity", vel), ("id", np.array([4, 8], np.uint32))):
        a = numpy_to_vtk(arr, deep=True)
        a.SetName(name)
        grid.GetPointData().AddArray(a)
    w = vtk.vtkUnstructuredGridWriter()
    w.SetFileName(str(tmp_path / "ParticleData_Fluid_3.vtk"))
    w.SetInputData(grid)
    w.SetFileTypeToBinary()
    w.Write()
    f = io.read(tmp_path / "ParticleData_Fluid_3.vtk", up="y")
    assert f.ids.tolist() == [4, 8]
    # y up becomes z up: height 1.0 is now z, falling along -y is now falling along -z.
    assert f.positions[0].tolist() == pytest.approx([0.0, -2.0, 1.0])
    assert f.velocities[0].tolist() == pytest.approx([0.0, 0.0, -1.0])


def test_bad_files_are_named(tmp_path, capsys):
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all")
    with pytest.raises(InputError, match="junk.ply"):
        io.read(tmp_path / "junk.ply")
    with pytest.raises(InputError, match="missing.ply: file not found"):
        io.read(tmp_path / "missing.ply")
    with pytest.raises(InputError, match="no reader"):
        (tmp_path / "x.abc").write_text("1")
        io.read(tmp_path / "x.abc")
    # NaN positions stop the foam stage with the file named.
    f = frame()
    f.positions[3] = np.nan
    (tmp_path / "seq").mkdir()
    io.write(tmp_path / "seq" / "p_0000.ply", f)
    code = main(["foam", str(tmp_path / "seq"), "--out", str(tmp_path / "o"), "--dt", "0.02", "--radius", "0.01"])
    err = capsys.readouterr().err
    assert code != 0 and "p_0000.ply" in err and "NaN" in err


def cut_files_at(limit: int):
    """While active, this process cannot write a regular file past ``limit`` bytes: the write fails
    with EFBIG as a write on a full disk fails with ENOSPC, inside whatever library is writing
    (RLIMIT_FSIZE, with SIGXFSZ ignored). Nothing else may write files meanwhile."""
    import contextlib
    import signal

    resource = pytest.importorskip("resource", reason="needs POSIX file size limits")

    @contextlib.contextmanager
    def cm():
        old = resource.getrlimit(resource.RLIMIT_FSIZE)
        handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, old[1]))
        try:
            yield
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, old)
            signal.signal(signal.SIGXFSZ, handler)

    return cm()


@pytest.mark.parametrize("ext", ["ply", "npz", "vtu"])
def test_writes_are_atomic(tmp_path, ext):
    """A write that fails half way through its file (the disk fills up after some bytes went out)
    leaves the earlier file as it was and no temporary file, and the error names the file asked
    for. The failure happens inside the format's writer, in the middle of the atomic write."""
    import errno

    f = frame()
    target = tmp_path / f"f.{ext}"
    io.write(target, f)
    before = target.read_bytes()
    with pytest.raises(OSError) as e:
        with cut_files_at(len(before) // 2):
            io.write(target, frame(seed=1))
    assert e.value.errno == errno.EFBIG and e.value.filename == str(target)
    assert target.read_bytes() == before  # the earlier file survives a failed write
    assert [p.name for p in tmp_path.iterdir()] == [target.name]  # and no temporary is left


def test_splishsplash_partio_bgeo_with_y_up(tmp_path):
    # SPlisHSPlasH's partio exporter: gzip-compressed BGEO V5 with 'id' (INT), 'velocity' and 'density', y up.
    from .conftest import write_partio_bgeo

    pos = np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]], np.float32)
    vel = np.array([[0.0, -1.0, 0.0], [2.0, 0.0, 0.0]], np.float32)
    p = tmp_path / "ParticleData_Fluid_7.bgeo"
    write_partio_bgeo(p, pos, {"id": np.array([4, 70000], np.int32), "velocity": vel, "density": [998.0, 1001.5]})
    f = io.read(p, up="y")
    assert f.ids.tolist() == [4, 70000]
    assert f.density.tolist() == [998.0, 1001.5]
    assert f.positions[1].tolist() == pytest.approx([3.0, -5.0, 4.0])
    assert f.velocities[0].tolist() == pytest.approx([0.0, 0.0, -1.0])
    # z up (the default) leaves the axes alone.
    assert io.read(p).positions[1].tolist() == pytest.approx([3.0, 4.0, 5.0])


def test_bad_bgeo_files_are_named(tmp_path):
    from .conftest import write_partio_bgeo

    pos = np.zeros((4, 3))
    write_partio_bgeo(tmp_path / "novel_1.bgeo", pos, {"id": np.arange(4, dtype=np.int32)})
    with pytest.raises(InputError, match=r"novel_1.bgeo: missing attribute 'velocity'"):
        io.read(tmp_path / "novel_1.bgeo")
    write_partio_bgeo(tmp_path / "plain_1.bgeo", pos, {"velocity": pos}, compress=False)
    with pytest.raises(InputError, match=r"plain_1.bgeo: not a gzip-compressed BGEO"):
        io.read(tmp_path / "plain_1.bgeo")
    import gzip

    whole = gzip.decompress((tmp_path / "novel_1.bgeo").read_bytes())
    (tmp_path / "cut_1.bgeo").write_bytes(gzip.compress(whole[:-20]))
    with pytest.raises(InputError, match=r"cut_1.bgeo: not a readable BGEO"):
        io.read(tmp_path / "cut_1.bgeo")


def test_two_fluids_in_one_folder_ask_for_a_glob(tmp_path):
    # SPlisHSPlasH writes one file per fluid model and frame into the same folder.
    from whitecap.io.sequence import find_sequence

    for name in ("Fluid", "Fluid2"):
        for i in (1, 2):
            io.write(tmp_path / f"ParticleData_{name}_{i}.npz", frame(seed=i))
    with pytest.raises(InputError, match=r"frame 1 also given by .*pass a glob such as '.*ParticleData_Fluid_\*\.npz'"):
        find_sequence(tmp_path)
    hint = str(tmp_path / "ParticleData_Fluid_*.npz")
    found = [(i, p.name) for i, p in find_sequence(hint)]
    assert found == [(1, "ParticleData_Fluid_1.npz"), (2, "ParticleData_Fluid_2.npz")]


# The output contract (README, "simulate" and "foam"): binary little-endian PLY, these properties in
# this order with these types. Readers cast, so only the file itself shows a wrong type.
FLUID_PLY = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("vx", "<f4"), ("vy", "<f4"), ("vz", "<f4"),
             ("density", "<f4"), ("id", "<u4")]
DIFFUSE_PLY = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("vx", "<f4"), ("vy", "<f4"), ("vz", "<f4"),
               ("type", "|u1"), ("lifetime", "<f4"), ("radius", "<f4"), ("id", "<u4")]


def test_run_files_have_the_contract_types(tiny_run, tmp_path):
    from plyfile import PlyData

    from whitecap.io.mesh import SurfaceMesh, write_mesh
    from whitecap.io.run import RunInfo

    info = RunInfo.load(tiny_run)
    for stage, layout in (("fluid", FLUID_PLY), ("diffuse", DIFFUSE_PLY)):
        files = info.files(stage)
        assert files, stage
        for _, rel in files:
            ply = PlyData.read(str(tiny_run / rel))
            assert not ply.text and ply.byte_order == "<", rel
            assert [e.name for e in ply.elements] == ["vertex"], rel
            assert ply["vertex"].data.dtype.descr == layout, rel
    # Surface meshes: vertex x y z nx ny nz vx vy vz float32, triangles as uchar count + int indices.
    m = SurfaceMesh(np.eye(3), [[0, 1, 2]], np.eye(3), {"velocity": np.ones((3, 3))})
    write_mesh(tmp_path / "m.ply", m)
    ply = PlyData.read(str(tmp_path / "m.ply"))
    assert not ply.text and ply.byte_order == "<"
    assert ply["vertex"].data.dtype.descr == [(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz", "vx", "vy", "vz")]
    (prop,) = ply["face"].properties
    assert (prop.name, prop.len_dtype, prop.val_dtype) == ("vertex_indices", "u1", "i4")


def test_one_registry_tells_particles_from_meshes(tmp_path):
    from whitecap.io.mesh import SurfaceMesh
    from whitecap.io.registry import MESH, PARTICLES, format_for, formats
    from whitecap.io.sequence import find_sequence

    # .ply is both; the kind asked for decides which reader runs.
    assert format_for("a.ply").kind == PARTICLES and format_for("a.ply", kind=MESH).kind == MESH
    assert {"ply", "obj"} <= set(formats(MESH)) and "obj" not in formats(PARTICLES)
    m = SurfaceMesh(np.eye(3), [[0, 1, 2]], arrays={"velocity": np.ones((3, 3))})
    for ext in ("ply", "obj"):
        io.write_mesh(tmp_path / f"m.{ext}", m)
        back = io.read_mesh(tmp_path / f"m.{ext}")
        assert isinstance(back, SurfaceMesh) and np.array_equal(back.faces, m.faces)
    with pytest.raises(InputError, match="m.obj: no reader for this file type"):
        io.read(tmp_path / "m.obj")  # a mesh is not a particle frame
    io.write(tmp_path / "x.vtu", frame())
    with pytest.raises(InputError, match="x.vtu: no reader.*mesh formats known: obj, ply"):
        io.read_mesh(tmp_path / "x.vtu")
    # A folder of OBJ meshes is not a particle sequence.
    (tmp_path / "seq").mkdir()
    io.write_mesh(tmp_path / "seq" / "m_0001.obj", m)
    with pytest.raises(InputError):
        find_sequence(tmp_path / "seq")


def test_find_array_matches_aliases_case_insensitively_in_order():
    from whitecap.io.registry import DENSITY_NAMES, VELOCITY_NAMES

    assert io.find_array({"Vel": 1, "v": 2}, VELOCITY_NAMES) == "Vel"  # DualSPHysics' name first
    assert io.find_array({"VELOCITY": 1, "V": 2}, VELOCITY_NAMES) == "VELOCITY"
    assert io.find_array({"Rho": 1, "Rhop": 2}, DENSITY_NAMES) == "Rhop"
    assert io.find_array({"speed": 1}, VELOCITY_NAMES) is None


def test_mesh_check_finite_names_the_file_and_the_bad_vertex_count(tmp_path):
    from whitecap.io.mesh import SurfaceMesh

    verts = np.eye(3)
    io.write_mesh(tmp_path / "m.ply", SurfaceMesh(verts, [[0, 1, 2]]))
    io.read_mesh(tmp_path / "m.ply").check_finite()  # finite: no error
    verts[1, 2] = np.nan
    io.write_mesh(tmp_path / "m.ply", SurfaceMesh(verts, [[0, 1, 2]]))
    with pytest.raises(InputError) as e:
        io.read_mesh(tmp_path / "m.ply").check_finite()
    assert str(e.value) == f"{tmp_path / 'm.ply'}: vertices: 1 are NaN or infinite"


def _plyfile_reference(frame) -> bytes:
    """A particle PLY as plyfile writes it from one structured array filled column by column (write_ply's
    layout: x y z vx vy vz [density] [arrays…] id), to hold write_ply's packing to the same bytes."""
    import io as _io

    from plyfile import PlyData, PlyElement

    n = len(frame)
    vel = frame.velocities if frame.velocities is not None else np.zeros((n, 3), np.float32)
    cols = [("x", frame.positions[:, 0]), ("y", frame.positions[:, 1]), ("z", frame.positions[:, 2]),
            ("vx", vel[:, 0]), ("vy", vel[:, 1]), ("vz", vel[:, 2])]
    if frame.density is not None:
        cols.append(("density", frame.density))
    cols += list(frame.arrays.items()) + [("id", frame.ids)]
    kinds = {"float32": "f4", "uint32": "u4", "uint8": "u1", "int32": "i4"}
    data = np.empty(n, [(k, kinds.get(np.dtype(a.dtype).name, "f4")) for k, a in cols])
    for k, a in cols:
        data[k] = a
    buf = _io.BytesIO()
    PlyData([PlyElement.describe(data, "vertex")], byte_order="<").write(buf)
    return buf.getvalue()


@pytest.mark.parametrize("threads", [1, 3])
def test_ply_packing_writes_the_same_bytes_for_every_layout(tmp_path, monkeypatch, threads):
    """write_ply packs vectors three components at a time into a buffer kept between files: the bytes are
    those of the plain column-by-column layout, for diffuse, fluid, velocity-less, strided, float64 and
    empty frames, and a smaller file after a larger one holds no bytes of it; also where a large file's rows
    are packed and written in parts by several threads (here parts of 4 kB, three threads)."""
    from whitecap.io import ply
    from whitecap.io.ply import write_ply

    monkeypatch.setattr(ply, "WRITE_THREADS", threads)
    monkeypatch.setattr(ply, "PART_BYTES", 4096)
    if threads > 1:
        assert len(ply._parts(1000, 37)) == 3 and ply._parts(10, 37) == [(0, 10)]

    rng = np.random.default_rng(3)
    n = 1000
    x = rng.random((n, 3), np.float32)
    ids = np.arange(n, dtype=np.uint32)
    frames = [
        ParticleFrame(x, x * 2, ids, arrays={"type": rng.integers(0, 3, n).astype(np.uint8),
                                             "lifetime": rng.random(n).astype(np.float32),
                                             "radius": np.full(n, 0.01, np.float32)}),
        ParticleFrame(x, -x, ids, density=rng.random(n).astype(np.float32)),
        ParticleFrame(x[:10], None, ids[:10]),
        ParticleFrame(np.asfortranarray(x), x[:, ::-1], ids),  # neither C-contiguous
        ParticleFrame(x.astype(np.float64), x, ids),  # cast to float32 as before
        ParticleFrame(np.zeros((0, 3), np.float32), None, np.zeros(0, np.uint32)),
    ]
    for k, f in enumerate(frames):
        write_ply(tmp_path / f"{k}.ply", f)
        assert (tmp_path / f"{k}.ply").read_bytes() == _plyfile_reference(f), k


@pytest.mark.parametrize("threads", [1, 3])
def test_a_frame_of_records_is_written_as_its_records_and_packed_once_an_array_is_replaced(tmp_path, monkeypatch,
                                                                                           threads):
    """ParticleFrame.from_records: the frame's arrays are views of the records (nothing copied) and write_ply writes
    the records as they are, without packing, the bytes of the same frame made of arrays, in one write where
    arrays go in parts (parts are for packing in parallel); a value written through an array since is in the file
    (the same memory). An array put in a field's place is written, packed, not the records it no longer is; so are
    records of another layout, and a frame made from a records frame (dataclasses.replace) does not carry them."""
    import dataclasses

    from whitecap.io import ply
    from whitecap.io.ply import record_dtype, write_ply

    monkeypatch.setattr(ply, "WRITE_THREADS", threads)
    monkeypatch.setattr(ply, "PART_BYTES", 4096)
    rng = np.random.default_rng(5)
    n = 1000
    arrays = ParticleFrame(rng.random((n, 3), np.float32), rng.random((n, 3), np.float32),
                           rng.permutation(n).astype(np.uint32),
                           arrays={"type": rng.integers(0, 3, n).astype(np.uint8),
                                   "lifetime": rng.random(n).astype(np.float32),
                                   "radius": np.full(n, 0.01, np.float32)})
    rec = np.empty(n, record_dtype(arrays))
    for names, a in ply._groups(arrays):
        for c, k in enumerate(names):
            rec[k] = a[:, c] if len(names) > 1 else a
    frame = ParticleFrame.from_records(rec, time=0.5)
    assert frame.records is rec and frame.time == 0.5 and list(frame.arrays) == ["type", "lifetime", "radius"]
    for mine, theirs in ((frame.positions, arrays.positions), (frame.velocities, arrays.velocities),
                         (frame.ids, arrays.ids), *((frame.arrays[k], arrays.arrays[k]) for k in arrays.arrays)):
        assert np.shares_memory(mine, rec) and np.array_equal(mine, theirs)
    packed = []
    pack = ply._pack
    monkeypatch.setattr(ply, "_pack", lambda *a: (packed.append(a[2:]), pack(*a)))
    write_ply(tmp_path / "arrays.ply", arrays)
    assert packed
    packed.clear()
    pwrites = []
    pwrite = ply.os.pwrite
    monkeypatch.setattr(ply.os, "pwrite", lambda *a: (pwrites.append(a[2]), pwrite(*a))[1])
    write_ply(tmp_path / "records.ply", frame)
    assert not packed and (tmp_path / "records.ply").read_bytes() == (tmp_path / "arrays.ply").read_bytes()
    assert not pwrites  # one write, not parts
    write_ply(tmp_path / "arrays_again.ply", arrays)
    assert bool(pwrites) == (threads > 1)  # the arrays: packed and written in parts where threads may share them
    packed.clear()
    frame.positions[7] = (1.0, 2.0, 3.0)  # through the view: in the records
    write_ply(tmp_path / "through.ply", frame)
    assert not packed and np.array_equal(io.read(tmp_path / "through.ply").positions[7], [1.0, 2.0, 3.0])
    frame.arrays["lifetime"] = frame.arrays["lifetime"] + 1.0  # another array: packed, and its values written
    write_ply(tmp_path / "replaced.ply", frame)
    assert packed
    assert np.array_equal(io.read(tmp_path / "replaced.ply").arrays["lifetime"], arrays.arrays["lifetime"] + 1.0)
    assert dataclasses.replace(frame).records is None
    other = ParticleFrame.from_records(rec[["x", "y", "z", "id"]])  # fields of the records, another layout
    packed.clear()
    write_ply(tmp_path / "other.ply", other)
    assert packed and np.array_equal(io.read(tmp_path / "other.ply").ids, arrays.ids)
    with pytest.raises(ValueError, match="x y z"):
        ParticleFrame.from_records(np.zeros(3, [("x", "<f4"), ("z", "<f4"), ("y", "<f4")]))


def test_a_full_disk_while_threads_write_a_ply_names_the_file_and_leaves_nothing(tmp_path, monkeypatch):
    """A large PLY written in parts by several threads (os.pwrite) on a full disk: one OSError naming the file asked
    for, as the one-thread write gives, no temporary file left and the earlier file kept whole."""
    import errno

    from whitecap.io import ply
    from whitecap.io.ply import write_ply

    monkeypatch.setattr(ply, "WRITE_THREADS", 3)
    monkeypatch.setattr(ply, "PART_BYTES", 4096)
    n = 1000
    x = np.random.default_rng(1).random((n, 3), np.float32)
    frame = ParticleFrame(x, x, np.arange(n, dtype=np.uint32))
    target = tmp_path / "fluid_00001.ply"
    write_ply(target, frame)
    before = target.read_bytes()
    calls = []
    real = os.pwrite

    def full(fd, data, offset):
        calls.append(offset)
        if len(calls) > 2:  # the header and a part get through, then the disk is full
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd, data, offset)

    monkeypatch.setattr(ply.os, "pwrite", full)
    with pytest.raises(OSError) as err:
        write_ply(target, ParticleFrame(x * 2, x, np.arange(n, dtype=np.uint32)))
    assert err.value.filename == str(target) and "No space left" in str(err.value)
    assert len(calls) >= 3 and target.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == [target.name]


def test_a_frame_read_as_written_is_copied_and_any_other_written(tmp_path, monkeypatch):
    """io.write_copy: a frame read from a file and not changed, written elsewhere (the fluid frames `whitecap foam
    --out` copies along). A PLY as whitecap writes it, read z up, is copied (the kernel's copy: the writer is not
    called); read y up, with a property whitecap writes otherwise (an int32 id), with bytes after its rows, or
    from another format, the frame is written. The file is the one write gives, every way. A full disk during the
    copy names the target and leaves the earlier file whole, and no temporary file."""
    import dataclasses
    import errno
    import shutil

    from plyfile import PlyData, PlyElement

    from whitecap.io import ply, registry, write_copy

    rng = np.random.default_rng(2)
    n = 500
    frame = ParticleFrame(rng.random((n, 3), np.float32), rng.random((n, 3), np.float32),
                          rng.permutation(n).astype(np.uint32), rng.random(n).astype(np.float32))
    own = tmp_path / "own.ply"
    io.write(own, frame)
    rec = np.empty(n, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("vx", "<f4"), ("vy", "<f4"), ("vz", "<f4"),
                       ("id", "<i4")])
    for k, a in (("x", frame.positions[:, 0]), ("y", frame.positions[:, 1]), ("z", frame.positions[:, 2]),
                 ("vx", frame.velocities[:, 0]), ("vy", frame.velocities[:, 1]), ("vz", frame.velocities[:, 2]),
                 ("id", frame.ids)):
        rec[k] = a
    int_ids = tmp_path / "int_ids.ply"
    PlyData([PlyElement.describe(rec, "vertex")], byte_order="<").write(str(int_ids))
    trailing = tmp_path / "trailing.ply"
    trailing.write_bytes(own.read_bytes() + b"\0" * 8)
    npz = tmp_path / "own.npz"
    io.write(npz, frame)
    written = []
    real = ply.write_ply
    key = ("particles", "ply")
    monkeypatch.setitem(registry.FORMATS, key, dataclasses.replace(registry.FORMATS[key],
                                                                   writer=lambda p, f: (written.append(p), real(p, f))))
    for src, options, copied in ((own, {}, True), (own, {"up": "z"}, True), (own, {"up": "y"}, False),
                                 (int_ids, {}, False), (trailing, {}, False), (npz, {}, False)):
        fr = io.read(src, **options)
        written.clear()
        write_copy(tmp_path / "out" / "copy.ply", fr, src, **options)
        io.write(tmp_path / "out" / "written.ply", fr)
        assert (written == [tmp_path / "out" / "written.ply"]) == copied, (src.name, options)
        assert (tmp_path / "out" / "copy.ply").read_bytes() == (tmp_path / "out" / "written.ply").read_bytes()
    target = tmp_path / "out" / "copy.ply"
    before = target.read_bytes()

    def full(a, b):
        Path(b).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(shutil, "copyfile", full)
    with pytest.raises(OSError) as err:
        write_copy(target, io.read(own), own)
    assert err.value.filename == str(target) and target.read_bytes() == before
    assert sorted(p.name for p in target.parent.iterdir()) == ["copy.ply", "written.ply"]


@pytest.mark.parametrize("layout", ["little", "big", "ascii", "float64", "reordered", "padded"])
def test_ply_vectors_read_alike_from_every_layout(tmp_path, layout):
    """read_ply copies x y z (and vx vy vz) as one 12-byte item a row where they are little-endian float32 side
    by side, and stacks the columns otherwise: the same (N, 3) float32 positions and velocities from a file
    written either way, big-endian, ASCII, in float64, with the components in another order or apart."""
    from plyfile import PlyData, PlyElement

    rng = np.random.default_rng(8)
    n = 257
    x = rng.normal(0, 1, (n, 3)).astype(np.float32)
    v = rng.normal(0, 3, (n, 3)).astype(np.float32)
    f4 = "f8" if layout == "float64" else "f4"
    names = ["x", "y", "z", "vx", "vy", "vz"]
    if layout == "reordered":
        names = ["y", "x", "z", "vz", "vy", "vx"]
    if layout == "padded":
        names = ["x", "y", "pad", "z", "vx", "vy", "vz"]
    cols = {"x": x[:, 0], "y": x[:, 1], "z": x[:, 2], "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2],
            "pad": np.zeros(n, np.float32)}
    data = np.empty(n, [(k, f4) for k in names] + [("id", "u4")])
    for k in names:
        data[k] = cols[k]
    data["id"] = np.arange(n)
    path = tmp_path / "frame.ply"
    PlyData([PlyElement.describe(data, "vertex")], text=layout == "ascii",
            byte_order=">" if layout == "big" else "<").write(str(path))
    fr = io.read(path)
    assert fr.positions.dtype == np.float32 and fr.positions.shape == (n, 3) and fr.positions.flags.c_contiguous
    assert (fr.positions == x).all() and (fr.velocities == v).all()
    assert (fr.ids == np.arange(n)).all()


def test_a_process_pool_is_kept_by_name_and_made_anew_in_a_forked_child(monkeypatch):
    """io.threads.process_pool (the PLY writer's parts, the GPU read-back thread): one pool per name and process,
    kept; a child (another pid) gets its own and drops the parent's, whose threads do not run there."""
    from whitecap.io import threads

    monkeypatch.setattr(threads, "_POOLS", {})
    a = threads.process_pool("whitecap-test", 2)
    assert threads.process_pool("whitecap-test", 2) is a and threads.process_pool("whitecap-other", 1) is not a
    assert a.submit(lambda: 7).result() == 7
    parent = os.getpid()
    monkeypatch.setattr(threads.os, "getpid", lambda: parent + 1)
    b = threads.process_pool("whitecap-test", 2)
    assert b is not a and list(threads._POOLS) == [(parent + 1, "whitecap-test")]
    a.shutdown()
    b.shutdown()
