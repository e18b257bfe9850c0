"""Parametrizations, the observability test and the jackknife, on hand-made information."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_trifocal.intrinsics.solve.observability import (
    MAX_RELATIVE_STD,
    effective_std,
    relative_std,
    select_free_parameters,
    tolerance,
)
from colmap_trifocal.intrinsics.solve.parametrization import (
    FULL,
    HELD,
    SINGLE_FOCAL,
    FreeParameters,
    candidate_free_parameters,
)
from colmap_trifocal.intrinsics.solve.theta import intrinsics_to_theta, theta_to_intrinsics
from colmap_trifocal.intrinsics.solve.uncertainty import (
    combined_information,
    image_groups,
    is_sequence,
    jackknife_covariance,
    jackknife_replicates,
)

START = np.array([2700.0, 2750.0, 1500.0, 1000.0])
PRIOR = np.array([2650.0, 2800.0, 1530.0, 990.0])
TOLERANCES = tolerance(START, 3072, 2048)


def information_from_std(std: np.ndarray) -> np.ndarray:
    """Diagonal information (4, 4) of independent θ with these relative stds (inf: none)."""
    return np.diag(np.where(np.isfinite(std), 1.0 / np.asarray(std) ** 2, 0.0))


@pytest.mark.parametrize("free_parameters", candidate_free_parameters(FULL))
def test_parametrization_round_trip_and_held_values(free_parameters: FreeParameters) -> None:
    parametrization = free_parameters.parametrization(START, PRIOR)
    rng = np.random.default_rng(0)
    free = rng.normal(0.0, 0.02, parametrization.dimension)
    theta = parametrization.theta(free)
    np.testing.assert_allclose(parametrization.free(theta), free, atol=1e-15)
    intrinsics = theta_to_intrinsics(theta, START)
    if free_parameters.focal == "tied":
        assert intrinsics[1] == pytest.approx(intrinsics[0], rel=1e-14)  # fy = fx in pixels
    if free_parameters.focal == "held":
        np.testing.assert_allclose(intrinsics[:2], PRIOR[:2], rtol=1e-14)
    for index, free_pp in ((2, free_parameters.cx), (3, free_parameters.cy)):
        if not free_pp:
            assert intrinsics[index] == pytest.approx(PRIOR[index], rel=1e-14)
    # p = 0 is the start, with held parameters at the prior.
    start = theta_to_intrinsics(parametrization.theta(np.zeros(parametrization.dimension)), START)
    expected = START.copy()
    if free_parameters.focal == "tied":
        expected[1] = START[0]
    if free_parameters.focal == "held":
        expected[:2] = PRIOR[:2]
    expected[2:] = np.where([free_parameters.cx, free_parameters.cy], START[2:], PRIOR[2:])
    np.testing.assert_allclose(start, expected, rtol=1e-14)


def test_candidate_free_parameters_are_subsets_largest_first() -> None:
    subsets = candidate_free_parameters(FULL)
    assert subsets[0] == FULL and subsets[-1] == HELD and len(subsets) == 12
    assert [m.dimension for m in subsets] == sorted((m.dimension for m in subsets), reverse=True)
    single = candidate_free_parameters(SINGLE_FOCAL)
    assert all(m.focal != "free" for m in single) and single[0] == SINGLE_FOCAL
    assert theta_to_intrinsics(intrinsics_to_theta(PRIOR, START), START) == pytest.approx(PRIOR)


def test_relative_std_of_a_null_direction_is_infinite() -> None:
    information = information_from_std(np.array([0.001, np.inf, 0.002, 0.003]))
    std = relative_std(information, FULL.parametrization(START, PRIOR))
    np.testing.assert_allclose(std[[0, 2, 3]], [0.001, 0.002, 0.003], rtol=1e-9)
    assert std[1] == np.inf
    # Tying fy to fx removes the null direction.
    tied = relative_std(information, SINGLE_FOCAL.parametrization(START, PRIOR))
    assert np.all(np.isfinite(tied))


def test_noise_free_null_direction_is_caught_by_the_eigenvalue_ratio() -> None:
    """Whitening by a tiny noise makes every direction look certain in absolute terms."""
    information = information_from_std(np.array([1e-9, 1e-3, 1e-9, 1e-9]))
    std = relative_std(information, FULL.parametrization(START, PRIOR))
    assert std[1] == np.inf and np.all(std[[0, 2, 3]] < 1e-8)


def test_undetermined_fy_is_tied_to_fx() -> None:
    information = information_from_std(np.array([0.001, 0.08, 0.001, 0.001]))
    free_parameters = select_free_parameters(information, FULL, FULL, START, PRIOR, TOLERANCES)
    assert free_parameters == FreeParameters("tied")
    assert free_parameters.assumptions() == ["fy = fx"]
    assert free_parameters.estimated(single_focal=False) == {
        "fx": True,
        "fy": False,
        "cx": True,
        "cy": True,
    }


def test_weakly_determined_parameters_are_still_estimated() -> None:
    """Between 1 and 3 tolerances: estimated (not observable), never held at the prior."""
    weak_principal_point = 1.5 * TOLERANCES[2:]
    information = information_from_std(np.r_[0.001, 0.001, weak_principal_point])
    assert select_free_parameters(information, FULL, FULL, START, PRIOR, TOLERANCES) == FULL
    # A weak focal length pair is estimated as one focal length (square pixels), not held.
    information = information_from_std(np.array([0.015, 0.015, 0.001, 0.001]))
    assert select_free_parameters(
        information, FULL, FULL, START, PRIOR, TOLERANCES
    ) == FreeParameters("tied")
    information = information_from_std(np.array([0.04, 0.04, 0.001, 0.001]))
    assert select_free_parameters(information, FULL, FULL, START, PRIOR, TOLERANCES).focal != "free"


@pytest.mark.parametrize("weak_fy", [0.012, 0.026])
def test_fy_known_worse_than_the_aspect_ratio_is_tied(weak_fy: float) -> None:
    """Planar motion with some pitch (a car): fy 1.2–2.6 % against fx 0.7 %.

    Square pixels (``TIED_ASPECT_STD``, 1 %) are the better evidence for fy then;
    on the shared KITTI drive this took fy from −5.4 % (estimated, std 19 px) to
    −2.7 % (tied to fx).
    """
    information = information_from_std(np.array([0.007, weak_fy, 0.001, 0.001]))
    assert select_free_parameters(
        information, FULL, FULL, START, PRIOR, TOLERANCES
    ) == FreeParameters("tied")
    information = information_from_std(np.array([0.007, 0.009, 0.001, 0.001]))
    assert select_free_parameters(information, FULL, FULL, START, PRIOR, TOLERANCES) == FULL


def test_nothing_determined_holds_everything() -> None:
    information = information_from_std(np.array([0.3, 0.2, 0.1, 0.1]))
    free_parameters = select_free_parameters(information, FULL, FULL, START, PRIOR, TOLERANCES)
    assert free_parameters == HELD
    assert free_parameters.assumptions() == ["fx, fy held at the prior", "cx, cy held at the prior"]


def test_all_determined_keeps_all_four_free() -> None:
    information = information_from_std(np.full(4, 0.2 * MAX_RELATIVE_STD))
    assert select_free_parameters(information, FULL, FULL, START, PRIOR, TOLERANCES) == FULL


def test_principal_point_tolerance_is_relative_to_the_image_size() -> None:
    """cx std 2.0 % of f is 3.5 % of half the width: beyond 3 tolerances, held."""
    np.testing.assert_allclose(TOLERANCES, 0.01 * np.array([1, 1, 1536 / 2700, 1024 / 2750]))
    information = information_from_std(np.array([0.001, 0.001, 0.020, 0.001]))
    free_parameters = select_free_parameters(information, FULL, FULL, START, PRIOR, TOLERANCES)
    assert free_parameters == FreeParameters("free", cx=False, cy=True)
    assert free_parameters.assumptions() == ["cx held at the prior"]


def test_parameter_coupled_to_a_held_one_is_held_too() -> None:
    """Only fx + cy and cx are determined: cy alone would absorb a held fx's error.

    With fx held exactly, cy's conditional std would be tiny; counting the held
    value's own uncertainty (30 %) shows that cy is not determined.
    """
    rows = np.array([[1.0, 0.0, 0.0, 1.0], [0.0, 0.0, 1.0, 0.0]]) * 1e4
    information = rows.T @ rows
    held_focal = FreeParameters("held")
    conditional = relative_std(information, held_focal.parametrization(START, PRIOR))
    assert conditional[3] < 1e-3
    effective = effective_std(information, held_focal, FULL, START, PRIOR)
    assert effective[3] > MAX_RELATIVE_STD and effective[2] < MAX_RELATIVE_STD
    free_parameters = select_free_parameters(information, FULL, FULL, START, PRIOR, TOLERANCES)
    assert free_parameters == FreeParameters("held", cx=True, cy=False)


def test_single_focal_camera_reports_fy_with_fx() -> None:
    assert SINGLE_FOCAL.estimated(single_focal=True)["fy"]
    assert not SINGLE_FOCAL.estimated(single_focal=False)["fy"]
    assert SINGLE_FOCAL.assumptions() == ["fy = fx"]


def test_image_groups_deal_unordered_images_round_robin() -> None:
    # Triplets spanning most of the images (matched in no order): not a sequence.
    ids = [(1, 4, 6), (2, 3, 5), (1, 3, 6)]
    assert not is_sequence(ids)
    assert image_groups(ids, max_groups=4) == [{1, 5}, {2, 6}, {3}, {4}]
    assert image_groups([(1, 2, 3)], max_groups=10) == [{1}, {2}, {3}]


def test_image_groups_of_a_sequence_are_consecutive_blocks() -> None:
    # Triplets of consecutive frames: deleting a block removes a stretch of the sequence.
    ids = [(1, 2, 3), (2, 3, 4), (4, 5, 6), (5, 6, 8), (7, 8, 9)]
    assert is_sequence(ids)
    assert image_groups(ids, max_groups=4) == [{1, 2}, {3, 4}, {5, 6}, {7, 8, 9}]
    # A ring whose triplets close the loop spans more than half the images.
    assert not is_sequence([(1, 2, 3), (3, 4, 5), (5, 6, 1)])


def test_jackknife_needs_enough_groups() -> None:
    def resolve(keep: np.ndarray) -> np.ndarray:
        return np.full(4, float(keep.sum()))

    assert jackknife_replicates([(1, 2, 3)], resolve) is None  # dropping any image empties it
    ids = [(1, 2, 3), (4, 5, 6), (1, 5, 6), (2, 4, 6), (3, 4, 5)]
    replicates = jackknife_replicates(ids, resolve)
    assert replicates is not None and replicates.shape == (6, 4)


def test_jackknife_covariance_of_known_replicates() -> None:
    replicates = np.array([[1.0], [2.0], [3.0], [4.0]])
    # (g − 1)/g Σ (x − x̄)² = 3/4 · 5
    np.testing.assert_allclose(jackknife_covariance(replicates), [[3.75]])


def test_combined_information_keeps_the_larger_variance_per_direction() -> None:
    curvature = information_from_std(np.array([0.001, 0.001, 0.001, 0.001]))
    parametrization = FULL.parametrization(START, PRIOR)
    rng = np.random.default_rng(1)
    # Replicates spread 0.005 in fx only (10x the variance of the curvature in fx? 25x).
    replicates = np.zeros((8, 4))
    replicates[:, 0] = rng.normal(0.0, 0.005, 8)
    spread = np.sqrt(jackknife_covariance(replicates)[0, 0])
    combined = combined_information(curvature, replicates, parametrization)
    std = relative_std(combined, parametrization)
    assert std[0] == pytest.approx(spread, rel=1e-6)
    np.testing.assert_allclose(std[1:], 0.001, rtol=1e-6)
    # Without replicates: the curvature alone.
    alone = relative_std(combined_information(curvature, None, parametrization), parametrization)
    np.testing.assert_allclose(alone, 0.001, rtol=1e-9)


def test_warning_names_weak_and_held_parameters() -> None:
    from colmap_trifocal.intrinsics.results import CameraCalibration

    def calibration(
        std: dict, observable: dict, assumptions: list[str], estimated: dict | None = None
    ) -> CameraCalibration:
        return CameraCalibration(
            camera_id=3,
            model="PINHOLE",
            method="msac-opt",
            fx=2760.0,
            fy=2760.0,
            cx=1520.0,
            cy=1000.0,
            std=std,
            observable=observable,
            num_triplets=20,
            num_inlier_triplets=18,
            prior=(2700.0, 2700.0, 1536.0, 1024.0),
            start=(2700.0, 2700.0, 1536.0, 1024.0),
            assumptions=assumptions,
            estimated=estimated or dict.fromkeys(("fx", "fy", "cx", "cy"), True),
            unconstrained_std={"fx": 41.0, "fy": 230.0, "cx": 3.0, "cy": 4.0},
        )

    everything = dict.fromkeys(("fx", "fy", "cx", "cy"), True)
    assert calibration(dict.fromkeys(everything, 2.0), everything, []).warning() is None
    planar = calibration(
        {"fx": 41.0, "fy": None, "cx": 3.0, "cy": 4.0},
        {"fx": False, "fy": False, "cx": True, "cy": True},
        ["fy = fx"],
        {"fx": True, "fy": False, "cx": True, "cy": True},
    )
    assert planar.warning() == (
        "camera 3: fy (std 230 px) not determined by these images (planar motion: all "
        "rotations about one axis?); fy = fx; fx (std 41 px) only weakly determined, "
        "kept as estimated"
    )

    # The Fundamental baseline has no std; a failed fit is reported, without a dangling "; ".
    failed = calibration(dict.fromkeys(everything), dict.fromkeys(everything, False), [])
    assert failed.warning() == "camera 3: fx, fy, cx, cy only weakly determined, kept as estimated"
