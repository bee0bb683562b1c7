"""The floor plan stays true: no module of kalmansfm imports a higher layer, not even inside a function.

The layers, bottom to top (docs/architecture.md):

0. ``errors``, ``_version`` (siblings)
1. ``_validation``, ``_compilation`` (siblings)
2. ``estimation``
3. ``tracking``, ``structure``, ``features`` (siblings: none imports another)
4. ``io``, ``mapping`` (siblings)
5. ``scenes``, ``experiments`` (siblings)
6. ``report``
7. ``pipeline``
8. ``cli``
9. the package's face: ``kalmansfm/__init__.py`` and ``__main__``

A module may import its own layer's package and any lower layer.  Every import
statement of every module counts, wherever it stands (module level, function body,
``TYPE_CHECKING`` block).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import kalmansfm

PACKAGE = Path(kalmansfm.__file__).parent

LAYERS: dict[str, int] = {
    "errors": 0,
    "_version": 0,
    "_validation": 1,
    "_compilation": 1,
    "estimation": 2,
    "tracking": 3,
    "structure": 3,
    "features": 3,
    "io": 4,
    "mapping": 4,
    "scenes": 5,
    "experiments": 5,
    "report": 6,
    "pipeline": 7,
    "cli": 8,
    "__main__": 9,
    "": 9,  # kalmansfm/__init__.py
}
#: Modules that belong to another room: ``_api`` holds the names kalmansfm/__init__.py loads on first use.
ROOM_OF = {"_api": ""}


def module_name(path: Path) -> str:
    """``kalmansfm.tracking.tracker`` for .../kalmansfm/tracking/tracker.py (packages by their __init__)."""
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imported_modules(path: Path, name: str | None = None) -> set[str]:
    """Every kalmansfm module that ``path`` imports (absolute names), from any statement in the file.

    ``name`` is the module's dotted name (default: from its place in the package).
    """
    name = module_name(path) if name is None else name
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.split(".")[0] == "kalmansfm")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "kalmansfm":
                continue
            if node.module is None or node.level and not node.module:
                # ``from . import figures``: the names may be modules of that package
                found.update(f"{target}.{alias.name}" for alias in node.names)
            found.add(target)
    return found


def layer_of(module: str) -> tuple[str, int]:
    """(room, layer) of a kalmansfm module: its first component below the package."""
    parts = module.split(".")
    room = parts[1] if len(parts) > 1 else ""
    room = ROOM_OF.get(room, room)
    if room not in LAYERS:
        raise KeyError(f"{module} belongs to no layer; add {room!r} to LAYERS and to docs/architecture.md")
    return room, LAYERS[room]


def violations(graph: dict[str, set[str]]) -> list[str]:
    """The imports that run against the layers: a lower layer importing a higher one, or a sibling."""
    found = []
    for module, targets in sorted(graph.items()):
        room, layer = layer_of(module)
        for target in sorted(targets):
            try:
                other, other_layer = layer_of(target)
            except KeyError:
                # ``from .x import name`` also lists "package.x.name"; names that are not modules are fine
                other, other_layer = layer_of(target.rsplit(".", 1)[0])
            if other == room:
                continue
            if other_layer > layer or (other_layer == layer and other != room):
                found.append(f"{module} (layer {layer}) imports {target} (layer {other_layer})")
    return found


def package_graph() -> dict[str, set[str]]:
    return {module_name(p): imported_modules(p) for p in sorted(PACKAGE.rglob("*.py"))}


def test_every_module_belongs_to_a_layer():
    for module in package_graph():
        layer_of(module)


def test_no_import_runs_against_the_layers():
    assert violations(package_graph()) == []


def test_the_check_catches_upward_and_sideways_imports():
    # The arrows this layout removed: tracking -> io (a lazy frame reader), io -> scenes, scenes -> report,
    # structure -> experiments, and one sibling import tracking -> structure.
    graph = {
        "kalmansfm.tracking.tracker": {"kalmansfm.io.frames", "kalmansfm.estimation.kalman"},
        "kalmansfm.io.ground_truth": {"kalmansfm.scenes.polyhedron"},
        "kalmansfm.scenes.fusion_tasks": {"kalmansfm.report.tables"},
        "kalmansfm.structure.consistency": {"kalmansfm.experiments.fusion_tasks"},
        "kalmansfm.tracking.smoothing": {"kalmansfm.structure.affine.factorization"},
        "kalmansfm.report.html": {"kalmansfm.io.run_folder", "kalmansfm.errors"},
    }
    assert violations(graph) == [
        "kalmansfm.io.ground_truth (layer 4) imports kalmansfm.scenes.polyhedron (layer 5)",
        "kalmansfm.scenes.fusion_tasks (layer 5) imports kalmansfm.report.tables (layer 6)",
        "kalmansfm.structure.consistency (layer 3) imports kalmansfm.experiments.fusion_tasks (layer 5)",
        "kalmansfm.tracking.smoothing (layer 3) imports kalmansfm.structure.affine.factorization (layer 3)",
        "kalmansfm.tracking.tracker (layer 3) imports kalmansfm.io.frames (layer 4)",
    ]


def test_function_level_and_relative_imports_are_seen(tmp_path):
    # A lazy import inside a function, written relative to the package, is an arrow like any other.
    source = tmp_path / "probe.py"
    source.write_text("def track(frames):\n    from ..io.frames import read_frames\n    return read_frames(frames)\n")
    graph = {"kalmansfm.tracking.probe": imported_modules(source, "kalmansfm.tracking.probe")}
    assert violations(graph) == ["kalmansfm.tracking.probe (layer 3) imports kalmansfm.io.frames (layer 4)"]
    # the real tracker no longer has that arrow
    assert "kalmansfm.io.frames" not in imported_modules(PACKAGE / "tracking" / "tracker.py")


@pytest.mark.parametrize("room", sorted(r for r in LAYERS if r and r != "__main__"))
def test_the_layer_map_names_real_modules(room):
    assert (PACKAGE / room).is_dir() or (PACKAGE / f"{room}.py").is_file()


#: Inside structure/, the wings and the record on top of them: a wing imports only lower floors, never a sibling.
STRUCTURE_FLOORS: dict[str, int] = {
    "points": 0,  # the point status every method shares
    "reconstruction": 1,  # the one record every method returns
    "geometry": 2,  # cameras, rotations, alignment, two-view triangulation
    "affine": 3,  # factorization (affine cameras)
    "fusion": 3,  # known cameras
    "perspective": 4,  # calibrated, unknown motion: uses fusion to triangulate
    "": 5,  # structure/__init__.py, the face
}


def wing_of(module: str) -> tuple[str, int]:
    """(wing, floor) of a module of kalmansfm.structure."""
    parts = module.split(".")
    wing = parts[2] if len(parts) > 2 else ""
    if wing not in STRUCTURE_FLOORS:
        raise KeyError(f"{module} belongs to no wing of structure/; add {wing!r} to STRUCTURE_FLOORS")
    return wing, STRUCTURE_FLOORS[wing]


def wing_violations(graph: dict[str, set[str]]) -> list[str]:
    """Imports inside structure/ that run up a floor or across to a sibling wing."""
    found = []
    for module, targets in sorted(graph.items()):
        if not module.startswith("kalmansfm.structure"):
            continue
        wing, floor = wing_of(module)
        for target in sorted(t for t in targets if t.startswith("kalmansfm.structure")):
            try:
                other, other_floor = wing_of(target)
            except KeyError:
                other, other_floor = wing_of(target.rsplit(".", 1)[0])
            if other != wing and (other_floor > floor or other_floor == floor):
                found.append(f"{module} ({wing}, floor {floor}) imports {target} ({other}, floor {other_floor})")
    return found


def test_structure_wings_import_only_downwards():
    assert wing_violations(package_graph()) == []


def test_the_wing_check_catches_a_sibling_and_an_upward_import():
    graph = {
        "kalmansfm.structure.affine.factorization": {"kalmansfm.structure.fusion.fuse"},
        "kalmansfm.structure.geometry.pinhole": {"kalmansfm.structure.reconstruction", "kalmansfm.structure.points"},
        "kalmansfm.structure.reconstruction": {"kalmansfm.structure.perspective.settings"},
    }
    assert wing_violations(graph) == [
        "kalmansfm.structure.affine.factorization (affine, floor 3) imports kalmansfm.structure.fusion.fuse "
        "(fusion, floor 3)",
        "kalmansfm.structure.reconstruction (reconstruction, floor 1) imports kalmansfm.structure.perspective.settings "
        "(perspective, floor 4)",
    ]
