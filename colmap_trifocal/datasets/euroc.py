"""EuRoC MAV camera folders (Burri et al., IJRR 2016), one camera of one sequence.

Kind ``euroc``; ``path`` is a folder holding ``sensor.yaml`` (the dataset's Kalibr
calibration: ``intrinsics: [fu, fv, cu, cv]``, ``distortion_model``,
``distortion_coefficients: [k1, k2, p1, p2]`` for ``radial-tangential``,
``resolution: [width, height]``) and the frames, either in ``images/`` or, as the
dataset ships them, in ``data/``. The intrinsics are in the OpenCV pixel convention:
cx, cy + 0.5. There are no poses in the camera folder (the body's ground truth is
another sensor's); :attr:`DatasetScene.distortion` holds the lens as OpenCV's
``k1, k2, p1, p2``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from ..common.errors import CalibrationError
from .base import (
    OPENCV_TO_COLMAP,
    DatasetScene,
    GroundTruthView,
    list_images,
    parsing,
    require_dir,
    require_file,
)

#: The distortion names of EuRoC's ``radial-tangential`` model, in file order.
RADTAN_NAMES = ("k1", "k2", "p1", "p2")


def read_euroc_scene(path: Path | str) -> DatasetScene:
    """An EuRoC camera folder as a :class:`DatasetScene` (one view per frame)."""
    folder = require_dir(path, "EuRoC camera folder")
    sensor = read_sensor_file(require_file(folder / "sensor.yaml", "EuRoC sensor file"))
    image_dir = next((folder / d for d in ("images", "data") if (folder / d).is_dir()), None)
    if image_dir is None:
        raise CalibrationError(f"no images/ or data/ folder in {folder}")
    names = list_images(image_dir)
    if not names:
        raise CalibrationError(f"no images in {image_dir}")
    intrinsics = np.asarray(sensor["intrinsics"], float) + OPENCV_TO_COLMAP
    width, height = (int(v) for v in sensor["resolution"])
    views = [GroundTruthView(name, intrinsics, width, height) for name in names]
    distortion = None
    if sensor.get("distortion_model") == "radial-tangential":
        distortion = dict(
            zip(RADTAN_NAMES, map(float, sensor["distortion_coefficients"]), strict=True)
        )
    return DatasetScene(
        kind="euroc", name=folder.name, image_dir=image_dir, views=views, distortion=distortion
    )


def read_sensor_file(path: Path) -> dict[str, Any]:
    """The keys of a Kalibr ``sensor.yaml`` this reader needs (a flat ``key: value`` file;
    lists as ``[a, b, …]``, comments after ``#``)."""
    with parsing(path, "EuRoC sensor file"):
        values: dict[str, Any] = {}
        for line in path.read_text().splitlines():
            line = line.split("#", 1)[0].strip()
            match = re.fullmatch(r"([A-Za-z_]\w*)\s*:\s*(.*)", line)
            if not match:
                continue
            key, text = match.groups()
            if text.startswith("["):
                values[key] = [float(v) for v in text.strip("[]").split(",") if v.strip()]
            else:
                values[key] = text.strip().strip("'\"")
        for key, size in (("intrinsics", 4), ("resolution", 2)):
            value = values.get(key)
            if not isinstance(value, list) or len(value) != size:
                raise ValueError(f"expected {key}: [{size} numbers]")
        if values.get("distortion_model") == "radial-tangential":
            coefficients = values.get("distortion_coefficients")
            if not isinstance(coefficients, list) or len(coefficients) != 4:
                raise ValueError("expected distortion_coefficients: [k1, k2, p1, p2]")
    return values
