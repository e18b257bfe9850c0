"""colmap-trifocal: camera self-calibration for COLMAP with the TrifocalCalib method.

From a database to a calibrated ``pycolmap.Reconstruction`` (``colmap-trifocal run``
after the features)::

    from colmap_trifocal import reconstruct
    reconstruction, results = reconstruct("database.db")   # images="images": colours

The calibration alone mirrors the ``colmap-trifocal calibrate`` command::

    from colmap_trifocal import CalibrationOptions, calibrate_database
    results = calibrate_database("database.db", CalibrationOptions(method="msac-opt"))
    print(results[0].fx, results[0].std["fx"])
    results[0].cameras                    # {camera_id: pycolmap.Camera} with the estimate
    results[0].apply(reconstruction)      # or a pycolmap.Database, or a database path
    merge_cameras(reconstruction, results[0].camera_ids)   # one shared camera per group
    write_cameras_txt(results, "cameras.txt")              # COLMAP's text cameras
    show(reconstruction, "view.png")      # Open3D (pip install 'colmap-trifocal[viz]')

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

from .common.errors import CalibrationError, NoEstimate

if TYPE_CHECKING:
    from .database.shared_cameras import merge_cameras
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
    from .intrinsics.results import PARAMETER_NAMES
    from .intrinsics.solve.observability import FALLBACK_FACTOR, MAX_RELATIVE_STD
    from .reconstruction.cameras_txt import write_cameras_txt
    from .reconstruction.pipeline import ReconstructOptions, reconstruct
    from .reconstruction.visualize import show

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


#: The other exports, loaded on first use: name -> the module that defines it.
_MODULE_EXPORTS = {
    "FALLBACK_FACTOR": ".intrinsics.solve.observability",
    "MAX_RELATIVE_STD": ".intrinsics.solve.observability",
    "PARAMETER_NAMES": ".intrinsics.results",
    "ReconstructOptions": ".reconstruction.pipeline",
    "merge_cameras": ".database.shared_cameras",
    "reconstruct": ".reconstruction.pipeline",
    "show": ".reconstruction.visualize",
    "write_cameras_txt": ".reconstruction.cameras_txt",
}


def __getattr__(name: str) -> Any:
    if name in _PIPELINE_EXPORTS:
        from .intrinsics import api as calibrate

        return getattr(calibrate, name)
    if name in _MODULE_EXPORTS:
        from importlib import import_module

        return getattr(import_module(_MODULE_EXPORTS[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "FALLBACK_FACTOR",
    "MAX_RELATIVE_STD",
    "METHODS",
    "PARAMETER_NAMES",
    "CalibrationError",
    "CalibrationOptions",
    "CameraCalibration",
    "GroupCalibration",
    "NoEstimate",
    "ReconstructOptions",
    "SkippedGroup",
    "__version__",
    "calibrate_contents",
    "calibrate_contents_methods",
    "calibrate_database",
    "calibrate_groups",
    "calibrate_reconstruction",
    "merge_cameras",
    "reconstruct",
    "show",
    "write_cameras_txt",
]
