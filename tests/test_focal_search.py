"""The focal-length search that replaces a poor prior focal before the tensors are estimated."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest
from conftest import intrinsics_of, synthesize

from colmap_trifocal import CalibrationError, CalibrationOptions, calibrate_database
from colmap_trifocal.intrinsics.start.focal_search import (
    SEARCH_FACTORS,
    hypothesis_costs,
    search_focal,
)
from colmap_trifocal.synthetic.scenes import DEFAULT_INTRINSICS, make_scene

TRUTH = DEFAULT_INTRINSICS


def _triplet_tracks(seeds: list[int], noise_px: float) -> list[np.ndarray]:
    return [make_scene(noise_px=noise_px, seed=seed).observations for seed in seeds]


@pytest.mark.parametrize("factor", [0.6, 1.33, 1.8])
def test_search_finds_the_focal_from_far_off(factor: float) -> None:
    """From 40 % short to 80 % long, the search lands within one grid step (12 %)."""
    start = TRUTH * np.array([factor, factor, 1, 1])
    result = search_focal(
        _triplet_tracks([0, 1, 2], 0.5), start, np.random.default_rng(0), workers=1
    )
    assert abs(result.focal / np.sqrt(TRUTH[0] * TRUTH[1]) - 1) < 0.06
    assert result.costs.shape == SEARCH_FACTORS.shape
    assert np.all(np.isfinite(result.costs))
    # The truth lies inside the searched range, so the minimum is not at its edge.
    assert 0 < int(np.argmin(result.costs)) < len(SEARCH_FACTORS) - 1


def test_search_is_reproducible() -> None:
    tracks = _triplet_tracks([3, 4], 1.0)
    start = TRUTH * np.array([1.3, 1.3, 1, 1])
    first = search_focal(tracks, start, np.random.default_rng(5), workers=1)
    second = search_focal(tracks, start, np.random.default_rng(5), workers=2)
    assert first.focal == second.focal
    np.testing.assert_array_equal(first.costs, second.costs)


def test_each_focal_length_is_costed_on_its_own() -> None:
    """A focal length's cost does not depend on the others costed in the same call
    (OpenCV's RANSACs seed each call): the search costs the start with its fine grid,
    in one call, and must get what a call of its own gives. A quarter of the matches
    are wrong, so the RANSACs draw many samples."""
    tracks = make_scene(noise_px=1.0, outlier_ratio=0.25, seed=7).observations
    focal = float(np.sqrt(TRUTH[0] * TRUTH[1]))
    fine = focal * 1.25 ** np.linspace(-1.0, 1.0, 9)
    start = 1.3 * focal
    together = hypothesis_costs(tracks, np.append(fine, start), TRUTH[2:], 4.0)
    np.testing.assert_array_equal(together[:-1], hypothesis_costs(tracks, fine, TRUTH[2:], 4.0))
    np.testing.assert_array_equal(
        together[-1:], hypothesis_costs(tracks, np.array([start]), TRUTH[2:], 4.0)
    )
    assert np.argmin(together) == 4  # the truth, mid-grid


def test_calibration_from_a_prior_50_percent_off(tmp_path: Path) -> None:
    """A pycolmap synthetic database, exact keypoints: recovered from a 50 % wrong focal."""
    params = [1100.0, 1250.0, 530.0, 370.0]
    path = tmp_path / "database.db"
    pycolmap.set_random_seed(0)  # the scene must not depend on the tests run before
    synthesize(path, "PINHOLE", params)
    truth = intrinsics_of(params, "PINHOLE")
    prior = tuple(truth * np.array([1.5, 1.45, 1.06, 0.94]))
    (result,) = calibrate_database(path, CalibrationOptions(prior=prior))
    np.testing.assert_allclose(result.intrinsics, truth, rtol=1e-5)
    assert result.prior == prior
    # Without the re-estimation: with the prior's principal point 6 % off, the calibrated
    # hypotheses fit poorly at every focal length (costs 79–95 of at most 96 px²), so
    # the tracks do not clearly favour the search's minimum (3 % off, cost ratio 1.15
    # against the prior's, not decisive) and the prior stays the start (issue 13: a
    # flat curve must not replace a prior). The search's estimate is still reported.
    (searched,) = calibrate_database(path, CalibrationOptions(prior=prior, restart=False))
    assert searched.focal_search is not None and not searched.focal_search["used"]
    assert not searched.focal_search["decisive"]
    assert abs(searched.focal_search["focal"] / np.sqrt(truth[0] * truth[1]) - 1) < 0.06
    assert searched.start == prior
    (held,) = calibrate_database(
        path, CalibrationOptions(prior=prior, focal_search=False, restart=False)
    )
    assert held.start == prior


def test_no_prior_starts_from_colmaps_guess(tmp_path: Path) -> None:
    """--no-prior ignores a badly wrong stored camera and still recovers K."""
    params = [1100.0, 1250.0, 530.0, 370.0]
    path = tmp_path / "database.db"
    reconstruction = synthesize(path, "PINHOLE", params)
    (camera,) = reconstruction.cameras.values()
    truth = intrinsics_of(params, "PINHOLE")
    (result,) = calibrate_database(path, CalibrationOptions(no_prior=True))
    guess = 1.2 * max(camera.width, camera.height)
    assert result.prior == (guess, guess, camera.width / 2, camera.height / 2)
    np.testing.assert_allclose(result.intrinsics, truth, rtol=1e-5)
    with pytest.raises(CalibrationError, match="exclude each other"):
        calibrate_database(path, CalibrationOptions(no_prior=True, prior=tuple(truth)))
