"""The domain of a run made from another solver's frames encloses the flow over all frames, by one
rule shared by `foam` and `import` (issue 30, item 14), printed and recorded in run.json."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from whitecap.cli import main
from whitecap.io import ParticleFrame, read, write
from whitecap.io.run import DOMAIN_RULE, RunInfo, flow_domain, sequence_bounds

R = 0.01


def travelling_block(folder, frames=4, step=0.3):
    """A 16 cm block of water that travels 30 cm along x each frame (a dam-break front runs this far)."""
    folder.mkdir(parents=True)
    g = (np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) * 2 * R
    paths = []
    for k in range(frames):
        pos = (g + [step * k, 0.0, 0.0]).astype(np.float32)
        vel = np.tile(np.float32([step * 30, 0.0, 0.0]), (len(g), 1))
        paths.append(folder / f"frame_{k:04d}.ply")
        write(paths[-1], ParticleFrame(pos, vel, np.arange(len(g), dtype=np.uint32)))
    return paths


def inside(points, domain) -> bool:
    return bool(((points >= domain["lower"]) & (points <= domain["upper"])).all())


def test_foam_domain_holds_every_frame_of_a_travelling_flow(tmp_path, capsys):
    paths = travelling_block(tmp_path / "seq")
    out = tmp_path / "F"
    assert main(["foam", str(tmp_path / "seq"), "--out", str(out), "--dt", "0.033", "--radius", str(R)]) == 0
    info = RunInfo.load(out)
    from whitecap.io import read

    for p in paths:
        assert inside(read(p).positions, info.domain), p
    assert info.domain == flow_domain(sequence_bounds(paths), R)
    assert info.extra["domain_rule"] == DOMAIN_RULE
    assert "domain: (" in capsys.readouterr().err
    # The top has room for spray: as high again as the water.
    lo, hi = np.array(info.domain["lower"]), np.array(info.domain["upper"])
    assert hi[2] - lo[2] >= 2 * 0.16


def test_import_uses_the_same_rule_over_all_frames(tmp_path):
    from whitecap.cases import read_case

    from .test_cases_dualsphysics import synthetic_case

    synthetic_case(tmp_path / "case", frames=3)
    out = tmp_path / "run"
    assert main(["import", str(tmp_path / "case"), "--out", str(out)]) == 0
    case = read_case(tmp_path / "case")
    boxes = [sequence_bounds([p for _, p in case.fluid])]
    boxes += [(np.min(s.vertices, 0), np.max(s.vertices, 0)) for s in case.shapes]
    want = flow_domain((np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)), case.particle_radius)
    info = RunInfo.load(out)
    assert np.allclose(info.domain["lower"], want["lower"]) and np.allclose(info.domain["upper"], want["upper"])
    assert info.extra["domain_rule"] == DOMAIN_RULE


def test_foam_refuses_to_guess_between_two_case_xmls(tmp_path, capsys):
    import shutil

    from .conftest import DATA

    src = tmp_path / "dsph"
    shutil.copytree(DATA / "dualsphysics", src)
    xml = (src / "CaseDambreak.xml").read_text()
    (src / "Another.xml").write_text(xml.replace('key="TimeOut" value="0.02"', 'key="TimeOut" value="0.05"'))
    assert main(["foam", str(src), "--out", str(tmp_path / "F")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "2 case XML files" in err and "--case" in err, err
    assert not (tmp_path / "F").exists()
    assert main(["foam", str(src), "--out", str(tmp_path / "F"), "--case", str(src / "CaseDambreak.xml")]) == 0
    assert RunInfo.load(tmp_path / "F").extra["case"] == str(src / "CaseDambreak.xml")


def test_a_kinetic_energy_minimum_no_particle_reaches_is_named_with_the_speed_it_needs(tmp_path, capsys):
    from .conftest import DATA
    from .test_diffuse import full_ini

    ini = tmp_path / "job.ini"
    # 5 J per particle of the case's mass: far beyond what a dam break's particles carry
    ini.write_text(full_ini(inp=str(DATA / "dualsphysics"), out=str(tmp_path / "o"),
                            xml=str(DATA / "dualsphysics" / "CaseDambreak.xml"), custom="no",
                            MinKineticEnergyThreshold=5.0, MaxKineticEnergyThreshold=50.0))
    assert main(["foam", "--params", str(ini)]) == 0
    err = " ".join(capsys.readouterr().err.split())
    assert "no diffuse particles were generated: no fluid particle reached the kinetic-energy minimum" in err
    assert "[FOAMPARAMETERS] MinKineticEnergyThreshold" in err and "auto" not in err.split("generated:")[1]
    info = RunInfo.load(tmp_path / "o")
    need = float(err.split("needs a speed of ")[1].split(" m/s")[0])
    assert need == pytest.approx((2 * 5.0 / info.particle_mass) ** 0.5, rel=1e-2)
    fastest = float(err.split("the fastest moved at ")[1].split(" m/s")[0])
    assert 0.5 < fastest < need


def test_foam_arch_cuda_without_a_gpu_is_one_line(tiny_run, tmp_path, capsys):
    from whitecap.sim.runtime import cuda_available

    if cuda_available():
        pytest.skip("a CUDA device is present")
    import shutil

    shutil.copytree(tiny_run, tmp_path / "R")
    assert main(["foam", str(tmp_path / "R"), "--arch", "cuda"]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--arch cuda: no CUDA device found" in err, err
    assert main(["foam", str(tmp_path / "R"), "--arch", "auto"]) == 0  # falls back to the CPU


def test_foam_of_a_foreign_sequence_is_import_then_foam_of_the_run(tmp_path):
    """`foam SEQ --out RUN` imports SEQ as a bare sequence, then makes foam over RUN: the same
    run.json and the same diffuse bytes as `import SEQ --out RUN` followed by `foam RUN`."""
    from .test_diffuse import _gentle_then_violent

    pattern = _gentle_then_violent(tmp_path / "seq", frames=6)
    opts = ["--dt", str(1 / 30), "--radius", "0.01"]
    assert main(["foam", pattern, "--out", str(tmp_path / "A"), *opts]) == 0
    assert main(["import", pattern, "--out", str(tmp_path / "B"), *opts]) == 0
    assert RunInfo.load(tmp_path / "B").extra["solver"] == "sequence"
    assert main(["foam", str(tmp_path / "B"), "--dt", str(1 / 30)]) == 0
    a, b = RunInfo.load(tmp_path / "A"), RunInfo.load(tmp_path / "B")
    assert a.simulation == b.simulation and a.domain == b.domain and a.extra == b.extra
    made = sorted(p.name for p in (tmp_path / "A" / "diffuse").iterdir())
    assert len(made) == 8 and "resume.npz" in made
    assert sum((tmp_path / "A" / "diffuse" / n).stat().st_size for n in made) > 7 * 1000
    for name in made:
        assert (tmp_path / "A" / "diffuse" / name).read_bytes() == (tmp_path / "B" / "diffuse" / name).read_bytes()
    fluid = sorted(p.name for p in (tmp_path / "B" / "fluid").iterdir())
    assert len(fluid) == 6 and sorted(p.name for p in (tmp_path / "A" / "fluid").iterdir()) == fluid
    for name in fluid:
        assert (tmp_path / "A" / "fluid" / name).read_bytes() == (tmp_path / "B" / "fluid" / name).read_bytes()
    assert [f.model_dump() for f in a.frames] == [f.model_dump() for f in b.frames]


def test_foam_of_a_foreign_sequence_reads_each_frame_from_the_sequence_and_never_its_own_copies(tmp_path,
                                                                                                 monkeypatch):
    """The import writes no frame of its own: the pass reads the sequence's files (each once, but the frames the
    look-ahead sampled, once more) and writes them into the run, which it never reads back."""
    from whitecap.cases import run_dir
    from whitecap.diffuse import driver

    from .test_diffuse import _gentle_then_violent

    pattern = _gentle_then_violent(tmp_path / "seq", frames=6)
    imported, passed = [], []
    monkeypatch.setattr(run_dir, "read", lambda path, **kw: imported.append(path))
    real = driver.read
    monkeypatch.setattr(driver, "read", lambda path, **kw: passed.append(Path(path)) or real(path, **kw))
    assert main(["foam", pattern, "--out", str(tmp_path / "A"), "--dt", str(1 / 30), "--radius", "0.01"]) == 0
    assert imported == []
    sources = sorted((tmp_path / "seq").glob("f_*.ply"))
    assert set(passed) == set(sources)
    assert sorted(passed).count(sources[1]) == 1 and len(passed) < 2 * len(sources)
    assert len(RunInfo.load(tmp_path / "A").files("fluid")) == 6


@pytest.mark.parametrize("fault", ["nan", "no velocities"])
def test_foam_of_a_foreign_sequence_with_a_bad_frame_leaves_no_run(tmp_path, capsys, monkeypatch, fault):
    """Frame 4 of 6 bad: a one-line error naming the file, exit status 2, and no run behind. Velocities that are
    not finite are met by the pass over the frames' bounds, before any foam is made; a frame without velocities
    (which an import takes) half-way through the foam pass, whose frames before it were written into the run by
    then: it is removed, as after an import that fails."""
    from whitecap.diffuse import driver
    from whitecap.diffuse.generator import FoamGenerator

    from .test_diffuse import _gentle_then_violent

    pattern = _gentle_then_violent(tmp_path / "seq", frames=6)
    bad = tmp_path / "seq" / "f_0004.ply"
    fr = read(bad)
    if fault == "nan":
        fr.velocities[7] = np.nan
        write(bad, fr)
    else:  # positions alone (whitecap's own writer fills in zero velocities)
        from plyfile import PlyData, PlyElement

        rows = np.empty(len(fr), [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
        rows["x"], rows["y"], rows["z"] = fr.positions.T
        PlyData([PlyElement.describe(rows, "vertex")]).write(str(bad))
    made, step = [], FoamGenerator.step
    monkeypatch.setattr(FoamGenerator, "step", lambda self, fluid, index, dt, **kw: made.append(index) or step(
        self, fluid, index, dt, **kw))
    written = []
    real = driver.write
    monkeypatch.setattr(driver, "write", lambda path, frame: written.append(path) or real(path, frame))
    assert main(["foam", pattern, "--out", str(tmp_path / "A"), "--dt", str(1 / 30), "--radius", "0.01"]) == 2
    err = capsys.readouterr().err.strip().splitlines()  # the progress before it, then the error
    assert [e for e in err if "error" in e] == err[-1:] and str(bad) in err[-1], err
    assert ("NaN" in err[-1]) == (fault == "nan") and "velocit" in err[-1]
    assert made == ([] if fault == "nan" else [0, 1, 2, 3])
    assert (len(written) > 0) == (fault != "nan")
    assert not (tmp_path / "A").exists()


def test_a_stopped_foam_of_a_foreign_sequence_resumes_into_the_same_run(tmp_path, monkeypatch, capsys):
    """Stopped at frame 3 (Ctrl-C), the run lists frames 0-2 with their fluid copies; run again, it goes on from
    frame 3 and ends with the files of an unstopped pass."""
    from .test_diffuse import _gentle_then_violent, _stop_foam_at

    pattern = _gentle_then_violent(tmp_path / "seq", frames=6)
    opts = ["--dt", str(1 / 30), "--radius", "0.01"]
    assert main(["foam", pattern, "--out", str(tmp_path / "whole"), *opts]) == 0
    _stop_foam_at(monkeypatch, 3)
    assert main(["foam", pattern, "--out", str(tmp_path / "A"), *opts]) != 0
    info = RunInfo.load(tmp_path / "A")
    assert [i for i, _ in info.files("fluid")] == [0, 1, 2] and [i for i, _ in info.files("diffuse")] == [0, 1, 2]
    monkeypatch.undo()
    capsys.readouterr()
    assert main(["foam", pattern, "--out", str(tmp_path / "A"), *opts]) == 0
    said = capsys.readouterr()
    assert "resuming at frame 3" in said.err and "for 3 of 6 frames" in said.out
    for kind in ("fluid", "diffuse"):
        names = sorted(p.name for p in (tmp_path / "whole" / kind).iterdir())
        assert sorted(p.name for p in (tmp_path / "A" / kind).iterdir()) == names
        for name in names:
            assert (tmp_path / "A" / kind / name).read_bytes() == (tmp_path / "whole" / kind / name).read_bytes()


def test_import_refuses_an_option_of_another_kind_of_input(tmp_path, capsys):
    travelling_block(tmp_path / "seq", frames=2)
    assert main(["import", str(tmp_path / "seq"), "--out", str(tmp_path / "R"), "--dt", "0.03", "--radius", "0.01",
                 "--scene", "s.json"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--scene is for SPlisHSPlasH cases; this is a bare sequence" in err, err
    assert not (tmp_path / "R").exists()
