"""The constraint estimate polished by a calibrated bundle adjustment of its triplets.

Why. The whitened constraint residuals (:mod:`.selfcalibration`) measure a
tensor's distance from the calibrated tensors of K to *first order* in the
tensor's noise. For a triplet whose tracks lie close to one plane the projective
tensor is poorly determined and that linearisation fails: the whitened norm ‖r‖
at the true K can be far beyond what χ(7) gives while the likelihood-ratio
statistic below is as χ²(7) predicts (docs/planar_and_sequences.md). Such
triplets are either left out as outliers or pull the estimate aside.

What. For each tensor (cameras ``P2``, ``P3`` of its ML projective fit) and a
camera K:

* **Calibrated cameras**: the essential matrices ``E = [a]ₓ A`` of
  ``K⁻¹ K0 [A | a]`` (view 1 is ``[I | 0]``), decomposed with OpenCV
  (:func:`cv2.recoverPose`, cheirality on the tracks); view 3's baseline scale by
  linear least squares on the tracks triangulated from views 1–2.
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
eliminated, :mod:`.bundle_information`; the same marginal as pycolmap's
``estimate_ba_covariance``): their sum gives the covariance, scaled by the noise
variance the residuals show, and one Gauss–Newton step per image group left out
gives the same delete-a-group jackknife as the constraint solve's
(:func:`.uncertainty.jackknife_replicates`) without new adjustments. Which
parameters are estimated
(free, tied ``fy = fx``, held) follows the constraint solve's
:class:`.parametrization.FreeParameters`; holding one principal-point coordinate
but not the other is not expressible with pycolmap's cameras, and gets no polish.

The camera is a PINHOLE (``fx, fy, cx, cy``) or, for a tied focal length, a
SIMPLE_PINHOLE camera in COLMAP's pixel convention (the centre of the top-left
pixel is (0.5, 0.5)). Keypoints of every triplet are added point by point: pycolmap
has no batch call for tracks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import pycolmap

from ...common.bundle_adjustment import bundle_adjustment_options
from ...common.log import keep_colmap_quiet
from ...common.parallel import map_jobs
from ...common.sampling import evenly_spaced
from ...database.cameras import CameraInfo
from ...geometry.projective_ba import refine_triplet
from ...geometry.tensor_estimation import TripletTensor
from ...geometry.trifocal import intrinsics_matrix
from ..solve.parametrization import FreeParameters
from ..solve.uncertainty import jackknife_covariance, jackknife_replicates
from .information import reduced_information

_CAMERA_ID = 1
#: Ceres tolerances: the polish should reach the optimum, not COLMAP's early stop.
_FUNCTION_TOLERANCE = 1e-12
_GRADIENT_TOLERANCE = 1e-14
_MAX_ITERATIONS = 200
#: Rounds of "choose the agreeing triplets at K, adjust them together".
ROUNDS = 2
#: Tracks per triplet at most (evenly spaced among its inliers): as many as the
#: tensor's own refinement uses (``TensorEstimationOptions.max_refined_tracks``).
MAX_TRACKS = 500
#: The projective fit that λ is measured against starts at the tensor's cameras,
#: already the ML fit of (up to 500 of) these tracks: a few iterations converge.
_PROJECTIVE_ITERATIONS = 20
_PROJECTIVE_TOLERANCE = 1e-9
#: Unknowns of a projective triplet beyond its points (two 3x4 cameras, less gauge).
_PROJECTIVE_PARAMETERS = 18


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


def pycolmap_camera_setup(free_parameters: FreeParameters) -> tuple[str, bool, bool] | None:
    """(COLMAP camera model, refine focal length, refine principal point) that estimate
    ``free_parameters``.

    None when pycolmap cannot express it (one principal-point coordinate held) or
    nothing is estimated.
    """
    if free_parameters.cx != free_parameters.cy or free_parameters.dimension == 0:
        return None
    camera_model = "SIMPLE_PINHOLE" if free_parameters.focal == "tied" else "PINHOLE"
    return camera_model, free_parameters.focal != "held", free_parameters.cx


def calibrated_cameras(
    tensor: TripletTensor, x: np.ndarray, start: np.ndarray, intrinsics: np.ndarray
) -> np.ndarray | None:
    """Calibrated cameras (3, 3, 4) ``[R | t]`` of a tensor's views under K, view 1 ``[I|0]``.

    Args:
        tensor: its ``P2``, ``P3`` are in coordinates normalised by ``start``.
        x: the triplet's inlier tracks (3, n, 2) normalised by ``intrinsics``.
        start: (fx0, fy0, cx0, cy0) of the tensor's normalisation, pixels.
        intrinsics: (fx, fy, cx, cy) of K, pixels.

    Returns None when OpenCV cannot decompose an essential matrix.
    """
    M = np.linalg.solve(intrinsics_matrix(start), intrinsics_matrix(intrinsics))  # K0⁻¹ K
    M_inverse = np.linalg.inv(M)
    poses = []
    for view, P in ((1, tensor.P2), (2, tensor.P3)):
        A, a = M_inverse @ P[:, :3] @ M, M_inverse @ P[:, 3]
        essential = np.cross(a, A, axisa=0, axisb=0, axisc=0)  # [a]ₓ A
        essential = essential / np.linalg.norm(essential)
        try:
            count, R, t, _ = cv2.recoverPose(essential, x[0], x[view], np.eye(3))
        except cv2.error:
            return None
        if count == 0:
            return None
        poses.append((R, t.ravel()))
    (R2, t2), (R3, t3) = poses
    cameras = np.stack([np.eye(3, 4), np.hstack([R2, t2[:, None]]), np.eye(3, 4)])
    points = triangulate(cameras[:2], x[:2])
    # View 3's baseline scale s: x3 ∥ R3 X + s t3, least squares over the tracks.
    rays = np.concatenate([x[2], np.ones((x.shape[1], 1))], axis=1)
    rotated = np.cross(rays, points @ R3.T)
    baseline = np.cross(rays, np.broadcast_to(t3, rays.shape))
    scale = -np.sum(rotated * baseline) / max(float(np.sum(baseline * baseline)), 1e-300)
    cameras[2] = np.hstack([R3, scale * t3[:, None]])
    return cameras


def triangulate(cameras: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Points (n, 3) from normalised tracks x (v, n, 2) and cameras (v, 3, 4) (linear DLT)."""
    rows = np.concatenate(
        [
            x[..., 0:1] * cameras[:, None, 2] - cameras[:, None, 0],
            x[..., 1:2] * cameras[:, None, 2] - cameras[:, None, 1],
        ],
        axis=0,
    )  # (2v, n, 4)
    homogeneous = np.linalg.svd(np.swapaxes(rows, 0, 1))[2][:, -1]
    w = homogeneous[:, 3:]
    return homogeneous[:, :3] / np.where(np.abs(w) > 1e-12, w, 1e-12)


