"""Issue 13: hard scenes. Focal search over 5°–150°, held values from the best evidence,
the diagnosis of undetermined parameters, and mapping retried with relaxed initialisation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from colmap_trifocal import CalibrationError, CalibrationOptions, calibrate_contents
from colmap_trifocal.geometry.motion import moves_forward
from colmap_trifocal.geometry.tracks import MatchGraph, select_triplets
from colmap_trifocal.intrinsics.assess.diagnosis import diagnose
from colmap_trifocal.intrinsics.inputs.prior import default_guess
from colmap_trifocal.intrinsics.start.candidates import held_values
from colmap_trifocal.intrinsics.start.focal_search import FocalSearchResult, search_focal
from colmap_trifocal.reconstruction.mapping import (
    RetryPlan,
    describe_attempts,
    map_with_retries,
)
from colmap_trifocal.synthetic.database import scene_contents
from colmap_trifocal.synthetic.demo import make_demo_database
from colmap_trifocal.synthetic.lenses import narrow_lens, turntable, wide_lens
from colmap_trifocal.synthetic.motions import (
    driving_turn,
    forward_driving,
    general_motion,
    handheld_indoor,
    pure_translation,
    scene_from_poses,
)
from colmap_trifocal.synthetic.scenes import SyntheticScene, _as_generator


def _tracks(scene: SyntheticScene, count: int = 6) -> list[np.ndarray]:
    """Pixel tracks (3, n, 2) of the first selected triplets, as the calibration picks them."""
    contents = scene_contents(scene)
    ids = sorted(contents.image_camera)
    graph = MatchGraph(contents.matches, {i: len(k) for i, k in contents.keypoints.items()})
    triplets = select_triplets(graph, ids, 40, 20)
    return [
        np.stack(
            [contents.keypoints[i][t.keypoint_indices[:, v]] for v, i in enumerate(t.image_ids)]
        )
        for t in triplets[:count]
    ]


@pytest.mark.parametrize("make", [narrow_lens, wide_lens], ids=["10deg", "100deg"])
def test_search_reaches_narrow_and_wide_lenses_from_the_default_camera(make) -> None:
    """A 10° lens is 4.8× COLMAP's guess, a 100° lens 0.35×: outside the former 0.5–2× grid."""
    scene = make(seed=1)
    truth = scene.intrinsics[0]
    start = default_guess(scene.width, scene.height)
    result = search_focal(
        _tracks(scene), start, np.random.default_rng(0), workers=1, image_size=(640, 480)
    )
    error = abs(result.focal / truth - 1)
    assert error < 0.10
    assert error < 3 * result.relative_std  # the std it states covers its error
    assert result.favours_focal  # the default guess is far worse: the tensors start here
    # The 10° curve is not decisive (weak perspective): it never replaces the start in
    # the report; the 100° one is.
    assert result.improves_on_start == result.decisive


def test_search_keeps_a_good_prior_on_straight_forward_motion() -> None:
    """Every focal length explains a straight drive; the search must not replace a 5 % prior."""
    scene = forward_driving(seed=0, yaw_deg=0.0)
    prior = scene.intrinsics * np.array([1.05, 0.95, 1.05, 0.95])
    result = search_focal(
        _tracks(scene), prior, np.random.default_rng(0), workers=1, image_size=(3072, 2048)
    )
    assert not result.decisive
    assert not result.improves_on_start
    held, std, source = held_values(prior, result)
    assert source == "prior"
    np.testing.assert_array_equal(held, prior)


def test_held_focal_comes_from_a_search_that_beat_the_prior() -> None:
    prior = np.array([1200.0, 1100.0, 320.0, 240.0])
    search = FocalSearchResult(
        focal=2000.0,
        factors=np.ones(1),
        costs=np.ones(1),
        relative_std=0.03,
        decisive=True,
        start_ratio=4.0,
    )
    held, std, source = held_values(prior, search)
    assert source == "focal-search"
    assert np.sqrt(held[0] * held[1]) == pytest.approx(2000.0)
    assert held[1] / held[0] == pytest.approx(1100.0 / 1200.0)  # the prior's aspect kept
    np.testing.assert_array_equal(held[2:], prior[2:])
    assert std[0] == std[1] == 0.03


def _planar_facade(seed: int = 0) -> SyntheticScene:
    """Cameras moving sideways and rotating in front of one wall (points on z = 10)."""
    rng = _as_generator(seed)
    points = np.stack(
        [rng.uniform(-6, 6, 2000), rng.uniform(-4, 4, 2000), np.full(2000, 10.0)], axis=1
    )
    angles = np.deg2rad(np.linspace(-8, 8, 6))
    c, s = np.cos(angles), np.sin(angles)
    rotations = np.stack(
        [np.array([[ci, 0, -si], [0, 1, 0], [si, 0, ci]]) for ci, si in zip(c, s, strict=True)]
    )
    rotations = rotations @ np.array(
        [[1, 0, 0], [0, np.cos(0.1), -np.sin(0.1)], [0, np.sin(0.1), np.cos(0.1)]]
    )
    centers = np.stack([np.linspace(-2, 2, 6), np.zeros(6), np.zeros(6)], axis=1)
    return scene_from_poses(rotations, centers, points, 0.5, rng)


