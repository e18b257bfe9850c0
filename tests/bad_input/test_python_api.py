"""The Python API on bad arguments: ``CalibrationError`` with a message, never a TypeError,
AttributeError or IndexError from deep inside (issue 37)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pycolmap
import pytest

from colmap_trifocal import (
    CalibrationError,
    CalibrationOptions,
    calibrate_contents,
    calibrate_database,
    calibrate_reconstruction,
)
from colmap_trifocal.intrinsics.api import (
    calibrate_contents_methods,
    calibrate_groups,
    read_contents,
)

#: Quick options (fewer triplets, no focal search): the rows are about the arguments.
QUICK = {"max_triplets": 3, "focal_search": False}


@pytest.mark.parametrize(
    ("reconstruction", "fragment"),
    [
        (None, "must be a path (str or os.PathLike), got NoneType"),
        (42, "got int"),
        (b"/nonexistent/model", "model folder not found: /nonexistent/model"),
        (pycolmap.Image(), "got Image"),
        (pycolmap.Camera(), "got Camera"),
        ([Path("sparse/0")], "got list"),
    ],
    ids=["None", "42", "bytes", "Image", "Camera", "a list"],
)
def test_calibrate_reconstruction_of_no_reconstruction(
    reconstruction: object, fragment: str
) -> None:
    with pytest.raises(CalibrationError, match=fragment.replace("(", r"\(").replace(")", r"\)")):
        calibrate_reconstruction(reconstruction)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("path", "fragment"),
    [(None, "got NoneType"), (42, "got int"), (["database.db"], "got list"), ("", "got ''")],
    ids=["None", "42", "a list of paths", "empty"],
)
def test_calibrate_database_of_no_path(path: object, fragment: str) -> None:
    with pytest.raises(CalibrationError, match=fragment):
        calibrate_database(path)  # type: ignore[arg-type]


def test_contents_methods_and_grouping(good_database: Path) -> None:
    """Every argument of the contents-level calls is checked before any work."""
    contents, _ = read_contents(good_database)
    options = CalibrationOptions(**QUICK)  # type: ignore[arg-type]
    calls: dict[str, tuple[Callable[[], object], str]] = {
        "options None": (lambda: calibrate_contents(contents, None), "got NoneType"),  # type: ignore[arg-type]
        "contents None": (lambda: calibrate_contents(None, options), "contents must be"),  # type: ignore[arg-type]
        "no methods": (lambda: calibrate_contents_methods(contents, options, ()), "got none"),
        "a method as a string": (
            lambda: calibrate_contents_methods(contents, options, "msac"),  # type: ignore[arg-type]
            "a tuple of method names, got 'msac'",
        ),
        "an unknown method": (
            lambda: calibrate_contents_methods(contents, options, ("x",)),
            "unknown method 'x'",
        ),
        "grouping a number": (
            lambda: calibrate_groups(contents, options, ("msac",), grouping=42),  # type: ignore[arg-type]
            "grouping must map camera ids to CameraInfo, got int",
        ),
        "grouping a list": (
            lambda: calibrate_groups(contents, options, ("msac",), grouping=[1]),  # type: ignore[arg-type]
            "got list",
        ),
        "grouping without a camera": (
            lambda: calibrate_groups(contents, options, ("msac",), grouping={}),
            "camera id 1 of the contents is missing",
        ),
        "grouping of other values": (
            lambda: calibrate_groups(contents, options, ("msac",), grouping={1: "x"}),  # type: ignore[dict-item]
            "camera id 1 does not map to its CameraInfo",
        ),
    }
    for call, fragment in calls.values():
        with pytest.raises(CalibrationError, match=fragment):
            call()


def test_camera_ids_any_iterable_and_never_empty(good_database: Path) -> None:
    """``camera_ids`` as a generator is read once, when the options are made (and the
    calibration uses it); an empty one is refused."""
    options = CalibrationOptions(camera_ids=(c for c in [1]), **QUICK)  # type: ignore[arg-type]
    assert options.camera_ids == (1,)
    (result,) = calibrate_database(good_database, options)
    assert result.camera_ids == [1]
    with pytest.raises(CalibrationError, match="at least one"):
        CalibrationOptions(camera_ids=[])
    with pytest.raises(CalibrationError, match="at least one"):
        CalibrationOptions(camera_ids=(c for c in []))


def test_apply_to_nothing(good_database: Path) -> None:
    """``result.apply`` of None, a lone camera or a number: CalibrationError."""
    (result,) = calibrate_database(good_database, CalibrationOptions(**QUICK))  # type: ignore[arg-type]
    camera = pycolmap.Camera()
    for target in (None, camera, 42):
        with pytest.raises(CalibrationError):
            result.apply(target)  # type: ignore[arg-type]
