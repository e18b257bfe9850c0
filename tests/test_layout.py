"""The package layout: stage sub-packages import only earlier stages (data flows one way)."""

from __future__ import annotations

import ast
import importlib
import importlib.metadata
import re
import subprocess
import sys
from pathlib import Path

import pytest

import colmap_trifocal

PACKAGE = Path(colmap_trifocal.__file__).parent

#: Sub-packages in the order data flows; a module may import its own stage or an earlier one.
STAGES = ("common", "database", "geometry", "intrinsics", "reconstruction")
#: Support packages sit after every stage: they may use any stage, no stage may use them;
#: the command line (``cli``) comes last: it may use every package, none may use it.
SUPPORT = ("synthetic", "datasets", "evaluation", "cli")


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


def test_only_the_command_line_imports_the_command_line() -> None:
    """The library returns and raises; only ``cli/`` prints, so nothing imports it."""
    offences = [
        str(path.relative_to(PACKAGE))
        for path in sorted(PACKAGE.rglob("*.py"))
        if path.relative_to(PACKAGE).parts[0] != "cli" and "cli" in _imported_subpackages(path)
    ]
    assert offences == []


def _stage_imports() -> dict[str, set[str]]:
    """Each stage: the other stages its modules import."""
    return {
        sub: {
            imported
            for path in (PACKAGE / sub).rglob("*.py")
            for imported in _imported_subpackages(path)
            if imported in STAGES and imported != sub
        }
        for sub in STAGES
    }


def _listed_subpackages(text: str) -> list[str]:
    """The sub-packages a document names (``name/``), in the order it names them first."""
    names = re.findall(r"(?:^|[`| ])([a-z_]+)/", text, flags=re.MULTILINE)
    known = (*STAGES, *SUPPORT)
    return list(dict.fromkeys(n for n in names if n in known))


def test_tree_lists_the_stages_in_flow_order() -> None:
    """STAGES is the package: its order is the one the imports give and the one
    docs/how_it_works.md and CONTRIBUTING show, and ``ls colmap_trifocal`` (alphabetical)
    lists it."""
    on_disk = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    assert on_disk == {*STAGES, *SUPPORT}, "a sub-package missing from STAGES/SUPPORT or gone"
    # Depth in the import graph (common 0, a stage importing only common 1, ...): the
    # flow order sorts the stages by it (ties alphabetically, as ls shows them).
    imports = _stage_imports()

    def depth_of(sub: str, seen: tuple[str, ...] = ()) -> int:
        assert sub not in seen, f"import cycle: {' -> '.join((*seen, sub))}"
        return 1 + max((depth_of(i, (*seen, sub)) for i in imports[sub]), default=-1)

    depth = {sub: depth_of(sub) for sub in STAGES}
    assert sorted(STAGES, key=lambda s: (depth[s], s)) == list(STAGES), depth
    assert all(imports[sub] for sub in STAGES[1:]), "a stage that takes nothing from earlier ones"
    assert sorted(STAGES) == list(STAGES)  # `ls` lists them in flow order
    readme = (PACKAGE.parent / "docs" / "how_it_works.md").read_text()
    table = readme[readme.index("The package is laid out by stage") :]
    table = table[: table.index("\n\n", table.index("| stage |"))]
    assert _listed_subpackages(table) == [*STAGES, *SUPPORT]
    contributing = (PACKAGE.parent / "CONTRIBUTING.md").read_text()
    layout = contributing[contributing.index("## Layout") : contributing.index("## Conventions")]
    assert _listed_subpackages(layout) == [*STAGES, *SUPPORT]


def test_every_subpackage_says_what_it_takes_and_gives() -> None:
    for sub in (*STAGES, *SUPPORT):
        doc = ast.get_docstring(ast.parse((PACKAGE / sub / "__init__.py").read_text()))
        assert doc, f"{sub}/__init__.py has no docstring"


#: The public API (``colmap_trifocal.__all__``), as CONTRIBUTING.md describes it.
PUBLIC_API = {
    "METHODS",
    "CalibrationError",
    "NoEstimate",
    "CalibrationOptions",
    "CameraCalibration",
    "GroupCalibration",
    "SkippedGroup",
    "__version__",
    "calibrate_contents",
    "calibrate_contents_methods",
    "calibrate_database",
    "calibrate_groups",
    "calibrate_reconstruction",
    "FALLBACK_FACTOR",
    "MAX_RELATIVE_STD",
    "PARAMETER_NAMES",
    "ReconstructOptions",
    "merge_cameras",
    "reconstruct",
    "show",
    "write_cameras_txt",
}
#: Where each public name outside ``intrinsics.api`` is defined.
DEFINED_IN = {
    "FALLBACK_FACTOR": "colmap_trifocal.intrinsics.solve.observability",
    "MAX_RELATIVE_STD": "colmap_trifocal.intrinsics.solve.observability",
    "PARAMETER_NAMES": "colmap_trifocal.intrinsics.results",
    "ReconstructOptions": "colmap_trifocal.reconstruction.pipeline",
    "merge_cameras": "colmap_trifocal.database.shared_cameras",
    "reconstruct": "colmap_trifocal.reconstruction.pipeline",
    "show": "colmap_trifocal.reconstruction.visualize",
    "write_cameras_txt": "colmap_trifocal.reconstruction.cameras_txt",
}


