"""Shared fixtures: real Strecha databases (built once per session) and synthetic ones."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_trifocal.database.features import build_database
from colmap_trifocal.datasets.strecha import default_datasets_root, scene_images

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def strecha_root() -> Path:
    """The ``strecha`` folder, or skip (fail under CI=true) when it is absent."""
    return shared_dataset("strecha")


def shared_dataset(relative: str) -> Path:
    """A folder of ``../shared/datasets``, or skip (fail under CI=true) when it is absent."""
    root = default_datasets_root(PROJECT_ROOT) / relative
    if not root.is_dir():
        message = f"{relative} not found at {root} (set COLMAP_TRIFOCAL_DATASETS)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
    return root


@pytest.fixture(scope="session")
def strecha_database(tmp_path_factory: pytest.TempPathFactory):
    """Factory: scene name -> (database path, scene folder), SIFT at 1600 px, exhaustive.

    Built once per session (about a minute per scene on 2 cores).
    """
    built: dict[str, Path] = {}

    def get(scene: str) -> tuple[Path, Path]:
        folder = strecha_root() / scene
        if scene not in built:
            database = tmp_path_factory.mktemp(scene) / "database.db"
            built[scene] = build_database(folder / "images", database, scene_images(folder))
        return built[scene], folder

    return get


def synthesize(
    path: Path,
    model: str = "SIMPLE_RADIAL",
    params: list[float] | None = None,
    cameras: int = 1,
    frames: int = 6,
    points: int = 400,
) -> pycolmap.Reconstruction:
    """A pycolmap synthetic database (exact keypoints) and its ground truth."""
    options = pycolmap.SyntheticDatasetOptions(
        num_rigs=1,
        num_cameras_per_rig=cameras,
        num_frames_per_rig=frames,
        num_points3D=points,
        camera_model_id=getattr(pycolmap.CameraModelId, model),
    )
    if params is not None:
        options.camera_params = params
    with pycolmap.Database.open(str(path)) as db:
        return pycolmap.synthesize_dataset(options, db)


def intrinsics_of(params: list[float], model: str) -> np.ndarray:
    """(fx, fy, cx, cy) of COLMAP params."""
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        return np.array([params[0], params[0], params[1], params[2]])
    return np.array(params[:4])