@pytest.mark.parametrize(
    ("make", "cause"),
    [
        (lambda: forward_driving(seed=0, yaw_deg=0.0), "forward motion with little rotation"),
        (lambda: driving_turn(seed=0), "rotation about one axis (planar motion; camera y"),
        (lambda: pure_translation(seed=0), "pure translation"),
        (lambda: _planar_facade(0), "planar structure"),
        (lambda: general_motion(seed=0), "no degenerate motion found"),
    ],
    ids=["forward", "turn", "translation", "facade", "general"],
)
def test_diagnosis_names_the_cause_the_tracks_show(make, cause: str) -> None:
    scene = make()
    assert cause in diagnose(_tracks(scene), scene.intrinsics)


def test_diagnosis_reports_too_few_tracks() -> None:
    scene = general_motion(seed=0)
    tracks = [x[:, :30] for x in _tracks(scene)]
    assert "too few tracks (median 30 per triplet)" in diagnose(tracks, scene.intrinsics)


def test_narrow_lens_from_the_default_camera() -> None:
    """The 11° turntable of issue 13 ended 43 % off from the default camera."""
    scene = narrow_lens(seed=0)
    (result,) = calibrate_contents(
        scene_contents(scene), CalibrationOptions(no_prior=True, seed=0, workers=1)
    )
    error = np.abs(result.intrinsics / scene.intrinsics - 1)
    assert error[0] < 0.01 and error[1] < 0.01
    assert result.source["fx"] == "trifocal" and result.observable["fx"]
    assert result.focal_search is not None and result.focal_search["used"]
    data = result.to_json()
    assert set(data["source"]) == {"fx", "fy", "cx", "cy"}
    # Every reported std covers its parameter's error within 3 std.
    for index, name in enumerate(("fx", "fy", "cx", "cy")):
        std = data["std"][name]
        if std is not None:
            assert abs(result.intrinsics[index] - scene.intrinsics[index]) < 3 * std


def test_forward_motion_tells_a_drive_from_a_turntable() -> None:
    """Both are sequences by their view graphs; only the drive moves forward."""
    for scene, forward in ((driving_turn(seed=0), True), (turntable(seed=0), False)):
        contents = scene_contents(scene)
        assert moves_forward(contents.keypoints, contents.matches, scene.intrinsics) is forward
        guess = default_guess(scene.width, scene.height)
        assert moves_forward(contents.keypoints, contents.matches, guess) is forward


@pytest.mark.parametrize("seed", [0, 1])
def test_turntable_with_a_narrow_lens_from_the_default_camera(seed: int) -> None:
    """Issue 13's 11° turntable ended 43 % off from the default camera (f = 768 px).

    The synthetic one ended 52 % off, held at the default guess: 0 of 20 tensors
    agreed there, and the sequence selection picked wide, weak triplets. Now a ring
    keeps the general selection and the tensors are estimated again from the focal
    search's candidates: seed 0 from its minimum (2410 px; result 0.06 % off), seed 1
    only from its third local minimum (1096 and 1237 px: 0 of 20 agree; 1930 px:
    19 agree, result 0.8 % off).
    """
    scene = turntable(seed=seed)
    (result,) = calibrate_contents(
        scene_contents(scene), CalibrationOptions(no_prior=True, seed=seed, workers=1)
    )
    error = abs(result.intrinsics[0] / scene.intrinsics[0] - 1)
    assert error < 0.02
    assert result.source["fx"] == "trifocal" and result.num_inlier_triplets >= 15
    std = result.std["fx"]
    assert std is not None and error * scene.intrinsics[0] < 3 * std


def test_small_handheld_set_from_the_default_camera() -> None:
    """17 VGA frames walked 0.5 m across a room (issue 13's handheld case, synthetic):
    a short baseline and 300 noisy tracks still determine every parameter to < 1.5 %
    of the focal length, and each stated std covers its error within 3 std."""
    scene = handheld_indoor(seed=1)
    (result,) = calibrate_contents(
        scene_contents(scene), CalibrationOptions(no_prior=True, seed=1, workers=1)
    )
    error = np.abs(result.intrinsics - scene.intrinsics)
    assert np.all(error / scene.intrinsics[0] < 0.015)
    assert result.observable["fx"] and result.observable["cx"]
    for index, name in enumerate(("fx", "fy", "cx", "cy")):
        std = result.std[name]
        if std is not None:
            assert error[index] < 3 * std


def test_mapping_retries_with_relaxed_initialisation(tmp_path: Path) -> None:
    """No pair reaches 360° (nor 90°, where COLMAP's own relaxation stops): no model.

    The retry at 4° registers every image, and the report line says what was done.
    """
    database = tmp_path / "demo.db"
    make_demo_database(database, seed=1, num_images=6, num_points=400)
    model, attempts, _ = map_with_retries(
        database, None, tmp_path / "out", plan=RetryPlan(angles=(360.0, 4.0))
    )
    assert [a.init_min_tri_angle for a in attempts] == [360.0, 4.0]
    assert attempts[0].num_registered_images == 0
    assert attempts[1].num_registered_images == model.num_reg_images() == 6
    assert describe_attempts(attempts) == (
        "mapping retried with relaxed initialisation (init_min_tri_angle 360°: 0/6, 4°: 6/6 "
        "registered)"
    )
    with pytest.raises(CalibrationError, match="no initial pair at 360°"):
        map_with_retries(database, None, tmp_path / "none", plan=RetryPlan(angles=(360.0,)))
