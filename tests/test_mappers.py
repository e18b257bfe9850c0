"""``run`` with COLMAP-default databases (one camera per image) and ``--mapper global``."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from test_camera_groups import TRUTH, per_image_database

from colmap_trifocal import CalibrationError
from colmap_trifocal.reconstruction.workflow import RunOptions, run_pipeline


def _intrinsics(values: dict) -> np.ndarray:
    return np.array([values[k] for k in ("fx", "fy", "cx", "cy")])


@pytest.fixture(scope="module")
def default_database(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("per_image") / "database.db"
    per_image_database(path, images=8, points=800)
    return path


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_run_groups_per_image_cameras_and_maps(
    mapper: str, default_database: Path, tmp_path: Path
) -> None:
    before = hashlib.sha256(default_database.read_bytes()).hexdigest()
    workspace = tmp_path / "ws"
    report = run_pipeline(
        None, workspace, RunOptions(database=default_database, mapper=mapper)
    ).to_json()
    assert hashlib.sha256(default_database.read_bytes()).hexdigest() == before
    assert report["mapper"] == mapper
    assert report["num_registered_images"] == 8
    (camera,) = report["cameras"]
    assert camera["camera_ids"] == list(range(1, 9))
    assert camera["num_registered_images"] == 8
    assert np.mean(np.abs(_intrinsics(camera["trifocal"]) / TRUTH - 1)) < 1e-4
    assert np.mean(np.abs(_intrinsics(camera["refined"]) / TRUTH - 1)) < 1e-3
    model = pycolmap.Reconstruction(workspace / "sparse" / "0")
    # The group's images share one camera in the model (refined once, not per image).
    assert list(model.cameras) == [1]
    assert {image.camera_id for image in model.images.values()} == {1}


def test_unknown_mapper(default_database: Path, tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="unknown --mapper 'sequential'"):
        run_pipeline(
            None, tmp_path / "ws", RunOptions(database=default_database, mapper="sequential")
        )
