"""Imports run one way: the bottom (config, io and their helpers), then the stages in pipeline
order, then pipeline, then cli. A module may import its own floor or a lower one, never a higher."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "whitecap"

# Floors, lowest first. Within "stages", the pipeline order: a stage may import an earlier one
# (the viewer draws the solver's and the foam's frames) but never a later one.
FLOORS = [
    {"errors", "timing", "progress", "resources", "workers", "__init__"},
    {"io", "config", "executor", "stage_frames"},
    {"geometry", "terrain"},
    {"cases"},   # import: foreign cases into run directories
    {"sim"},     # simulate
    {"diffuse"},  # foam
    {"view"},
    {"surface"},  # mesh
    {"blender"},  # the bpy layer shared by render and the Blender add-on
    {"render"},
    {"export"},  # export: series and scenes (the scene's camera and looks are the renderer's)
    {"pipeline"},
    {"cli"},
]
# Known and lazy: loading a scene expands its [terrain] section into an obstacle
# (config.scene_from_dict -> terrain.expand), inside the function.
ALLOWED = {("config", "terrain")}


def floor_of(name: str) -> int:
    for k, names in enumerate(FLOORS):
        if name in names:
            return k
    raise AssertionError(f"whitecap.{name}: not placed in a floor of tests/test_layering.py")


def imported_top_names(source: str, rel: tuple) -> set[str]:
    """The top-level whitecap names imported by ``source``, the module at ``rel`` (path parts
    below the package, without the suffix)."""
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.level:
            base = list(rel[:-1])[: len(rel) - node.level]
            parts = base + (node.module.split(".") if node.module else [])
            if parts:
                out.add(parts[0])
            else:
                out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "whitecap":
            out.add(node.module.split(".")[1] if "." in node.module else "__init__")
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("whitecap."):
                    out.add(a.name.split(".")[1])
    return out


def test_imports_run_one_way():
    wrong = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        if rel.parts[0] == "render" and "addon" in rel.parts:
            continue  # the Blender add-on is loaded by Blender, apart from the package
        own = rel.with_suffix("").parts[0]
        for name in imported_top_names(path.read_text(), rel.with_suffix("").parts):
            if name in {"__version__"} or name == own or (own, name) in ALLOWED:
                continue
            if floor_of(name) > floor_of(own):
                wrong.append(f"{rel} imports whitecap.{name}")
    assert not wrong, "imports that run upward:\n" + "\n".join(wrong)


def test_the_check_sees_an_upward_import():
    """The scan finds upward imports however they are written."""
    rel = ("sim", "probe")
    for line in ("from ..pipeline import simulate", "from whitecap.render.scene import build_scene",
                 "import whitecap.cli", "from .. import render"):
        names = imported_top_names(line + "\n", rel)
        assert any(floor_of(n) > floor_of("sim") for n in names), line
    assert imported_top_names("from .grid import F1\nfrom ..io import read\n", rel) == {"sim", "io"}