@dataclass
class _Observed:
    """A tensor's tracks for the polish and their projective fit (the λ reference)."""

    index: int  # position among the tensors
    tensor: TripletTensor
    pixels: np.ndarray  # (3, n, 2) inlier tracks, pixels
    projective_cost: float  # C_proj, px²
    sigma2: float  # σ² = C_proj / (3n − 18), px²


def observed_tracks(
    tensors: list[TripletTensor],
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    max_tracks: int = MAX_TRACKS,
    workers: int | None = None,
) -> list[_Observed]:
    """Each tensor's inlier tracks (at most ``MAX_TRACKS``, evenly spaced) and their
    projective cost, from a projective bundle adjustment warm-started at its cameras
    (over ``workers`` threads; None: one per core).

    The tensor's own noise estimate comes from the tracks its last refinement used,
    not these, so C_proj is measured on exactly the tracks λ compares.
    """
    jobs = [(index, tensor, tracks, start, max_tracks) for index, tensor in enumerate(tensors)]
    return [o for o in map_jobs(_observed_job, jobs, workers) if o is not None]


def _observed_job(job: tuple[Any, ...]) -> _Observed | None:
    index, tensor, tracks, start, max_tracks = job
    pixels = _inlier_pixels(tensor, tracks, max_tracks)
    if pixels.shape[1] <= _PROJECTIVE_PARAMETERS // 3:
        return None
    fit = refine_triplet(
        (pixels - start[2:]) / start[:2],
        tensor.P2,
        tensor.P3,
        start[:2],
        max_iterations=_PROJECTIVE_ITERATIONS,
        tolerance=_PROJECTIVE_TOLERANCE,
    )
    cost = float(fit.squared_errors.sum())
    if not (np.isfinite(cost) and fit.sigma > 0):
        return None
    return _Observed(index, tensor, pixels, cost, fit.sigma**2)


