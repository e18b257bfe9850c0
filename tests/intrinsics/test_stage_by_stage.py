"""Each stage of intrinsics/ through its own function, on one small synthetic camera.

The stages in the pipeline's order (:mod:`colmap_trifocal.intrinsics.pipeline`): the
attempts (tensors and their solve), the hold, the polish, the lens warp, the lens stage
and the assessment, each given what the stage before it gave, as the pipeline does.
"""

from __future__ import annotations

import numpy as np
import pytest

from colmap_trifocal import CalibrationOptions
from colmap_trifocal.common.timing import StageClock
from colmap_trifocal.database.cameras import CameraInfo
from colmap_trifocal.intrinsics.assess.assessment import AssessInput, assess
from colmap_trifocal.intrinsics.inputs.camera_input import CameraInput, camera_input
from colmap_trifocal.intrinsics.inputs.triplet_selection import (
    CameraTracks,
    select_camera_triplets,
)
from colmap_trifocal.intrinsics.lens.distortion import DistortionInput, estimate_distortion
from colmap_trifocal.intrinsics.lens.search import DIVISION, LensSearchResult
from colmap_trifocal.intrinsics.lens.warp import lens_search_applies, warped_input
from colmap_trifocal.intrinsics.polish.bundle import PolishInput
from colmap_trifocal.intrinsics.polish.stage import polish
from colmap_trifocal.intrinsics.results import JSON_KEYS
from colmap_trifocal.intrinsics.start.candidates import first_start
from colmap_trifocal.intrinsics.tensors.attempts import (
    MIN_AGREEING,
    Attempt,
    AttemptInputs,
    attempt,
    checked_estimate,
    consensus,
    held_where_nothing_agrees,
    majority,
)
from colmap_trifocal.intrinsics.tensors.estimator import TensorEstimator
from colmap_trifocal.synthetic.database import CAMERA_ID, scene_contents
from colmap_trifocal.synthetic.motions import general_motion

#: A start 4 % off in every parameter.
START_ERROR = np.array([1.04, 0.96, 1.04, 0.96])


def _relative_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    return float(np.max(np.abs(np.asarray(estimate) / truth - 1.0)))


@pytest.fixture(scope="module")
def camera() -> tuple[AttemptInputs, np.ndarray]:
    """The attempts' inputs of a 6-view general-motion camera (0.5 px noise) from a
    start 4 % off, and the true (fx, fy, cx, cy)."""
    scene = general_motion(num_images=6, seed=2, noise_px=0.5)
    contents = scene_contents(scene)
    options = CalibrationOptions(prior=tuple(scene.intrinsics * START_ERROR), workers=1)
    images = sorted(contents.keypoints)
    data = camera_input(contents, contents.cameras[CAMERA_ID], images, options.start_options)
    tracks = select_camera_triplets(data, images, options.track_options, options.work_options)
    seeds = np.random.SeedSequence(0).spawn(len(tracks.triplets))
    estimator = TensorEstimator(tracks, CAMERA_ID, options, seeds)
    return AttemptInputs(data, tracks, estimator, "msac-opt", options, StageClock()), (
        scene.intrinsics
    )


@pytest.fixture(scope="module")
def first(camera: tuple[AttemptInputs, np.ndarray]) -> Attempt:
    inputs, _ = camera
    return attempt(inputs, first_start(inputs.data.prior, None))


def test_an_attempt_solves_its_tensors_from_the_start(camera, first: Attempt) -> None:
    """Every tensor agrees with an estimate near the truth; the work is counted in the
    camera's budget and timed as the tensors and solve stages."""
    inputs, truth = camera
    assert first.majority_agrees and consensus(first.fallback)
    assert first.agreeing == len(first.tensors.tensors) >= MIN_AGREEING
    estimate = checked_estimate(first, CAMERA_ID, "msac-opt")
    assert _relative_error(estimate, truth) < 0.005
    assert 0 < inputs.estimator.starts_used <= inputs.estimator.budget
    assert {"tensors", "solve"} <= set(inputs.clock.seconds)


def test_the_hold_keeps_an_agreed_estimate_and_holds_one_nothing_agrees_with(
    camera, first: Attempt
) -> None:
    inputs, _ = camera
    assert held_where_nothing_agrees(inputs, first) is first
    nobody = first.fallback.solution.inlier_tensors.copy()
    nobody[:] = False
    assert not majority(nobody)
    lonely = Attempt(
        first.candidate,
        first.tensors,
        type(first.fallback)(**{**vars(first.fallback), "solution": _without_inliers(first)}),
    )
    held = held_where_nothing_agrees(inputs, lonely)
    assert held.fallback.free_parameters.dimension == 0  # every value held at the start
    np.testing.assert_allclose(
        checked_estimate(held, CAMERA_ID, "direct"), first.candidate.held, rtol=1e-12
    )


