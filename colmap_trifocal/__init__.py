"""colmap-trifocal: camera self-calibration for COLMAP with the TrifocalCalib method.

The public API mirrors the ``colmap-trifocal calibrate`` command::

    from colmap_trifocal import CalibrationOptions, calibrate_database
    results = calibrate_database("database.db", CalibrationOptions(method="msac-opt"))
    print(results[0].fx, results[0].std["fx"])
    results[0].camera                     # a pycolmap.Camera with the estimate
    results[0].apply(reconstruction)      # into a pycolmap.Reconstruction's cameras

``calibrate_reconstruction(reconstruction_or_folder)`` calibrates from a
reconstruction's tracks instead, beside its own intrinsics (``result.reference``).

Each result is a ``CameraCalibration``: one physical camera's estimate, for every
camera id of its group (``result.camera_ids``; ``GroupCalibration`` is the same class);
``calibrate_groups`` also returns the groups it skipped (``SkippedGroup``). Both have
``to_json()``, the objects ``colmap-trifocal calibrate --json`` writes.

Conventions used throughout: intrinsics are (fx, fy, cx, cy) in pixels with
COLMAP's pixel convention (the centre of the top-left pixel is at (0.5, 0.5));
K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]; tensor slices follow Hartley &
Zisserman (``T_i = a_i b4ᵀ − a4 b_iᵀ`` for ``P2 = [A|a4]``, ``P3 = [B|b4]``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

from .common.errors import CalibrationError

if TYPE_CHECKING:
    from .intrinsics.api import (
        METHODS,
        CalibrationOptions,
        CameraCalibration,
        GroupCalibration,
        SkippedGroup,
        calibrate_contents,
        calibrate_contents_methods,
        calibrate_database,
        calibrate_groups,
        calibrate_reconstruction,
    )

#: Loaded on first use (PEP 562), so that ``import colmap_trifocal.cli`` is quick and the
#: command line can turn Ctrl-C during the heavy imports into one ``error:`` line.
_PIPELINE_EXPORTS = frozenset(
    {
        "METHODS",
        "CalibrationOptions",
        "CameraCalibration",
        "GroupCalibration",
        "SkippedGroup",
        "calibrate_contents",
        "calibrate_contents_methods",
        "calibrate_database",
        "calibrate_groups",
        "calibrate_reconstruction",
    }
)


def __getattr__(name: str) -> Any:
    if name in _PIPELINE_EXPORTS:
        from .intrinsics import api as calibrate

        return getattr(calibrate, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "METHODS",
    "CalibrationError",
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
]