@dataclass
class _Triplet:
    """One triplet inside the shared reconstruction."""

    index: int  # position among the tensors
    image_ids: tuple[int, int, int]  # the triplet's images in the reconstruction
    point_ids: np.ndarray  # (n,) its 3D points
    pixels: np.ndarray  # (3, n, 2) its tracks, pixels
    projective_cost: float  # C_proj, px²
    sigma2: float  # σ², px²


class _SharedCamera:
    """A pycolmap reconstruction: one camera, each triplet its own three images and points."""

    def __init__(
        self,
        intrinsics: np.ndarray,
        camera_model: str,
        width: int,
        height: int,
        distortion: np.ndarray | None = None,
    ):
        """A camera of ``camera_model`` (any of :data:`..database.cameras.SUPPORTED_MODELS`)
        at (fx, fy, cx, cy), pixels, its distortion parameters ``distortion`` (COLMAP's
        order; default 0)."""
        self.reconstruction = pycolmap.Reconstruction()
        blank = pycolmap.Camera.create_from_model_name(_CAMERA_ID, camera_model, 1.0, width, height)
        zero = CameraInfo(_CAMERA_ID, camera_model, width, height, np.zeros(len(blank.params)))
        if distortion is not None:
            zero = zero.with_distortion(distortion)
        camera = zero.with_intrinsics(*map(float, intrinsics)).to_pycolmap()
        self.reconstruction.add_camera_with_trivial_rig(camera)
        self.triplets: list[_Triplet] = []

    @property
    def camera(self) -> pycolmap.Camera:
        """The shared camera, as adjusted."""
        return self.reconstruction.cameras[_CAMERA_ID]

    def cost(self, which: list[int]) -> float:
        """Summed squared reprojection error (px²) of the triplets ``which``."""
        return float(sum(self._squared_errors(self.triplets[p]).sum() for p in which))

    def intrinsics(self) -> np.ndarray:
        camera = self.reconstruction.cameras[_CAMERA_ID]
        return np.array(
            [
                camera.focal_length_x,
                camera.focal_length_y,
                camera.principal_point_x,
                camera.principal_point_y,
            ]
        )

    def add(
        self, observed: _Observed, cameras: np.ndarray, keypoints: np.ndarray | None = None
    ) -> None:
        """Add a triplet's tracks with its calibrated cameras (3, 3, 4): its points
        triangulated from its (undistorted) tracks, observed at ``keypoints`` (3, n, 2)
        pixels where the camera's distortion is to explain them (default: the tracks)."""
        intrinsics = self.intrinsics()
        normalised = (observed.pixels - intrinsics[2:]) / intrinsics[:2]
        points = triangulate(cameras, normalised)
        pixels = observed.pixels if keypoints is None else keypoints
        first = 3 * len(self.triplets) + 1
        image_ids = (first, first + 1, first + 2)
        for view, image_id in enumerate(image_ids):
            image = pycolmap.Image(
                name=f"{image_id}.png",
                keypoints=np.ascontiguousarray(pixels[view], dtype=np.float64),
                camera_id=_CAMERA_ID,
                image_id=image_id,
            )
            pose = pycolmap.Rigid3d(
                pycolmap.Rotation3d(cameras[view][:, :3]), cameras[view][:, 3].copy()
            )
            self.reconstruction.add_image_with_trivial_frame(image, pose)
        point_ids = np.array(
            [
                self.reconstruction.add_point3D(
                    point, pycolmap.Track([pycolmap.TrackElement(i, k) for i in image_ids])
                )
                for k, point in enumerate(points)
            ]
        )
        self.triplets.append(
            _Triplet(
                observed.index,
                image_ids,
                point_ids,
                pixels,
                observed.projective_cost,
                observed.sigma2,
            )
        )

    def adjuster(
        self,
        which: list[int],
        refine_focal: bool,
        refine_principal_point: bool,
        refine_distortion: bool = False,
        fix_scale: bool = False,
        function_tolerance: float = _FUNCTION_TOLERANCE,
        max_iterations: int = _MAX_ITERATIONS,
    ) -> pycolmap.CeresBundleAdjuster:
        """pycolmap's bundle adjuster of the triplets ``which`` (positions in
        ``self.triplets``): poses and points, the camera's parameters as asked.

        Each triplet's first pose is held; its scale is a gauge direction that Ceres'
        damping handles, or, with ``fix_scale`` (for a covariance, which needs a problem
        without gauge freedom), that its first point holds.
        """
        config = pycolmap.BundleAdjustmentConfig()
        for position in which:
            triplet = self.triplets[position]
            for image_id in triplet.image_ids:
                config.add_image(image_id)
            first = self.reconstruction.images[triplet.image_ids[0]]
            config.set_constant_rig_from_world_pose(first.frame_id)
            if fix_scale:
                config.add_constant_point(int(triplet.point_ids[0]))
        if not (refine_focal or refine_principal_point or refine_distortion):
            config.set_constant_cam_intrinsics(_CAMERA_ID)
        options = bundle_adjustment_options(
            refine_focal,
            refine_principal_point,
            refine_distortion,
            function_tolerance=function_tolerance,
            gradient_tolerance=_GRADIENT_TOLERANCE,
            max_iterations=max_iterations,
            threads=1,
        )
        return pycolmap.create_default_ceres_bundle_adjuster(options, config, self.reconstruction)

    def adjust(
        self,
        which: list[int],
        refine_focal: bool,
        refine_principal_point: bool,
        refine_distortion: bool = False,
    ) -> bool:
        """Bundle-adjust the triplets ``which`` in place (:meth:`adjuster`); False when
        Ceres finds no usable solution."""
        summary = self.solve(which, refine_focal, refine_principal_point, refine_distortion)
        return bool(summary.is_solution_usable())

    def solve(
        self,
        which: list[int],
        refine_focal: bool,
        refine_principal_point: bool,
        refine_distortion: bool = False,
        function_tolerance: float = _FUNCTION_TOLERANCE,
        max_iterations: int = _MAX_ITERATIONS,
    ) -> pycolmap.BundleAdjustmentSummary:
        """:meth:`adjust` with Ceres' relative ``function_tolerance`` and
        ``max_iterations`` given; pycolmap's summary of the solve."""
        with keep_colmap_quiet():
            adjuster = self.adjuster(
                which,
                refine_focal,
                refine_principal_point,
                refine_distortion,
                function_tolerance=function_tolerance,
                max_iterations=max_iterations,
            )
            return adjuster.solve()

    def adjust_each(self, which: list[int]) -> bool:
        """Adjust the poses and points of each triplet of ``which`` at the camera as it
        is, one problem per triplet (they share nothing while the camera is held, and
        one triplet far from the camera would keep a joint problem iterating for all);
        False when Ceres finds no usable solution for any of them."""
        usable = [self.adjust([position], False, False) for position in which]
        return any(usable)

    def poses_and_points(self, triplet: _Triplet) -> tuple[np.ndarray, np.ndarray]:
        """A triplet's cameras (3, 3, 4) ``[R | t]`` and points (n, 3), as adjusted."""
        poses = np.stack(
            [
                np.asarray(self.reconstruction.images[i].cam_from_world().matrix())
                for i in triplet.image_ids
            ]
        )
        points = np.array([self.reconstruction.points3D[int(p)].xyz for p in triplet.point_ids])
        return poses, points

    def information(self, which: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per triplet of ``which``: its information (m, 4, 4) and gradient (m, 4) on
        (fx, fy, cx, cy) and its squared error (m,), px² (:mod:`.bundle_information`)."""
        intrinsics = self.intrinsics()
        parts = [
            reduced_information(
                intrinsics, *self.poses_and_points(self.triplets[p]), self.triplets[p].pixels
            )
            for p in which
        ]
        return (
            np.stack([h for h, _, _ in parts]),
            np.stack([g for _, g, _ in parts]),
            np.array([c for _, _, c in parts]),
        )

    def _squared_errors(self, triplet: _Triplet) -> np.ndarray:
        """(3, n) squared reprojection errors (px²) of a triplet through the shared
        camera (its distortion included); inf behind a camera."""
        poses, points = self.poses_and_points(triplet)
        camera = self.camera
        errors = np.empty((3, len(points)))
        for view, pose in enumerate(poses):
            local = points @ pose[:, :3].T + pose[:, 3]
            in_front = local[:, 2] > 0
            safe = np.where(in_front[:, None], local, [0.0, 0.0, 1.0])
            pixels = np.asarray(camera.img_from_cam(np.ascontiguousarray(safe), False))
            squared = np.sum((pixels - triplet.pixels[view]) ** 2, axis=1)
            errors[view] = np.where(in_front & np.isfinite(squared), squared, np.inf)
        return errors

    def ratios(self) -> np.ndarray:
        """λ of every triplet at the current cameras (inf where a point is behind a camera)."""
        return np.array(
            [
                (float(self._squared_errors(triplet).sum()) - triplet.projective_cost)
                / triplet.sigma2
                for triplet in self.triplets
            ]
        )


def polish_intrinsics(
    tensors: list[TripletTensor],
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    estimate: np.ndarray,
    free_parameters: FreeParameters,
    size: tuple[int, int],
    tau: float,
    workers: int | None = None,
) -> TripletBundleResult | None:
    """The ML intrinsics of the agreeing triplets, from the constraint estimate.

    Args:
        tensors: the tensors, normalised by ``start``.
        tracks: per triplet (image ids), all its tracks (3, n, 2) in pixels; each
            tensor's ``inliers`` picks from them.
        start: (fx0, fy0, cx0, cy0) of the tensors' normalisation, pixels.
        estimate: the constraint solve's (fx, fy, cx, cy), held values included.
        free_parameters: what is estimated (see :func:`pycolmap_camera_setup`).
        size: (width, height) of the images, pixels.
        tau: the MSAC threshold; triplets with ``λ < τ²`` agree.
        workers: threads for the per-triplet work (None: one per core).

    Returns None when ``free_parameters`` are not expressible, no triplet agrees, or
    Ceres fails.
    """
    start_values = _camera_start(free_parameters, estimate)
    if start_values is None or not tensors:
        return None
    camera_model, refine_focal, refine_principal_point, intrinsics = start_values
    limit = tau**2
    observed = observed_tracks(tensors, tracks, start, workers=workers)
    shared = _shared_camera(observed, start, intrinsics, camera_model, size, workers)
    if shared is None:
        return None
    everything = list(range(len(shared.triplets)))
    # Each round: the triplets not adjusted with the current K get their poses and
    # points adjusted at it (the first round: all), which gives every triplet's λ at
    # K; the agreeing ones are then adjusted together with K free. A triplet adjusted
    # with K free is already at its optimum for that K, and when the agreeing set
    # does not change, neither does K: the rounds stop there.
    agreeing: list[int] = []
    for _ in range(ROUNDS):
        stale = [p for p in everything if p not in agreeing]
        if stale and not shared.adjust_each(stale):
            return None
        before = shared.ratios()
        chosen = [p for p, ratio in enumerate(before) if ratio < limit]
        if not chosen:
            return None
        if chosen == agreeing:
            break
        agreeing = chosen
        if not shared.adjust(agreeing, refine_focal, refine_principal_point):
            return None
        intrinsics = shared.intrinsics()
    information, gradients, costs = shared.information(agreeing)
    free = _refined_directions(
        camera_model == "SIMPLE_PINHOLE", refine_focal, refine_principal_point
    )
    observations = sum(6 * len(shared.triplets[p].point_ids) for p in agreeing)
    unknowns = sum(3 * len(shared.triplets[p].point_ids) + 11 for p in agreeing)
    variance = float(costs.sum()) / max(observations - unknowns - free.shape[1], 1)
    reduced = _reduced(information.sum(axis=0), free)
    if reduced is None:
        return None
    covariance_std = np.sqrt(np.diag(variance * free @ np.linalg.inv(reduced) @ free.T))
    groups = [tensors[shared.triplets[p].index].image_ids for p in agreeing]
    jackknife_std = _one_step_jackknife_std(intrinsics, information, gradients, free, groups)
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
    """

    step: np.ndarray
    jackknife_std: np.ndarray | None


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
    camera (:func:`.bundle_information.reduced_information`), one Gauss–Newton step
    with every triplet and one per image group left out. Milliseconds per tensor; what
    the polish would reach differs by its further iterations. None where it cannot be
    formed.
    """
    start_values = _camera_start(free_parameters, estimate)
    if start_values is None or not tensors:
        return None
    camera_model, refine_focal, refine_principal_point, intrinsics = start_values
    parts = calibrated_information(tensors, tracks, start, intrinsics, workers=workers)
    if not parts:
        return None
    free = _refined_directions(
        camera_model == "SIMPLE_PINHOLE", refine_focal, refine_principal_point
    )
    information = np.stack([part.information for part in parts])
    gradients = np.stack([part.gradient for part in parts])
    moved = _gauss_newton(intrinsics, information.sum(axis=0), gradients.sum(axis=0), free)
    if moved is None:
        return None
    jackknife_std = _one_step_jackknife_std(
        intrinsics, information, gradients, free, [part.tensor.image_ids for part in parts]
    )
    return PredictedPolish(moved - np.asarray(estimate, float), jackknife_std)


@dataclass
class TripletInformation:
    """What one tensor's tracks say about the camera, without an adjustment: its
    calibrated cameras at K, its tracks triangulated, their Schur complement."""

    tensor: TripletTensor
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
    also on its radial coefficients, :func:`.bundle_information.reduced_information`),
    from its calibrated cameras (:func:`calibrated_cameras`) and its tracks (at most
    ``max_tracks``) triangulated; tensors where either cannot be formed are left out.
    Milliseconds per tensor, over ``workers`` threads (None: one per core)."""
    jobs = [(tensor, tracks, start, intrinsics, radial, max_tracks) for tensor in tensors]
    return [part for part in map_jobs(_information_job, jobs, workers) if part is not None]


def _information_job(job: tuple[Any, ...]) -> TripletInformation | None:
    tensor, tracks, start, intrinsics, radial, max_tracks = job
    pixels = _inlier_pixels(tensor, tracks, max_tracks)
    normalised = (pixels - intrinsics[2:]) / intrinsics[:2]
    cameras = calibrated_cameras(tensor, normalised, start, intrinsics)
    if cameras is None or not np.all(np.isfinite(cameras)):
        return None
    points = triangulate(cameras, normalised)
    information, gradient, cost = reduced_information(intrinsics, cameras, points, pixels, radial)
    if not (np.all(np.isfinite(information)) and np.all(np.isfinite(gradient))):
        return None
    return TripletInformation(tensor, information, gradient, cost, pixels.shape[1])


def _one_step_jackknife_std(
    intrinsics: np.ndarray,
    information: np.ndarray,
    gradients: np.ndarray,
    free: np.ndarray,
    groups: list[tuple[int, int, int]],
) -> np.ndarray | None:
    """(4,) delete-a-group-of-images jackknife std (pixels) of a shared camera: each
    replicate one Gauss–Newton step ``−(Σ_kept H_t)⁻¹ Σ_kept g_t`` from ``intrinsics``.

    ``information`` (m, 4, 4) and ``gradients`` (m, 4) per triplet, ``free`` (4, k) the
    refined parameters, ``groups`` the triplets' image ids. None with too few groups.
    """

    def replicate(keep: np.ndarray) -> np.ndarray | None:
        return _gauss_newton(
            intrinsics, information[keep].sum(axis=0), gradients[keep].sum(axis=0), free
        )

    replicates = jackknife_replicates(groups, replicate)
    return None if replicates is None else np.sqrt(np.diag(jackknife_covariance(replicates)))


def _reduced(information: np.ndarray, free: np.ndarray) -> np.ndarray | None:
    """``Aᵀ H A`` (k, k): a summed information H (q, q) on the k refined directions A
    (``free``, q × k); None where it is not finite or singular."""
    reduced = free.T @ information @ free
    if not np.all(np.isfinite(reduced)) or np.linalg.matrix_rank(reduced) < free.shape[1]:
        return None
    return np.asarray(reduced)


def _gauss_newton(
    intrinsics: np.ndarray, information: np.ndarray, gradient: np.ndarray, free: np.ndarray
) -> np.ndarray | None:
    """The parameters after one Gauss–Newton step ``−A (AᵀHA)⁻¹ Aᵀg`` from ``intrinsics``
    on a summed information H (q, q) and gradient g (q,), along the refined directions
    A (``free``); None where :func:`_reduced` is."""
    reduced = _reduced(information, free)
    if reduced is None:
        return None
    return np.asarray(intrinsics - free @ np.linalg.solve(reduced, free.T @ gradient))


def _inlier_pixels(
    tensor: TripletTensor,
    tracks: dict[tuple[int, int, int], np.ndarray],
    max_tracks: int = MAX_TRACKS,
) -> np.ndarray:
    """A tensor's inlier tracks (3, n, 2) in pixels, at most ``max_tracks`` evenly spaced."""
    pixels = tracks[tensor.image_ids][:, tensor.inliers]
    return pixels[:, evenly_spaced(pixels.shape[1], max_tracks)]


def _camera_start(
    free_parameters: FreeParameters, estimate: np.ndarray
) -> tuple[str, bool, bool, np.ndarray] | None:
    """The shared camera's setup (:func:`pycolmap_camera_setup`) and its starting
    (fx, fy, cx, cy) in pixels (fy = fx for a single focal length); None where
    pycolmap cannot express ``free_parameters``."""
    setup = pycolmap_camera_setup(free_parameters)
    if setup is None:
        return None
    intrinsics = np.asarray(estimate, dtype=float).copy()
    if setup[0] == "SIMPLE_PINHOLE":
        intrinsics[1] = intrinsics[0]
    return (*setup, intrinsics)


def _refined_directions(
    tied: bool, refine_focal: bool, refine_principal_point: bool, extra: int = 0
) -> np.ndarray:
    """A (4 + extra, k): (fx, fy, cx, cy, extra parameters) = A p for the k parameters an
    adjustment refines: one focal length (``tied``) or two, the principal point, and
    each of the ``extra`` (distortion) parameters."""
    q = 4 + extra
    unit = np.eye(q)
    columns = []
    if refine_focal:
        columns += [unit[0] + unit[1]] if tied else [unit[0], unit[1]]
    if refine_principal_point:
        columns += [unit[2], unit[3]]
    columns += [unit[4 + i] for i in range(extra)]
    return np.array(columns).reshape(-1, q).T


def _shared_camera(
    observed: list[_Observed],
    start: np.ndarray,
    intrinsics: np.ndarray,
    camera_model: str,
    size: tuple[int, int],
    workers: int | None = None,
    keypoints: list[np.ndarray] | None = None,
    distortion: np.ndarray | None = None,
) -> _SharedCamera | None:
    """Every triplet whose calibrated cameras can be formed at K, in one reconstruction
    (the cameras over ``workers`` threads; None: one per core). With ``keypoints`` (per
    triplet of ``observed``, (3, n, 2) pixels) the triplets are observed there through
    a camera whose distortion starts at ``distortion`` (:meth:`_SharedCamera.add`)."""
    shared = _SharedCamera(intrinsics, camera_model, *size, distortion)
    jobs = [(triplet, start, intrinsics) for triplet in observed]
    seen = keypoints if keypoints is not None else [None] * len(observed)
    cameras_of = map_jobs(_cameras_job, jobs, workers)
    for triplet, cameras, at in zip(observed, cameras_of, seen, strict=True):
        if cameras is not None and np.all(np.isfinite(cameras)):
            shared.add(triplet, cameras, at)
    return shared if shared.triplets else None


def _cameras_job(job: tuple[Any, ...]) -> np.ndarray | None:
    triplet, start, intrinsics = job
    normalised = (triplet.pixels - intrinsics[2:]) / intrinsics[:2]
    return calibrated_cameras(triplet.tensor, normalised, start, intrinsics)
