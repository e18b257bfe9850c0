"""Real databases as COLMAP users have them (Strecha scenes; skipped without the data).

* COLMAP's default extraction (one SIMPLE_RADIAL camera per image): calibrated as one
  physical camera, exactly as the same database with one shared camera id, and
  ``--write`` updates every camera.
* A mixed folder: two physical cameras of different sizes, images interleaved by
  name, and a third camera with only 2 images (skipped, exit 0).

The databases come from the shared cache (``conftest.DatabaseCache``); the test that
writes works on a copy.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import CliResult, DatabaseCache, strecha_root

from colmap_trifocal.database.shared_cameras import merge_group_cameras
from colmap_trifocal.database.snapshot import read_database
from colmap_trifocal.datasets.strecha import ground_truth_intrinsics, scene_images
from colmap_trifocal.intrinsics.api import CalibrationOptions, calibrate_database


def _error(values: dict | np.ndarray, truth: np.ndarray) -> float:
    if isinstance(values, dict):
        values = np.array([values[k] for k in ("fx", "fy", "cx", "cy")])
    return float(np.mean(np.abs(np.asarray(values) / truth - 1)))


pytestmark = [pytest.mark.real_data, pytest.mark.slow]


@pytest.mark.parametrize(("scene", "num_images"), [("fountain-P11", 11), ("Herz-Jesus-P8", 8)])
def test_colmap_default_database(
    scene: str,
    num_images: int,
    tmp_path: Path,
    real_scene_database: Callable[[str, str], Path],
    run_main: Callable[..., CliResult],
) -> None:
    folder = strecha_root() / scene
    cached = real_scene_database(scene, "default")  # what `colmap feature_extractor` makes
    database = DatabaseCache.copy(cached, tmp_path / "database.db")  # written below
    cameras = read_database(database).cameras
    assert len(cameras) == num_images
    assert len({c.params.tobytes() for c in cameras.values()}) == 1
    single = tmp_path / "single.db"
    shutil.copyfile(database, single)
    merge_group_cameras(single, [sorted(cameras)])

    report = tmp_path / "out.json"
    result = run_main("calibrate", database, "--json", report, "--write")
    assert result.returncode == 0, result.stderr
    assert f"wrote {num_images} camera(s)" in result.stdout
    (entry,) = json.loads(report.read_text())
    assert entry["camera_ids"] == sorted(cameras)
    truth = ground_truth_intrinsics(folder)
    assert _error(entry, truth) <= 0.005
    # The same accuracy as the single-camera database: the same numbers.
    (reference,) = calibrate_database(single, CalibrationOptions())
    assert [entry[k] for k in ("fx", "fy", "cx", "cy")] == reference.intrinsics.tolist()
    for camera in read_database(database).cameras.values():
        np.testing.assert_allclose(camera.intrinsics, reference.intrinsics, rtol=1e-12)
        # k as estimated where the tracks showed distortion (the test's 5 % false alarms
        # on these undistorted images find |k| ~ 0.001), else kept at 0.
        assert camera.params[3] == (entry["distortion"] or [0.0])[0]
        assert abs(camera.params[3]) < 0.003


def _mixed_folder(target: Path) -> tuple[dict[str, np.ndarray], list[str]]:
    """fountain-P11 at full size, Herz-Jesus-P8 at half size, 2 more at another size,
    interleaved by name. Returns the ground truth per size label and the 2-image names."""
    root = strecha_root()
    fountain, herz = root / "fountain-P11", root / "Herz-Jesus-P8"
    target.mkdir()
    f_names = scene_images(fountain)[2:7]
    h_names = scene_images(herz)
    half, other = h_names[1:6], h_names[6:8]
    names = []
    for k, (f, h) in enumerate(zip(f_names, half, strict=True)):
        shutil.copyfile(fountain / "images" / f, target / f"{2 * k:02d}.jpg")
        image = cv2.imread(str(herz / "images" / h))
        small = cv2.resize(image, (1536, 1024), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(target / f"{2 * k + 1:02d}.jpg"), small)
        names += [f"{2 * k:02d}.jpg", f"{2 * k + 1:02d}.jpg"]
    pair = []
    for k, h in enumerate(other):
        image = cv2.imread(str(herz / "images" / h))
        name = f"{10 + k:02d}.jpg"
        cv2.imwrite(
            str(target / name), cv2.resize(image, (1200, 800), interpolation=cv2.INTER_AREA)
        )
        pair.append(name)
    scale = np.array([0.5, 0.5, 0.5, 0.5])
    truth = {
        "3072x2048": ground_truth_intrinsics(fountain),
        "1536x1024": ground_truth_intrinsics(herz) * scale,
    }
    return truth, pair


def test_mixed_folder_two_cameras_and_a_skipped_pair(
    tmp_path: Path, database_cache: DatabaseCache, run_main: Callable[..., CliResult]
) -> None:
    images = tmp_path / "images"
    truth, pair = _mixed_folder(images)
    # The same images every run (OpenCV writes them alike): the cache key finds them.
    database = database_cache.get(images, max_image_size=1000, camera_mode="auto")
    contents = read_database(database)
    assert len(contents.cameras) == 12  # one per image, as COLMAP's default
    report = tmp_path / "out.json"
    result = run_main("calibrate", database, "--json", report)
    err = result.stderr
    assert result.returncode == 0, err
    entries = json.loads(report.read_text())
    calibrated = [e for e in entries if "skipped" not in e]
    (skipped,) = [e for e in entries if "skipped" in e]
    assert len(calibrated) == 2
    pair_cameras = sorted(
        contents.image_camera[i] for i, n in contents.image_names.items() if n in pair
    )
    assert skipped["camera_ids"] == pair_cameras and skipped["skipped"] == "2 images"
    assert f"camera group {pair_cameras[0]} (2 ids) skipped: 2 images" in err
    for entry in calibrated:
        camera = contents.cameras[entry["camera_id"]]
        size = f"{camera.width}x{camera.height}"
        names = {
            contents.image_names[i]
            for i, c in contents.image_camera.items()
            if c in entry["camera_ids"]
        }
        assert len(names) == 5
        assert all((int(n[:2]) % 2 == 0) == (size == "3072x2048") for n in names)
        assert _error(entry, truth[size]) <= 0.01, (size, entry)
