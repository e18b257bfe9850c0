"""The estimate as COLMAP's ``cameras.txt`` (the text model's camera list).

One line per camera id of every calibrated group, ``CAMERA_ID MODEL WIDTH HEIGHT
PARAMS...``, each camera with its stored model, size and distortion and the group's
estimate (pixels, COLMAP's pixel convention), params written with Python's shortest
round-trip repr (COLMAP reads them back bit for bit). A group the images determined
nothing of is written at its start, as the JSON gives it (``source``: ``prior``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from ..common.errors import CalibrationError
from ..common.files import write_text_atomically
from ..intrinsics.api import updated_cameras
from ..intrinsics.results import CameraCalibration

_HEADER = (
    "# Camera list with one line of data per camera:\n"
    "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
    "# Number of cameras: {count}\n"
)


def cameras_txt(results: Sequence[CameraCalibration]) -> str:
    """The text of ``cameras.txt`` for every camera id of ``results``, by camera id."""
    cameras = updated_cameras(results, determined_only=False)
    lines = [
        " ".join(
            [str(camera_id), camera.model, str(camera.width), str(camera.height)]
            + [repr(float(p)) for p in camera.params]
        )
        for camera_id, camera in sorted(cameras.items())
    ]
    return _HEADER.format(count=len(lines)) + "".join(f"{line}\n" for line in lines)


def write_cameras_txt(results: Sequence[CameraCalibration], path: Path | str) -> Path:
    """Write :func:`cameras_txt` to ``path`` atomically (a complete file or none); the path.

    Put it beside COLMAP's ``images.txt`` and ``points3D.txt`` of a text model, or read it
    with any tool that takes COLMAP cameras.

    Raises:
        CalibrationError: the file cannot be written (its folder missing, no space, ...).
    """
    path = Path(path)
    text = cameras_txt(results)
    try:
        write_text_atomically(path, text)
    except OSError as exc:
        raise CalibrationError(f"cannot write {path}: {exc.strerror or exc}") from None
    return path
