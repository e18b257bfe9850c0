"""The lens fit's statistics: the cost without distortion, the std, and the screen.

:func:`cost_without_distortion` is C₀ of the likelihood ratio ``(C₀ − C_k) / σ²``
that says whether the tracks show distortion; :func:`camera_params_std` and
:func:`jackknife_std` the std of the fitted camera (pycolmap's covariance, the image
jackknife); :func:`screen_statistic` the same ratio predicted by one Gauss–Newton step
before any adjustment (a score test). Pixels in COLMAP's convention; k unitless.
"""

from __future__ import annotations

import numpy as np
import pycolmap

from ...database.cameras import CameraInfo
from ...geometry.tensor_estimation import TripletTensor
from ..polish.bundle import calibrated_information
from ..polish.camera_setup import Refined, refined_directions
from ..polish.information import reduced_information
from ..polish.shared_camera import (
    FUNCTION_TOLERANCE,
    SharedCamera,
)
from ..solve.uncertainty import one_step_jackknife_std

#: Tracks per triplet at most (evenly spaced among its inliers): the distortion is
#: read from where the tracks lie across the image, which 300 per triplet cover.
MAX_TRACKS = 300
#: Models whose distortion is radial only, with a single focal length: the jackknife
#: of :func:`intrinsics.polish.information.reduced_information` applies.
RADIAL_MODELS = ("SIMPLE_RADIAL", "RADIAL")
#: Iterations of the pinhole fit C₀ at full precision; the rest to a relative
#: precision ``C0_PRECISION`` of ``C₀ − C_k`` per iteration (Ceres' function tolerance).
C0_ITERATIONS = 20


C0_PRECISION = 1e-4


def cost_without_distortion(shared: SharedCamera, agreeing: list[int], refined: Refined) -> float:
    """C₀: the agreeing triplets' squared error (px²) adjusted with the distortion held
    at 0, on a copy of the reconstruction (itself at the distortion's optimum).

    C₀ is only read through ``C₀ − C_k``: after ``C0_ITERATIONS`` iterations the rest
    runs to a relative precision ``C0_PRECISION`` of that difference, not of C₀. A
    strong lens's pinhole fit crawls along a long valley (its focal length moves far
    from the camera's) for changes far below what the test can see.
    """
    copy = pycolmap.Reconstruction(shared.reconstruction)
    camera = shared.camera
    with_distortion = shared.cost(agreeing)
    held = CameraInfo.from_pycolmap(camera)
    params = held.params.copy()
    params[list(camera.extra_params_idxs())] = 0.0
    original = shared.reconstruction
    shared.reconstruction = copy
    try:
        copy.cameras[camera.camera_id].params = params.tolist()
        first = shared.solve(agreeing, refined, max_iterations=C0_ITERATIONS)
        if not first.is_solution_usable():
            return float("nan")
        cost = shared.cost(agreeing)
        if first.termination_type != pycolmap.BundleAdjustmentTerminationType.NO_CONVERGENCE:
            return cost
        tolerance = FUNCTION_TOLERANCE
        if np.isfinite(cost) and cost > 0:
            tolerance = max(C0_PRECISION * max(cost - with_distortion, 0.0) / cost, tolerance)
        rest = shared.solve(agreeing, refined, function_tolerance=tolerance)
        return shared.cost(agreeing) if rest.is_solution_usable() else float("nan")
    finally:
        shared.reconstruction = original


def camera_params_std(
    covariance: pycolmap.BACovariance | None,
    camera: pycolmap.Camera,
    variance: float,
    refined: list[int],
) -> np.ndarray:
    """Std of every camera parameter (COLMAP's order) from pycolmap's covariance of the
    adjustment (unit weights) scaled by the residual variance: the ``refined``
    parameters' (indices, ascending: pycolmap's block covers those), 0 for the held
    ones; inf where unavailable."""
    count = len(camera.params)
    if covariance is None:
        return np.full(count, np.inf)
    block = covariance.get_other_params_cov(camera.params)
    if block is None:
        return np.full(count, np.inf)
    block = np.asarray(block, dtype=float)
    if block.shape != (len(refined), len(refined)):
        return np.full(count, np.inf)
    std = np.zeros(count)
    std[refined] = np.sqrt(np.clip(np.diag(block), 0.0, None) * variance)
    return std


