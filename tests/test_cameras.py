"""Tests of colmap_trifocal.database.cameras against pycolmap's camera models."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.database.cameras import (
    SINGLE_FOCAL_MODELS,
    SUPPORTED_MODELS,
    CameraInfo,
    check_supported,
    undistort_to_pinhole,
)

WIDTH, HEIGHT = 1200, 800

#: A camera per supported model, with nonzero distortion where the model has any.
CAMERAS = {
    "SIMPLE_PINHOLE": [1000.0, 610.0, 395.0],
    "PINHOLE": [1000.0, 1040.0, 610.0, 395.0],
    "SIMPLE_RADIAL": [1000.0, 610.0, 395.0, -0.08],
    "RADIAL": [1000.0, 610.0, 395.0, -0.1, 0.03],
    "OPENCV": [1000.0, 1040.0, 610.0, 395.0, -0.1, 0.03, 0.001, -0.002],
}
#: (fx, fy, cx, cy) of the cameras above.
INTRINSICS = {
    "SIMPLE_PINHOLE": [1000.0, 1000.0, 610.0, 395.0],
    "PINHOLE": [1000.0, 1040.0, 610.0, 395.0],
    "SIMPLE_RADIAL": [1000.0, 1000.0, 610.0, 395.0],
    "RADIAL": [1000.0, 1000.0, 610.0, 395.0],
    "OPENCV": [1000.0, 1040.0, 610.0, 395.0],
}
DISTORTED = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")


def _camera(model: str, camera_id: int = 3) -> CameraInfo:
    return CameraInfo(camera_id, model, WIDTH, HEIGHT, np.array(CAMERAS[model]))


def _image_grid(n: int = 25) -> np.ndarray:
    """Pixel positions covering the whole image, borders included."""
    u, v = np.meshgrid(np.linspace(0.0, WIDTH, n), np.linspace(0.0, HEIGHT, n))
    return np.column_stack([u.ravel(), v.ravel()])


def test_model_lists() -> None:
    assert CAMERAS.keys() == set(SUPPORTED_MODELS)
    assert set(SINGLE_FOCAL_MODELS) <= set(SUPPORTED_MODELS)


@pytest.mark.parametrize("model", SUPPORTED_MODELS)
def test_intrinsics_and_k(model: str) -> None:
    camera = _camera(model)
    fx, fy, cx, cy = INTRINSICS[model]
    assert camera.single_focal == (model in SINGLE_FOCAL_MODELS)
    assert camera.intrinsics.shape == (4,)
    np.testing.assert_array_equal(camera.intrinsics, INTRINSICS[model])
    np.testing.assert_array_equal(camera.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    np.testing.assert_array_equal(camera.K, camera.to_pycolmap().calibration_matrix())


@pytest.mark.parametrize("model", SUPPORTED_MODELS)
def test_with_intrinsics_round_trip(model: str) -> None:
    camera = _camera(model)
    assert camera.with_intrinsics(*camera.intrinsics) == camera

    changed = camera.with_intrinsics(900.0, 920.0, 600.5, 401.25)
    if model in SINGLE_FOCAL_MODELS:
        np.testing.assert_array_equal(changed.intrinsics, [910.0, 910.0, 600.5, 401.25])
    else:
        np.testing.assert_array_equal(changed.intrinsics, [900.0, 920.0, 600.5, 401.25])
    # Distortion and everything else kept; the original is unchanged.
    np.testing.assert_array_equal(changed.distortion, camera.distortion)
    assert (changed.camera_id, changed.model, changed.width, changed.height) == (
        3,
        model,
        WIDTH,
        HEIGHT,
    )
    np.testing.assert_array_equal(camera.params, CAMERAS[model])
    back = changed.with_intrinsics(*INTRINSICS[model])
    assert back == camera


@pytest.mark.parametrize("model", SUPPORTED_MODELS)
def test_pycolmap_round_trip(model: str) -> None:
    camera = _camera(model)
    colmap_camera = camera.to_pycolmap()
    assert colmap_camera.model_name == model
    assert (colmap_camera.camera_id, colmap_camera.width, colmap_camera.height) == (
        3,
        WIDTH,
        HEIGHT,
    )
    np.testing.assert_array_equal(colmap_camera.params, CAMERAS[model])
    assert CameraInfo.from_pycolmap(colmap_camera) == camera


def test_params_are_read_only_and_checked() -> None:
    source = np.array(CAMERAS["OPENCV"])
    camera = CameraInfo(1, "OPENCV", WIDTH, HEIGHT, source)
    source[0] = 1.0  # the camera keeps its own copy
    assert camera.params[0] == 1000.0
    with pytest.raises(ValueError):
        camera.params[0] = 5.0
    with pytest.raises(ValueError, match="has 8 params"):
        CameraInfo(1, "OPENCV", WIDTH, HEIGHT, np.zeros(4))
    with pytest.raises(ValueError, match="unknown COLMAP camera model"):
        CameraInfo(1, "NOT_A_MODEL", WIDTH, HEIGHT, np.zeros(4))


@pytest.mark.parametrize("model", DISTORTED)
def test_undistort_inverts_img_from_cam(model: str) -> None:
    camera = _camera(model)
    assert np.any(camera.distortion != 0)
    colmap_camera = camera.to_pycolmap()
    # Normalised points whose pinhole projections cover the image.
    normalised = (_image_grid() - camera.intrinsics[2:]) / camera.intrinsics[:2]
    distorted = colmap_camera.img_from_cam(np.column_stack([normalised, np.ones(len(normalised))]))
    pinhole = normalised * camera.intrinsics[:2] + camera.intrinsics[2:]
    assert np.max(np.abs(distorted - pinhole)) > 5.0  # the distortion is not negligible

    undistorted = undistort_to_pinhole(camera, distorted)

    assert undistorted.shape == distorted.shape and undistorted.dtype == np.float64
    np.testing.assert_allclose(undistorted, pinhole, rtol=0, atol=1e-6)


@pytest.mark.parametrize("model", ["SIMPLE_PINHOLE", "PINHOLE"])
def test_undistort_pinhole_is_a_copy(model: str) -> None:
    camera = _camera(model)
    xy = _image_grid(5).astype(np.float32)
    result = undistort_to_pinhole(camera, xy)
    assert result.dtype == np.float64
    np.testing.assert_array_equal(result, xy)
    result[0] = -1.0
    assert xy[0, 0] == 0.0  # input not modified


def test_undistort_zero_distortion_is_identity() -> None:
    camera = CameraInfo(1, "OPENCV", WIDTH, HEIGHT, np.array([900.0, 950.0, 600, 400, 0, 0, 0, 0]))
    xy = _image_grid(7)
    result = undistort_to_pinhole(camera, xy)
    assert result is not xy
    np.testing.assert_array_equal(result, xy)


def test_undistort_empty() -> None:
    assert undistort_to_pinhole(_camera("RADIAL"), np.zeros((0, 2))).shape == (0, 2)


@pytest.mark.parametrize("model", SUPPORTED_MODELS)
def test_check_supported_accepts(model: str) -> None:
    check_supported(_camera(model))
    check_supported(_camera(model).to_pycolmap())


@pytest.mark.parametrize("model", ["OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE"])
def test_check_supported_rejects_fisheye(model: str) -> None:
    camera = CameraInfo.from_pycolmap(
        pycolmap.Camera.create_from_model_name(5, model, 800.0, WIDTH, HEIGHT)
    )
    with pytest.raises(CalibrationError) as info:
        check_supported(camera)
    message = str(info.value)
    assert "\n" not in message
    assert f"fisheye camera model {model} is not supported" in message
    assert "camera 5" in message
    assert all(name in message for name in SUPPORTED_MODELS)


def test_check_supported_rejects_other_models() -> None:
    camera = pycolmap.Camera.create_from_model_name(2, "FULL_OPENCV", 800.0, WIDTH, HEIGHT)
    with pytest.raises(CalibrationError, match="camera model FULL_OPENCV is not supported") as info:
        check_supported(camera)
    assert "fisheye" not in str(info.value)