def test_public_api_imports_from_the_top_level(tmp_path: Path) -> None:
    """``__all__`` is the documented API; each name is the object of its stage; a user
    error raises CalibrationError; importing the package loads no heavy module."""
    from colmap_trifocal.common import errors
    from colmap_trifocal.intrinsics import api as calibrate

    assert set(colmap_trifocal.__all__) == PUBLIC_API
    for name in PUBLIC_API - {"__version__", "CalibrationError", "NoEstimate"}:
        module = importlib.import_module(DEFINED_IN[name]) if name in DEFINED_IN else calibrate
        assert getattr(colmap_trifocal, name) is getattr(module, name), name
    assert colmap_trifocal.CalibrationError is errors.CalibrationError
    assert issubclass(colmap_trifocal.CalibrationError, Exception)
    assert colmap_trifocal.NoEstimate is errors.NoEstimate
    assert issubclass(colmap_trifocal.NoEstimate, colmap_trifocal.CalibrationError)
    assert colmap_trifocal.__version__ == importlib.metadata.version("colmap-trifocal")
    contributing = (PACKAGE.parent / "CONTRIBUTING.md").read_text()
    start = contributing.index("The public API is what")
    sentence = contributing[start : contributing.index("…)", start)]
    documented = set(re.findall(r"`(\w+)`", sentence))
    assert documented >= {"calibrate_database", "CalibrationOptions", "CalibrationError"}
    assert documented <= PUBLIC_API

    assert colmap_trifocal.METHODS[0] == colmap_trifocal.CalibrationOptions().method
    assert set(colmap_trifocal.METHODS) >= {"msac-opt", "msac", "direct", "fundamental"}
    missing = tmp_path / "missing.db"
    with pytest.raises(colmap_trifocal.CalibrationError, match="database not found"):
        colmap_trifocal.calibrate_database(missing)
    assert not missing.exists()
    with pytest.raises(colmap_trifocal.CalibrationError, match="unknown method"):
        colmap_trifocal.calibrate_database(missing, colmap_trifocal.CalibrationOptions("magic"))

    # PEP 562: the pipeline (numpy, pycolmap, ...) loads on first use, not on import.
    probe = "import sys, colmap_trifocal; print(sorted({'numpy', 'pycolmap'} & set(sys.modules)))"
    loaded = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=60
    )
    assert loaded.stdout.strip() == "[]"


#: Words that put history (a measurement, an issue, an earlier version) in a docstring
#: or comment; it belongs in docs/ and in commit messages (STYLE.md).
HISTORY = re.compile(
    r"\bMeasured\b|\(measured|\bissue \d|\(issue|before this|last round"
    # a measured result: a signed percentage, a before → after of seconds or percent
    r"|: [+−]\d+(\.\d+)? ?%|\d(\.\d+)? ?(s|%) ?(→|->) ?\d"
)


def test_docstrings_and_comments_hold_no_history() -> None:
    found = [
        f"{path.relative_to(PACKAGE)}:{number}: {line.strip()}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if HISTORY.search(line)
    ]
    assert found == []


#: intrinsics/ in the order its stages' data flows: the solve's mathematics first (every
#: stage uses it), the options and results the stages share, then the stages as the
#: pipeline runs them; ``pipeline`` runs them, ``api`` is the public entry.
INTRINSICS_ORDER = (
    "solve",
    "options",
    "result_parts",
    "camera_writing",
    "results",
    "inputs",
    "start",
    "tensors",
    "polish",
    "lens",
    "assess",
    "baselines",
    "pipeline",
    "api_checks",
    "api",
)


def _intrinsics_imports(path: Path) -> set[str]:
    """The parts of intrinsics/ (sub-packages and top modules) the module imports."""
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:
            base = list(parts[:-1])[: len(parts) - node.level]
            target = [*base, *(node.module or "").split(".")]
        else:
            target = (node.module or "").split(".")[1:]
        target = [t for t in target if t]
        if target[:1] != ["intrinsics"]:
            continue
        if len(target) > 1:
            found.add(target[1])
        else:
            found.update(alias.name for alias in node.names)
    return found


def test_intrinsics_stages_import_no_later_stage() -> None:
    """Each part of intrinsics/ imports only itself and earlier parts: no stage climbs
    back to a later one, and only the pipeline runs the stages (only the API, the
    pipeline)."""
    root = PACKAGE / "intrinsics"
    on_disk = {p.stem for p in root.glob("*.py") if p.stem != "__init__"}
    on_disk |= {p.name for p in root.iterdir() if (p / "__init__.py").is_file()}
    assert on_disk == set(INTRINSICS_ORDER)
    offences = []
    for path in sorted(root.rglob("*.py")):
        relative = path.relative_to(root).with_suffix("").parts
        own = relative[0]
        if own == "__init__":
            continue
        for imported in _intrinsics_imports(path):
            if imported in INTRINSICS_ORDER and (
                INTRINSICS_ORDER.index(imported) > INTRINSICS_ORDER.index(own)
            ):
                offences.append(f"intrinsics/{'/'.join(relative)} imports {imported}")
    assert offences == []
