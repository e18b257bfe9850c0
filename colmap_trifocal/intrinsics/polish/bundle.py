"""The constraint estimate polished by a calibrated bundle adjustment of its triplets.

Why. The whitened constraint residuals (:mod:`intrinsics.solve.constraints`) measure a
tensor's distance from the calibrated tensors of K to *first order* in the
tensor's noise. For a triplet whose tracks lie close to one plane the projective
tensor is poorly determined and that linearisation fails: the whitened norm ‖r‖
at the true K can be far beyond what χ(7) gives while the likelihood-ratio
statistic below is as χ²(7) predicts (docs/planar_and_sequences.md). Such
triplets are either left out as outliers or pull the estimate aside.

What. For each tensor (cameras ``P2``, ``P3`` of its ML projective fit) and a
camera K:

* **Calibrated cameras**: the essential matrices ``E = [a]ₓ A`` of
  ``K⁻¹ K0 [A | a]`` (view 1 is ``[I | 0]``), decomposed by cheirality on the tracks
  (:func:`geometry.motion.recover_pose`); view 3's baseline scale by linear least
  squares on the tracks triangulated from views 1–2.
* **Likelihood ratio** ``λ = (C_cal − C_proj) / σ²``: ``C_cal`` is the squared
  reprojection error (px²) of the triplet's inlier tracks after a bundle adjustment
  of the three calibrated poses and the points with K fixed (pycolmap),
  ``C_proj = σ² (3n − 18)`` that of the projective fit (:mod:`..geometry.projective_ba`).
  At the true K, λ ~ χ²(7), the codimension of calibrated tensors.
* **Shared-camera bundle adjustment**: the triplets with ``λ < τ²`` (τ the MSAC
  threshold, so that the same triplets count as agreeing as with ‖r‖ < τ to first
  order) are adjusted together, one camera shared by all of them, each triplet its
  own poses and points (first pose fixed; its scale is a free gauge direction that
  Ceres' damping handles). Two rounds: the agreeing set is chosen again at the
  first round's K.

The result is the maximum-likelihood K of the agreeing triplets' tracks. Each
triplet's information on the camera is its Schur complement (points and poses
eliminated, :mod:`intrinsics.polish.information`; the same marginal as pycolmap's
``estimate_ba_covariance``): their sum gives the covariance, scaled by the noise
variance the residuals show, and one Gauss–Newton step per image group left out
gives the same delete-a-group jackknife as the constraint solve's
(:func:`intrinsics.solve.uncertainty.jackknife_replicates`) without new adjustments. Which
parameters are estimated
(free, tied ``fy = fx``, held) follows the constraint solve's
:class:`intrinsics.solve.parametrization.FreeParameters`; holding one principal-point coordinate
but not the other is not expressible with pycolmap's cameras, and gets no polish.

The camera is a PINHOLE (``fx, fy, cx, cy``) or, for a tied focal length, a
SIMPLE_PINHOLE camera in COLMAP's pixel convention (the centre of the top-left
pixel is (0.5, 0.5)). Keypoints of every triplet are added point by point: pycolmap
has no batch call for tracks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ...common.parallel import MIN_FORKED_JOBS, map_jobs
from ...geometry.tensor_estimation import TripletTensor
from ..solve.fallback import FallbackSolution
from ..solve.parametrization import FreeParameters
from ..solve.uncertainty import (
    gauss_newton_step,
    one_step_jackknife_std,
    restricted_information,
)
from .calibrated_tracks import (
    MAX_TRACKS,
    Observed,
    calibrated_cameras,
    inlier_pixels,
    observed_tracks,
    triangulate,
)
from .camera_setup import camera_start, refined_directions
from .information import reduced_information
from .shared_camera import agree_and_adjust, cameras_at, observed_at, shared_camera


@dataclass
class TripletBundleResult:
    """The polished camera and what it rests on.

    Attributes:
        intrinsics: (fx, fy, cx, cy), pixels.
        ratios: (n,) likelihood-ratio statistic λ of every tensor at ``intrinsics``
            (inf where no calibrated cameras could be formed).
        agreeing: (n,) bool, ``λ < τ²``.
        covariance_std: (4,) std of (fx, fy, cx, cy) from the adjustment's covariance
            ``σ² (Σ H_t)⁻¹``, pixels (0 for a parameter it held).
        jackknife_std: (4,) their delete-a-group-of-images jackknife std (one
            Gauss–Newton step per replicate), pixels; None with too few groups.
    """

    intrinsics: np.ndarray
    ratios: np.ndarray
    agreeing: np.ndarray
    covariance_std: np.ndarray
    jackknife_std: np.ndarray | None

    @property
    def std(self) -> np.ndarray:
        """(4,) the larger of the covariance's and the jackknife's std, pixels."""
        if self.jackknife_std is None:
            return self.covariance_std
        return np.asarray(np.maximum(self.covariance_std, self.jackknife_std))


@dataclass(frozen=True)
class PolishInput:
    """What the polish reads.

    Attributes:
        tensors: the solve's tensors, normalised by ``start`` (pixels).
        tracks: per triplet (image ids), its tracks (3, n, 2), pixels.
        start: the tensors' normalisation (fx0, fy0, cx0, cy0), pixels.
        estimate: the constraint estimate (fx, fy, cx, cy), pixels.
        fallback: the constraint solve (free parameters, std, jackknife).
        agreeing: tensors that agree with ``estimate``.
        size: (width, height) of the images, pixels.
        tau: the MSAC threshold.
        camera_id: for messages.
        workers: threads for the per-triplet work (None: one per core).
    """

    tensors: list[TripletTensor]
    tracks: dict[tuple[int, int, int], np.ndarray]
    start: np.ndarray
    estimate: np.ndarray
    fallback: FallbackSolution
    agreeing: int
    size: tuple[int, int]
    tau: float
    camera_id: int
    workers: int | None = None


def polish_intrinsics(
    given: PolishInput,
    free_parameters: FreeParameters | None = None,
    *,
    observed: list[Observed] | None = None,
    cameras: dict[tuple[int, int, int], np.ndarray] | None = None,
) -> TripletBundleResult | None:
    """The ML intrinsics of the agreeing triplets (``λ < τ²``), from the constraint
    estimate (held values included); each tensor's ``inliers`` pick its tracks.

    ``free_parameters`` are those the adjustment estimates (default: the constraint
    solve's, ``given.fallback.free_parameters``). ``observed`` (the tensors' tracks and
    projective costs, :func:`observed_tracks`) is computed where not given, and so are
    the calibrated cameras at the estimate of the tensors not in ``cameras`` (by the
    tensor's images, :attr:`PredictedPolish.cameras`). Returns None when the free
    parameters are not expressible
    (:func:`intrinsics.polish.camera_setup.pycolmap_camera_setup`), no triplet agrees,
    or Ceres fails.
    """
    tensors, tracks, start, estimate = given.tensors, given.tracks, given.start, given.estimate
    tau, workers = given.tau, given.workers
    if free_parameters is None:
        free_parameters = given.fallback.free_parameters
    start_values = camera_start(free_parameters, estimate)
    if start_values is None or not tensors:
        return None
    setup, intrinsics = start_values
    limit = tau**2
    if observed is None and cameras is None:
        observed, formed = observed_at(tensors, tracks, start, intrinsics, workers=workers)
    else:
        if observed is None:
            observed = observed_tracks(tensors, tracks, start, workers=workers)
        formed = cameras_at(observed, start, intrinsics, workers, known=cameras)
    shared = shared_camera(observed, formed, intrinsics, setup.model, given.size)
    if shared is None:
        return None
    agreement = agree_and_adjust(shared, limit, setup.refined)
    if agreement is None:
        return None
    agreeing, before = agreement.agreeing, agreement.ratios
    intrinsics = shared.intrinsics()
    information, gradients, costs = shared.information(agreeing)
    free = refined_directions(setup.refined, tied=setup.tied)
    observations = sum(6 * len(shared.triplets[p].point_ids) for p in agreeing)
    unknowns = sum(3 * len(shared.triplets[p].point_ids) + 11 for p in agreeing)
    variance = float(costs.sum()) / max(observations - unknowns - free.shape[1], 1)
    reduced = restricted_information(information.sum(axis=0), free)
    if reduced is None:
        return None
    covariance_std = np.sqrt(np.diag(variance * free @ np.linalg.inv(reduced) @ free.T))
    groups = [tensors[shared.triplets[p].index].image_ids for p in agreeing]
    jackknife_std = one_step_jackknife_std(intrinsics, information, gradients, free, groups)
    # λ at the final K: exact for the adjusted triplets; the others keep their λ at
    # the final round's start (they disagreed there, and K moved by a fraction of a std).
    after = shared.ratios()
    adjusted = set(agreeing)
    ratios = np.full(len(tensors), np.inf)
    for position, triplet in enumerate(shared.triplets):
        ratios[triplet.index] = after[position] if position in adjusted else before[position]
    return TripletBundleResult(
        intrinsics=intrinsics,
        ratios=ratios,
        agreeing=ratios < limit,
        covariance_std=covariance_std,
        jackknife_std=jackknife_std,
    )


@dataclass
class PredictedPolish:
    """Where the polish would take the estimate, predicted by its first Gauss–Newton step.

    Attributes:
        step: (4,) move of (fx, fy, cx, cy) from the constraint estimate, pixels.
        jackknife_std: (4,) its delete-a-group jackknife std, pixels (None: too few
            image groups).
        cameras: each tensor's calibrated cameras (3, 3, 4) at the constraint
            estimate, by the tensor's images (where they could be formed): the polish
            starts from the same ones.
    """

    step: np.ndarray
    jackknife_std: np.ndarray | None
    cameras: dict[tuple[int, int, int], np.ndarray]


def predict_polish(
    tensors: list[TripletTensor],
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    estimate: np.ndarray,
    free_parameters: FreeParameters,
    workers: int | None = None,
) -> PredictedPolish | None:
    """The polish's move and jackknife std predicted from its first Gauss–Newton step.

    No adjustment is run: each tensor's calibrated cameras at the constraint estimate,
    its tracks (at most ``MAX_TRACKS``) triangulated, their Schur complements on the
    camera (:func:`intrinsics.polish.information.reduced_information`), one Gauss–Newton step
    with every triplet and one per image group left out. Milliseconds per tensor; what
    the polish would reach differs by its further iterations. None where it cannot be
    formed.
    """
    start_values = camera_start(free_parameters, estimate)
    if start_values is None or not tensors:
        return None
    setup, intrinsics = start_values
    parts = calibrated_information(tensors, tracks, start, intrinsics, workers=workers)
    if not parts:
        return None
    free = refined_directions(setup.refined, tied=setup.tied)
    information = np.stack([part.information for part in parts])
    gradients = np.stack([part.gradient for part in parts])
    moved = gauss_newton_step(intrinsics, information.sum(axis=0), gradients.sum(axis=0), free)
    if moved is None:
        return None
    jackknife_std = one_step_jackknife_std(
        intrinsics, information, gradients, free, [part.tensor.image_ids for part in parts]
    )
    cameras = {part.tensor.image_ids: part.cameras for part in parts}
    return PredictedPolish(moved - np.asarray(estimate, float), jackknife_std, cameras)


@dataclass
class TripletInformation:
    """What one tensor's tracks say about the camera, without an adjustment: its
    calibrated cameras at K, its tracks triangulated, their Schur complement."""

    tensor: TripletTensor
    cameras: np.ndarray  # (3, 3, 4) its calibrated cameras [R | t] at K
    information: np.ndarray  # (q, q) on (fx, fy, cx, cy[, k...])
    gradient: np.ndarray  # (q,)
    cost: float  # Σ r², px²
    num_tracks: int


def calibrated_information(
    tensors: list[TripletTensor],
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    intrinsics: np.ndarray,
    radial: np.ndarray | None = None,
    max_tracks: int = MAX_TRACKS,
    workers: int | None = None,
) -> list[TripletInformation]:
    """Each tensor's information on the camera at ``intrinsics`` (pixels; with ``radial``
    also on its radial coefficients, :func:`intrinsics.polish.information.reduced_information`),
    from its calibrated cameras (:func:`calibrated_cameras`) and its tracks (at most
    ``max_tracks``) triangulated; tensors where either cannot be formed are left out.
    Milliseconds per tensor, over ``workers`` threads, or forked processes from
    ``MIN_FORKED_JOBS`` tensors (None: one per core)."""
    jobs = [(tensor, tracks, start, intrinsics, radial, max_tracks) for tensor in tensors]
    parts = map_jobs(_information_job, jobs, workers, processes=len(jobs) >= MIN_FORKED_JOBS)
    return [part for part in parts if part is not None]


def _information_job(job: tuple[Any, ...]) -> TripletInformation | None:
    tensor, tracks, start, intrinsics, radial, max_tracks = job
    pixels = inlier_pixels(tensor, tracks, max_tracks)
    normalised = (pixels - intrinsics[2:]) / intrinsics[:2]
    cameras = calibrated_cameras(tensor, normalised, start, intrinsics)
    if cameras is None or not np.all(np.isfinite(cameras)):
        return None
    points = triangulate(cameras, normalised)
    information, gradient, cost = reduced_information(intrinsics, cameras, points, pixels, radial)
    if not (np.all(np.isfinite(information)) and np.all(np.isfinite(gradient))):
        return None
    return TripletInformation(tensor, cameras, information, gradient, cost, pixels.shape[1])
