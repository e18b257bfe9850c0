"""colmap-trifocal: camera self-calibration for COLMAP with the TrifocalCalib method.

The public API mirrors the ``colmap-trifocal calibrate`` command::

    from colmap_trifocal import CalibrationOptions, calibrate_database
    results = calibrate_database("database.db", CalibrationOptions(method="msac-opt"))
    print(results[0].fx, results[0].std["fx"])

Conventions used throughout: intrinsics are (fx, fy, cx, cy) in pixels with
COLMAP's pixel convention (the centre of the top-left pixel is at (0.5, 0.5));
K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]; tensor slices follow Hartley &
Zisserman (``T_i = a_i b4ᵀ − a4 b_iᵀ`` for ``P2 = [A|a4]``, ``P3 = [B|b4]``).
"""

__version__ = "0.1.0"

from .errors import CalibrationError
from .pipeline import (
    METHODS,
    CalibrationOptions,
    CameraCalibration,
    calibrate_contents,
    calibrate_contents_methods,
    calibrate_database,
)

__all__ = [
    "METHODS",
    "CalibrationError",
    "CalibrationOptions",
    "CameraCalibration",
    "__version__",
    "calibrate_contents",
    "calibrate_contents_methods",
    "calibrate_database",
]
