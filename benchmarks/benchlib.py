"""Small helpers shared by the speed benchmarks (public API and pycolmap only).

Kept outside the package on purpose: the benchmarks must keep working while the core
changes, so they use nothing but ``colmap_trifocal.calibrate_database``,
``CalibrationOptions``, ``colmap_trifocal.database.features.build_database`` and pycolmap.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import time
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path

import numpy as np
import pycolmap

from colmap_trifocal.common.log import silenced_stderr

#: Strecha camera (fountain-P11 / Herz-Jesus-P8), 3072 x 2048, pixels.
STRECHA_INTRINSICS = (2759.48, 2764.16, 1520.69, 1006.81)
PARAMETER_NAMES = ("fx", "fy", "cx", "cy")


def mean_relative_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Mean relative error of (fx, fy, cx, cy), percent."""
    return float(np.mean(np.abs(np.asarray(estimate) / np.asarray(truth) - 1.0)) * 100.0)


def parse_intrinsics(text: str) -> np.ndarray:
    """``FX,FY,CX,CY`` or the path of a ``ground_truth.json`` (key ``intrinsics``) or a
    Strecha ``.camera`` file."""
    path = Path(text)
    if path.is_file():
        if path.suffix == ".json":
            data = json.loads(path.read_text())
            return np.array([data["intrinsics"][k] for k in PARAMETER_NAMES], float)
        rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
        K = np.array(rows[:3], float)
        return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    values = np.array([float(v) for v in text.split(",")])
    if values.shape != (4,):
        raise SystemExit(f"error: expected FX,FY,CX,CY or a file, got {text!r}")
    return values


def quiet_stderr(enabled: bool = True) -> AbstractContextManager[None]:
    """Silence file descriptor 2 (glog, where COLMAP logs) for the duration of a call."""
    return silenced_stderr() if enabled else nullcontext()


def copy_with_camera(database: Path, target: Path, params: np.ndarray | None) -> Path:
    """Copy ``database`` to ``target``; set every camera's parameters to ``params`` if given."""
    shutil.copyfile(database, target)
    if params is not None:
        with pycolmap.Database.open(str(target)) as db:
            for camera in db.read_all_cameras():
                camera.params = np.asarray(params, float)
                db.update_camera(camera)
    return target


def stored_intrinsics(database: Path) -> np.ndarray:
    """(fx, fy, cx, cy) of the first camera stored in the database (PINHOLE expected)."""
    with pycolmap.Database.open(str(database)) as db:
        camera = db.read_all_cameras()[0]
    return np.array(
        [
            camera.focal_length_x,
            camera.focal_length_y,
            camera.principal_point_x,
            camera.principal_point_y,
        ]
    )


def database_summary(database: Path) -> dict[str, float]:
    """Images, verified pairs, mean keypoints per image and mean inlier matches per pair."""
    with pycolmap.Database.open(str(database)) as db:
        images = db.read_all_images()
        keypoints = [db.num_keypoints_for_image(i.image_id) for i in images]
        _, geometries = db.read_two_view_geometries()
        inliers = [len(g.inlier_matches) for g in geometries]
    verified = [n for n in inliers if n > 0]
    return {
        "images": len(images),
        "pairs": len(verified),
        "keypoints_per_image": float(np.mean(keypoints)) if keypoints else 0.0,
        "matches_per_pair": float(np.mean(verified)) if verified else 0.0,
    }


def cpu_seconds() -> float:
    """User + system CPU seconds of this process (all threads) and its waited-for children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def load_average() -> float:
    """The 1-minute load average (other work on the machine skews wall-clock times)."""
    return os.getloadavg()[0]


class Stopwatch:
    """``with Stopwatch() as w: ...``; then ``w.seconds`` (wall) and ``w.cpu`` (CPU seconds).

    CPU seconds include this process's threads (pycolmap's mapper) and the worker
    processes it started and joined (calibrate's pool); they are less sensitive than
    wall-clock time to other processes competing for the cores.
    """

    def __enter__(self) -> Stopwatch:
        self.start = time.perf_counter()
        self.cpu_start = cpu_seconds()
        self.seconds = self.cpu = float("nan")
        return self

    def __exit__(self, *exc: object) -> None:
        self.seconds = time.perf_counter() - self.start
        self.cpu = cpu_seconds() - self.cpu_start