def intrinsics_std_of(camera: CameraInfo, params_std: np.ndarray) -> np.ndarray:
    """(4,) std of (fx, fy, cx, cy) in pixels from the parameters' std."""
    return CameraInfo(
        camera.camera_id, camera.model, camera.width, camera.height, params_std
    ).intrinsics


def jackknife_std(
    shared: SharedCamera,
    agreeing: list[int],
    fitted: CameraInfo,
    tensors: list[TripletTensor],
    *,
    refine_principal_point: bool,
) -> np.ndarray | None:
    """(4 + m,) delete-a-group-of-images jackknife std of (fx, fy, cx, cy, k1[, k2]) of
    a ``SIMPLE_RADIAL`` / ``RADIAL`` camera (pixels; k unitless): one Gauss–Newton step
    per replicate on the triplets' Schur complements (:mod:`intrinsics.polish.information`).
    None for other models or too few image groups."""
    if fitted.model not in RADIAL_MODELS:
        return None
    radial = fitted.distortion
    parts = []
    for position in agreeing:
        triplet = shared.triplets[position]
        poses, points = shared.poses_and_points(triplet)
        parts.append(reduced_information(fitted.intrinsics, poses, points, triplet.pixels, radial))
    # The radial models have a single focal length, refined with the distortion.
    refined = Refined(focal=True, principal_point=refine_principal_point)
    free = refined_directions(refined, tied=True, extra=len(radial))
    groups = [tensors[shared.triplets[p].index].image_ids for p in agreeing]
    return one_step_jackknife_std(
        np.r_[fitted.intrinsics, radial],
        np.stack([h for h, _, _ in parts]),
        np.stack([g for _, g, _ in parts]),
        free,
        groups,
    )


def screen_statistic(
    tensors: list[TripletTensor],
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    intrinsics: np.ndarray,
    refined: Refined,
    *,
    tied: bool,
    workers: int | None = None,
) -> float | None:
    """The likelihood ratio of freeing k1, predicted without an adjustment (a score test).

    Each tensor's calibrated cameras at ``intrinsics`` and its triangulated tracks give
    its Schur complement and gradient on (fx, fy, cx, cy, k1) at k1 = 0
    (:func:`intrinsics.polish.information.reduced_information`); summed over the tensors, one
    Gauss–Newton step predicts how much the squared error falls with k1 free beyond
    what the intrinsics alone take (``refined``; one focal length where ``tied``), over
    σ². Milliseconds per tensor. None where it cannot be formed.
    """
    parts = [
        part
        for part in calibrated_information(
            tensors, tracks, start, intrinsics, np.zeros(1), MAX_TRACKS, workers
        )
        if np.isfinite(part.cost)
    ]
    information = sum((part.information for part in parts), np.zeros((5, 5)))
    gradient = sum((part.gradient for part in parts), np.zeros(5))
    cost = sum(part.cost for part in parts)
    observations = sum(6 * part.num_tracks for part in parts)
    unknowns = sum(3 * part.num_tracks + 11 for part in parts)
    with_k = refined_directions(refined, tied=tied, extra=1)
    if observations <= unknowns + with_k.shape[1]:
        return None
    variance = cost / (observations - unknowns - with_k.shape[1])

    def decrease(directions: np.ndarray) -> float:
        if directions.size == 0:
            return 0.0
        reduced = directions.T @ information @ directions
        step = np.linalg.lstsq(reduced, directions.T @ gradient, rcond=None)[0]
        return float((directions.T @ gradient) @ step)

    without_k = with_k[:, :-1]
    return float((decrease(with_k) - decrease(without_k)) / variance)
