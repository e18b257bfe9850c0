"""Cameras the calibration skips are still mapped, from their stored values, as COLMAP maps
them: a group of fewer than 3 images, or one the images give no estimate of
(:class:`colmap_trifocal.NoEstimate`). pycolmap synthetic data."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from conftest import CliResult, synthesize
from test_camera_groups import TRUTH, per_image_database

from colmap_trifocal import (
    CalibrationError,
    CalibrationOptions,
    NoEstimate,
    ReconstructOptions,
    calibrate_database,
    calibrate_groups,
    reconstruct,
)
from colmap_trifocal.database.snapshot import read_database
from colmap_trifocal.reconstruction.mapping import camera_intrinsics
from colmap_trifocal.synthetic.demo import make_demo_database

#: The stored focal length of the two odd cameras, 20 % longer than the truth.
WRONG_FOCAL = 1.2 * TRUTH[0]


@pytest.fixture(scope="module")
def two_odd_cameras(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """COLMAP's default database of 8 views (one camera per image, the true parameters),
    where cameras 7 and 8 store a focal length 20 % too long: grouped apart, 2 images."""
    path = tmp_path_factory.mktemp("odd") / "database.db"
    per_image_database(path, images=8, points=800)
    with pycolmap.Database.open(str(path)) as db:
        for camera_id in (7, 8):
            camera = db.read_camera(camera_id)
            camera.params = [WRONG_FOCAL, *camera.params[1:]]
            db.update_camera(camera)
    return path


def test_a_group_of_two_images_is_mapped_with_its_focal_length_refined(
    two_odd_cameras: Path, tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """The skipped group's stored focal length, 20 % off, is refined while mapping, as
    COLMAP's mapper refines it. Before, the other group's estimate, determined, held every
    focal length fixed through mapping, this one too: its images mapped at 20 % off."""
    workspace = tmp_path / "ws"
    result = run_main(
        "run", tmp_path / "no-images", workspace, "--database", two_odd_cameras,
        "--refine", "none",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert (
        "warning: camera group 7 (2 ids) skipped: 2 images; mapped from its stored values"
        in result.stderr.splitlines()
    )
    report = read_report(workspace)
    (group,) = report["skipped_cameras"]
    assert (group["camera_ids"], group["skipped"], group["num_registered_images"]) == (
        [7, 8],
        "2 images",
        2,
    )
    assert group["stored"]["fx"] == WRONG_FOCAL
    assert abs(group["refined"]["fx"] / TRUTH[0] - 1) < 0.01
    stored_row = next(line.split() for line in result.stdout.splitlines() if "stored" in line)
    assert stored_row[:3] == ["7", "stored", f"{WRONG_FOCAL:.2f}"]
    assert report["mapping"]["refined_while_mapping"]["focal_length"] is True
    (camera,) = report["cameras"]
    assert camera["camera_ids"] == list(range(1, 7))
    assert report["num_registered_images"] == 8
    model = pycolmap.Reconstruction(workspace / "sparse" / "0")
    for camera_id in (7, 8):
        mapped = camera_intrinsics(model.cameras[camera_id])
        assert abs(mapped[0] / TRUTH[0] - 1) < 0.01, mapped


def test_no_estimate_maps_from_the_stored_camera(tmp_path: Path) -> None:
    """Where no triplet has the three-view tracks the calibration needs, ``calibrate``
    stops with :class:`NoEstimate`; ``reconstruct`` maps from the stored camera (the
    demo's, every value 5 % off), its focal length refined while mapping."""
    path = tmp_path / "database.db"
    truth, stored = make_demo_database(path, seed=0, num_images=8)
    needs = CalibrationOptions(min_tracks=100_000)
    with pytest.raises(NoEstimate, match="no image triplet with at least 100000 three-view"):
        calibrate_database(path, needs)
    results, skipped = calibrate_groups(
        read_database(path), needs, ("msac-opt",), skip_unestimated=True
    )
    assert results == {"msac-opt": []}
    assert [g.camera_ids for g in skipped] == [[1]]
    assert "no image triplet with at least 100000" in skipped[0].reason
    before = sorted(p.name for p in tmp_path.iterdir()), path.read_bytes()
    options = ReconstructOptions(calibration=needs, write=True)
    reconstruction, calibrations = reconstruct(path, options=options)
    assert calibrations == []
    # write=True with nothing calibrated: the database as it was, and no backup.
    assert (sorted(p.name for p in tmp_path.iterdir()), path.read_bytes()) == before
    assert reconstruction.num_reg_images() == 8
    (mapped,) = (camera_intrinsics(c) for c in reconstruction.cameras.values())
    assert abs(stored[0] / truth[0] - 1) > 0.04
    assert abs(mapped[0] / truth[0] - 1) < 0.01, mapped
    np.testing.assert_allclose(mapped[2:], stored[2:])  # COLMAP's mapper holds the centre


def test_no_estimate_and_no_model_say_both(
    tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """Where the mapper makes no model from the stored cameras either, the one error line
    says why the calibration had nothing (before, it was that reason alone)."""
    path = tmp_path / "database.db"
    synthesize(path, "PINHOLE", [1280.0, 1280.0, 512.0, 384.0], frames=6, points=20)
    result = run_main("run", tmp_path / "no-images", tmp_path / "ws", "--database", path)
    assert result.returncode == 2
    (line,) = result.stderr.splitlines()
    assert line.startswith("error: incremental mapping registered no images")
    assert line.endswith(
        "; nor did the calibration estimate a camera: camera 1: no image triplet with at "
        "least 30 three-view tracks"
    )


def test_an_input_error_still_stops_the_run(two_odd_cameras: Path, tmp_path: Path) -> None:
    """Only a missing estimate is mapped around: a prior no camera of this size has is an
    error, as before."""
    prior = (1e6, 1e6, 512.0, 384.0)
    options = ReconstructOptions(calibration=CalibrationOptions(prior=prior))
    with pytest.raises(CalibrationError, match="invalid starting intrinsics") as raised:
        reconstruct(two_odd_cameras, options=options)
    assert not isinstance(raised.value, NoEstimate)


def read_report(workspace: Path) -> dict:
    """The run's ``report.json``."""
    return json.loads((workspace / "report.json").read_text())