def _without_inliers(first: Attempt):
    solution = first.fallback.solution
    return type(solution)(
        **{**vars(solution), "inlier_tensors": np.zeros_like(solution.inlier_tensors)}
    )


def test_the_polish_keeps_or_refuses_with_a_reason(camera, first: Attempt) -> None:
    """On tensors that all agree the polish either replaces the estimate by one at
    least as close to the truth or keeps it and says why."""
    inputs, truth = camera
    estimate = checked_estimate(first, CAMERA_ID, "msac-opt")
    polished = polish(
        PolishInput(
            first.tensors.tensors,
            inputs.tracks.by_images(),
            first.tensors.start,
            estimate,
            first.fallback,
            first.agreeing,
            (inputs.data.camera.width, inputs.data.camera.height),
            inputs.options.tau,
            CAMERA_ID,
            workers=1,
        )
    )
    assert polished.summary is not None
    if polished.summary["used"]:
        assert _relative_error(polished.intrinsics, truth) < 0.005
    else:
        assert polished.summary["rejected"]
        np.testing.assert_array_equal(polished.intrinsics, estimate)


def test_the_lens_stage_finds_no_distortion_in_a_pinhole_camera(camera, first: Attempt) -> None:
    inputs, _ = camera
    estimate = checked_estimate(first, CAMERA_ID, "msac-opt")
    lens = estimate_distortion(
        DistortionInput(
            first.tensors.tensors,
            inputs.tracks.by_images(),
            first.tensors.start,
            estimate,
            first.fallback.free_parameters,
            inputs.data.camera,
            inputs.options.tau,
            workers=1,
        )
    )
    assert lens is None or not lens.present


def test_the_lens_warp_applies_to_cameras_storing_no_distortion(camera) -> None:
    """A pinhole camera too: its lens stage fits OPENCV (it stays pinhole); never a
    stored distortion, or another variant than the polished one."""
    inputs, _ = camera
    pinhole = inputs.data.camera
    radial = CameraInfo(
        CAMERA_ID, "SIMPLE_RADIAL", pinhole.width, pinhole.height, [900.0, 320.0, 240.0, 0.0]
    )
    stored = radial.with_distortion([0.01])
    options = inputs.options
    assert pinhole.model == "PINHOLE" and lens_search_applies(pinhole, "msac-opt", options)
    assert lens_search_applies(radial, "msac-opt", options)
    assert not lens_search_applies(radial, "msac", options)
    assert not lens_search_applies(stored, "msac-opt", options)


def test_a_warp_undistorts_keypoints_and_tracks_alike(camera) -> None:
    inputs, _ = camera
    data, tracks = inputs.data, inputs.tracks
    centre = np.asarray(data.prior[2:4], float)
    scale = float(np.hypot(data.camera.width, data.camera.height))
    warp = LensSearchResult(
        family=DIVISION,
        parameter=-0.2,
        centre=centre,
        scale=scale,
        focal=None,
        grid=np.array([-0.2]),
        costs=np.array([1.0]),
        ratio=2.0,
    )
    warped_data, warped_tracks = warped_input(data, tracks, warp)
    assert isinstance(warped_data, CameraInput) and isinstance(warped_tracks, CameraTracks)
    triplet = tracks.triplets[0]
    for view, image in enumerate(triplet.image_ids):
        keypoints = warped_data.keypoints[image][triplet.keypoint_indices[:, view]]
        np.testing.assert_allclose(warped_tracks.tracks[0][view], keypoints, atol=1e-9)
    moved = np.linalg.norm(warped_tracks.tracks[0] - tracks.tracks[0], axis=-1)
    assert moved.max() > 1.0  # the warp moved the tracks


def test_the_assessment_reports_every_json_key(camera, first: Attempt) -> None:
    inputs, truth = camera
    estimate = checked_estimate(first, CAMERA_ID, "msac-opt")
    from colmap_trifocal.intrinsics.polish.stage import Polished

    result = assess(
        AssessInput(
            inputs.data,
            "msac-opt",
            first.candidate,
            first.tensors.start,
            first.tensors.tensors,
            first.fallback,
            Polished(
                estimate,
                first.fallback.relative_std,
                first.agreeing,
                None,
                first.fallback.free_parameters,
            ),
            None,
            inputs.tracks.tracks,
            workers=1,
        )
    )
    assert tuple(result.to_json()) == JSON_KEYS
    assert all(result.observable.values()) and result.diagnosis is None
    assert all(source == "trifocal" for source in result.source.values())
    errors = np.abs(result.intrinsics - truth)
    std = np.array([result.std[name] for name in ("fx", "fy", "cx", "cy")])
    assert np.all(errors < 4 * std)
    assert result.seconds == 0.0  # the pipeline, which times the stage, gives the timing
