"""The package layout: stage sub-packages import only earlier stages (data flows one way)."""

from __future__ import annotations

import ast
from pathlib import Path

import colmap_trifocal

PACKAGE = Path(colmap_trifocal.__file__).parent

#: Sub-packages in the order data flows; a module may import its own stage or an earlier one.
STAGES = ("common", "database", "geometry", "intrinsics", "reconstruction")
#: Support packages sit after every stage: they may use any stage, no stage may use them.
SUPPORT = ("synthetic", "datasets", "evaluation")


def _imported_subpackages(path: Path) -> set[str]:
    """Top-level sub-packages of colmap_trifocal that the module at ``path`` imports."""
    module_parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = list(module_parts[:-1])[: len(module_parts) - node.level]
                target = [*base, *(node.module or "").split(".")]
            else:
                target = (node.module or "").split(".")
            names = [alias.name for alias in node.names]
            if target[0] == "colmap_trifocal":
                parts = [p for p in target[1:] if p]
                found.update(parts[:1] or names)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == "colmap_trifocal" and len(parts) > 1:
                    found.add(parts[1])
    return found


def _rank(subpackage: str) -> int:
    order = (*STAGES, *SUPPORT)
    return order.index(subpackage) if subpackage in order else len(order)


def test_stages_import_no_later_stage() -> None:
    offences = []
    for sub in STAGES:
        for path in sorted((PACKAGE / sub).rglob("*.py")):
            for imported in _imported_subpackages(path):
                if imported in (*STAGES, *SUPPORT) and _rank(imported) > _rank(sub):
                    offences.append(f"{path.relative_to(PACKAGE)} imports {imported}")
    assert offences == []


def test_tree_lists_the_stages_in_flow_order() -> None:
    """``ls colmap_trifocal`` (alphabetical) shows the stages in the order data flows."""
    listed = sorted(p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name in STAGES)
    assert listed == list(STAGES)


def test_every_subpackage_says_what_it_takes_and_gives() -> None:
    for sub in (*STAGES, *SUPPORT):
        doc = ast.get_docstring(ast.parse((PACKAGE / sub / "__init__.py").read_text()))
        assert doc, f"{sub}/__init__.py has no docstring"


def test_public_api_imports_from_the_top_level() -> None:
    from colmap_trifocal import (  # noqa: F401
        METHODS,
        CalibrationError,
        CalibrationOptions,
        CameraCalibration,
        calibrate_contents,
        calibrate_contents_methods,
        calibrate_database,
    )

    assert "msac-opt" in METHODS
