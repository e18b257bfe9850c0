"""Real SIFT matches: the accuracy bar on the Strecha scenes against gt_dense_cameras."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from colmap_trifocal import CalibrationOptions, calibrate_database
from colmap_trifocal.datasets.strecha import ground_truth_intrinsics, read_camera_file

GROUND_TRUTH = np.array([2759.48, 2764.16, 1520.69, 1006.81])
SCENES = ["fountain-P11", "Herz-Jesus-P8"]
SEEDS = [0, 1, 2]


def mean_relative_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    return float(np.mean(np.abs(estimate / truth - 1)))


def test_camera_file_reader(tmp_path: Path) -> None:
    path = tmp_path / "0000.jpg.camera"
    path.write_text(
        "2759.48 0 1520.69\n0 2764.16 1006.81\n0 0 1\n0 0 0\n"
        "1 0 0\n0 1 0\n0 0 1\n1.5 -2 3\n3072 2048\n"
    )
    camera = read_camera_file(path)
    np.testing.assert_allclose(camera.intrinsics, GROUND_TRUTH)
    np.testing.assert_allclose(camera.centre, [1.5, -2, 3])
    assert (camera.width, camera.height) == (3072, 2048)


@pytest.mark.real_data
@pytest.mark.parametrize("scene", SCENES)
def test_msac_opt_accuracy_bar(scene: str, strecha_database) -> None:
    """msac-opt from a ±5 % prior: mean error ≤ 0.5 %, no seed above 1 %."""
    database, folder = strecha_database(scene)
    truth = ground_truth_intrinsics(folder)
    np.testing.assert_allclose(truth, GROUND_TRUTH, rtol=1e-6)
    errors = []
    for seed in SEEDS:
        prior = truth * (1 + np.random.default_rng(100 + seed).uniform(-0.05, 0.05, 4))
        (result,) = calibrate_database(database, CalibrationOptions(prior=tuple(prior), seed=seed))
        errors.append(mean_relative_error(result.intrinsics, truth))
        assert result.num_inlier_triplets >= 10
    assert np.mean(errors) <= 0.005, errors
    assert max(errors) <= 0.01, errors


@pytest.mark.real_data
def test_msac_and_fundamental_on_fountain(strecha_database) -> None:
    """msac alone is within 1 %; TrifocalCalib beats the Fundamental baseline."""
    database, folder = strecha_database("fountain-P11")
    truth = ground_truth_intrinsics(folder)
    prior = tuple(truth * np.array([1.04, 0.96, 0.97, 1.03]))
    (msac,) = calibrate_database(database, CalibrationOptions(method="msac", prior=prior))
    (fundamental,) = calibrate_database(
        database, CalibrationOptions(method="fundamental", prior=prior)
    )
    msac_error = mean_relative_error(msac.intrinsics, truth)
    assert msac_error <= 0.01
    assert msac_error < mean_relative_error(fundamental.intrinsics, truth)


@pytest.mark.real_data
@pytest.mark.parametrize("scene", SCENES)
def test_from_colmap_default_camera(scene: str, strecha_database) -> None:
    """No prior: the database holds COLMAP's guess f = 1.2 · 3072 (33 % too long)."""
    database, folder = strecha_database(scene)
    truth = ground_truth_intrinsics(folder)
    (result,) = calibrate_database(database)
    assert result.prior[0] == pytest.approx(1.2 * 3072)
    assert abs(result.start[0] / truth[0] - 1) < 0.05  # the focal search
    assert mean_relative_error(result.intrinsics, truth) <= 0.005
    # Measured 27-28 of 30 (10 of 30 before the focal search: plane-dominated tensors).
    assert result.num_inlier_triplets >= 0.75 * result.num_triplets


@pytest.mark.real_data
def test_wide_priors_on_fountain(strecha_database) -> None:
    """Priors 10-30 % off per parameter (random signs): the same accuracy as ±5 %."""
    database, folder = strecha_database("fountain-P11")
    truth = ground_truth_intrinsics(folder)
    for seed in SEEDS:
        rng = np.random.default_rng(200 + seed)
        prior = truth * (1 + rng.choice([-1, 1], 4) * rng.uniform(0.10, 0.30, 4))
        (result,) = calibrate_database(database, CalibrationOptions(prior=tuple(prior), seed=seed))
        assert mean_relative_error(result.intrinsics, truth) <= 0.005, (prior, result.intrinsics)
