"""Rebuild this folder from the full SPlisHSPlasH sample in ../shared/data/splishsplash_rigid.

Keeps frames 1, 29 and 30 (the solver re-sorts its particles between 29 and 30),
40 fluid particles per frame (every 173rd id, rows kept in the file's own order),
the rigid-body BIN files of those frames with the meshes beside them, the OBJ
exports of those frames, the scene JSON and the tank model. Run from the
repository root: ``python tests/data/splishsplash_rigid/make_tiny.py``.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
SRC = ROOT.parent / "shared" / "data" / "splishsplash_rigid"
FRAMES = (1, 29, 30)
EVERY = 173

sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT))


def main() -> None:
    from tests.test_cases_splishsplash import write_splishsplash_vtk
    from whitecap.io.vtk_legacy import read_points

    for sub in ("vtk", "rigid_bodies", "obj", "Scenes", "models"):
        (HERE / sub).mkdir(exist_ok=True)
    for k in FRAMES:
        pos, a = read_points(SRC / "vtk" / f"ParticleData_Fluid_{k}.vtk")
        keep = a["id"].reshape(-1) % EVERY == 0
        write_splishsplash_vtk(HERE / "vtk" / f"ParticleData_Fluid_{k}.vtk", pos[keep], a["id"].reshape(-1)[keep],
                               a["velocity"].reshape(-1, 3)[keep], a["density"].reshape(-1)[keep])
        shutil.copyfile(SRC / "rigid_bodies" / f"rb_data_{k}.bin", HERE / "rigid_bodies" / f"rb_data_{k}.bin")
        shutil.copyfile(SRC / "obj" / f"rb_data_1_{k}.obj", HERE / "obj" / f"rb_data_1_{k}.obj")
    for name in ("UnitBox.obj", "sphere.obj"):
        shutil.copyfile(SRC / "rigid_bodies" / name, HERE / "rigid_bodies" / name)
    shutil.copyfile(SRC / "obj" / "rb_data_0_1.obj", HERE / "obj" / "rb_data_0_1.obj")
    shutil.copyfile(SRC / "Scenes" / "WC_RigidSample.json", HERE / "Scenes" / "WC_RigidSample.json")
    shutil.copyfile(SRC / "models" / "UnitBox.obj", HERE / "models" / "UnitBox.obj")


if __name__ == "__main__":
    main()
