"""Robust trifocal tensor estimation for one image triplet.

1. Coordinates are normalised with the prior intrinsics, ``x̂ = K0⁻¹ x``: centred
   and of unit scale, which conditions the linear system as well as Hartley's
   normalisation and lets the tensor be calibrated later by ``M = K0⁻¹ K``.
2. MSAC over a pool of hypotheses scored by a geometric error: cameras
   ``P2, P3`` of each hypothesis, each track triangulated in closed form (its
   view-1 point plus the inverse depth that best fits views 2 and 3), and the
   squared reprojection errors of views 2 and 3 summed, in pixels. The pool:

   * minimal linear tensors (7 tracks each, all solved in one batched SVD);
   * one hypothesis from the prior intrinsics: the essential matrix of views 1-2
     (5-point RANSAC) and the pose of view 3 by PnP RANSAC on the triangulated
     tracks. When most tracks lie on one plane, linear 7-point samples are
     degenerate and many of the tensors they give are wrong (constraints no
     smaller at the true K than at the prior); neither the 5-point solver nor PnP
     is degenerate for planes, so this hypothesis wins there, and the projective
     refinement removes the prior's bias.
3. The best hypothesis is refined: its inliers (at most ``max_refined_tracks`` of
   them, a seeded random subset) by three-view
   projective bundle adjustment (:mod:`.projective_ba`), inliers re-selected with
   the refined cameras and refined once more; then on to convergence
   (``final_ba_tolerance``). With ``second_start`` the calibrated hypothesis is
   refined the same way too and the lower MSAC score wins: with little depth
   relief (a facade) the BA from one start can stop along a flat valley or in a
   local minimum. The caller asks for it only for tensors that disagree with the
   estimate (:mod:`colmap_trifocal.intrinsics.tensors.estimator`).

Optionally (``TensorEstimationOptions.planar_share``, off by default), a triplet
whose tracks mostly fit one plane gets a plane + parallax start as well
(:mod:`.planarity`).

The returned tensor is built from the refined cameras, so it is a geometrically
valid trifocal tensor, and it comes with the covariance of those cameras.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import NamedTuple

import cv2
import numpy as np

from ..common.log import logger
from .motion import recover_pose
from .planarity import DominantPlane, dominant_plane, plane_parallax_cameras
from .projective_ba import ProjectiveBAResult, initial_points, refine_triplet
from .tensor_estimation import BA_TOLERANCE, TensorEstimationOptions, TripletTensor, transfer_errors
from .trifocal import cameras_from_tensor, linear_tensor, normalize_tensor, tensor_from_cameras

#: Tracks of a minimal (linear) tensor hypothesis.
MINIMAL_SAMPLE = 7
#: Fewest inlier tracks the bundle adjustment starts from.
MIN_TRACKS_TO_REFINE = 12


def estimate_triplet_tensor(
    image_ids: tuple[int, int, int],
    x_px: np.ndarray,
    K0: np.ndarray,
    rng: np.random.Generator,
    options: TensorEstimationOptions | None = None,
    *,
    second_start: bool = True,
) -> TripletTensor | None:
    """MSAC + Gold Standard tensor for one triplet (:func:`fit_triplet`'s tensor).

    Args:
        image_ids: the database image ids of views 1, 2, 3.
        x_px: tracks (3, n, 2) in undistorted pixel coordinates (COLMAP convention).
        K0: prior intrinsics (3x3) used to normalise coordinates.
        rng: random generator (the result is reproducible for a seeded generator).
        options: estimation settings.
        second_start: also refine the calibrated hypothesis (when
            ``options.calibrated_start``); False refines the best MSAC hypothesis
            only. The generator is used the same way either way, so with the same
            seed both give the same first start.

    Returns:
        The refined tensor, or None when fewer than ``min_inliers`` tracks agree.
    """
    fit = fit_triplet(image_ids, x_px, K0, rng, options, second_start=second_start)
    return None if fit is None else fit.tensor


@dataclass
class TripletFit:
    """One triplet's refined starts at one normalisation K0, and the start it deferred.

    The tensor is the refined start with the lowest MSAC score. ``deferred`` is the
    calibrated hypothesis where it was left unrefined (``second_start=False``):
    :meth:`with_second_start` refines it alone, which gives exactly what
    :func:`fit_triplet` with ``second_start=True`` gives from the same seed, at the cost
    of one start instead of the hypotheses and both starts again.

    Attributes:
        image_ids: views 1, 2, 3.
        x: tracks (3, n, 2) normalised by K0.
        pixel_scale: (fx0, fy0) of K0, pixels per normalised unit.
        order: the random order of the tracks every refinement round uses.
        options: the estimation settings.
        candidates: per refined start, (BA result, inliers (n,) bool, MSAC score px²).
        deferred: cameras (P2, P3) of the unrefined calibrated hypothesis, or None.
    """

    image_ids: tuple[int, int, int]
    x: np.ndarray = field(repr=False)
    pixel_scale: np.ndarray
    order: np.ndarray = field(repr=False)
    options: TensorEstimationOptions
    candidates: list[tuple[ProjectiveBAResult, np.ndarray, float]] = field(repr=False)
    deferred: tuple[np.ndarray, np.ndarray] | None = field(repr=False)

    @cached_property
    def tensor(self) -> TripletTensor | None:
        """The lowest-score start's tensor; None when no start refined or fewer than
        ``min_inliers`` tracks agree with it."""
        if not self.candidates:
            return None
        result, inliers, _ = min(self.candidates, key=lambda c: c[2])
        if inliers.sum() < self.options.min_inliers:
            return None
        P2, P3 = result.P2, result.P3
        return TripletTensor(
            image_ids=self.image_ids,
            tensor=normalize_tensor(tensor_from_cameras(P2, P3)),
            P2=P2,
            P3=P3,
            camera_covariance=result.camera_covariance,
            num_tracks=self.x.shape[1],
            num_inliers=int(inliers.sum()),
            sigma_px=result.sigma,
            inliers=inliers,
        )

    def with_second_start(self) -> TripletFit:
        """The fit with its deferred calibrated hypothesis refined too (itself where
        nothing was deferred)."""
        if self.deferred is None:
            return self
        return replace(
            self, candidates=self.candidates + self._refined([self.deferred]), deferred=None
        )

    def _refine(
        self,
        P2: np.ndarray,
        P3: np.ndarray,
        threshold2: float,
        tolerance: float,
        iterations: int | None = None,
        points: np.ndarray | None = None,
    ) -> _Refinement | None:
        """Bundle adjustment and inlier re-selection from cameras P2, P3 (see the module steps).

        The tracks' one random order (``self.order``) serves every round (later rounds
        refine mostly the same tracks, warm-started from their refined points). Returns
        the last BA result, the inliers, the MSAC score and where every track's point
        would start another round (:class:`_Refinement`), or None when the BA fails or
        too few tracks agree. ``tolerance`` and ``iterations`` (default
        ``options.max_ba_iterations``) are the BA's stopping rule; ``points`` (n, 3)
        the tracks' (u, v, ρ) to start from (default: in closed form at P2, P3).
        """
        x, pixel_scale, order, options = self.x, self.pixel_scale, self.order, self.options
        iterations = options.max_ba_iterations if iterations is None else iterations
        n = x.shape[1]
        inliers = transfer_errors(x, P2, P3, pixel_scale) < threshold2
        # Refinement can grow a small initial consensus (a prior far off, heavy noise),
        # so min_inliers is only checked after it; the BA needs a few tracks to start.
        if inliers.sum() < MIN_TRACKS_TO_REFINE:
            return None
        points = initial_points(x, P2, P3) if points is None else points
        result: ProjectiveBAResult | None = None
        errors = np.zeros(n)
        for _ in range(options.refinement_rounds):
            used = np.sort(order[inliers[order]][: options.max_refined_tracks])
            result = refine_triplet(
                x[:, used], P2, P3, pixel_scale, points[used], iterations, tolerance
            )
            if not (np.all(np.isfinite(result.camera_covariance)) and np.isfinite(result.sigma)):
                return None
            P2, P3 = result.P2, result.P3
            # Warm start of the next round: refined points where known, closed form elsewhere.
            points = initial_points(x, P2, P3)
            points[used] = result.points
            errors = transfer_errors(x, P2, P3, pixel_scale)
            new_inliers = errors < threshold2
            if new_inliers.sum() < MIN_TRACKS_TO_REFINE:
                return None
            # Converged when at most 0.5 % of the tracks changed side: on real data a few
            # borderline tracks flip at every round, so exact equality would never stop.
            converged = np.count_nonzero(new_inliers != inliers) <= max(2, 0.005 * n)
            inliers = new_inliers
            if converged:
                break
        assert result is not None
        return _Refinement(result, inliers, float(np.minimum(errors, threshold2).sum()), points)

    def _refined(
        self, starts: list[tuple[np.ndarray, np.ndarray]]
    ) -> list[tuple[ProjectiveBAResult, np.ndarray, float]]:
        """Each start refined (:func:`_refine`), then on to convergence where
        ``final_ba_tolerance`` asks for it; the starts whose refinement fails dropped."""
        options = self.options
        threshold2 = options.inlier_threshold_px**2
        refined = [self._refine(P2, P3, threshold2, BA_TOLERANCE) for P2, P3 in starts]
        candidates = [r for r in refined if r is not None]
        if options.final_ba_tolerance < BA_TOLERANCE:
            # With little depth relief (a facade) the BA crawls along a flat valley
            # (relative decreases below 1e-4 long before the minimum), and each start
            # can end in its own local minimum: every start is refined on to
            # convergence, from its points as refined so far, and the lowest MSAC
            # score wins (docs/planar_and_sequences.md).
            candidates = [
                self._refine(
                    r.result.P2,
                    r.result.P3,
                    threshold2,
                    options.final_ba_tolerance,
                    options.final_ba_iterations,
                    r.points,
                )
                or r
                for r in candidates
            ]
        return [(r.result, r.inliers, r.score) for r in candidates]


class _Refinement(NamedTuple):
    """A start refined (:meth:`TripletFit._refine`): the last BA result, the inliers (n,)
    bool, the MSAC score over all tracks (squared pixel errors truncated at the
    threshold, px²), and every track's (u, v, ρ) (n, 3) where another round would start
    (the refined points where the BA used the track, in closed form elsewhere)."""

    result: ProjectiveBAResult
    inliers: np.ndarray
    score: float
    points: np.ndarray


def fit_triplet(
    image_ids: tuple[int, int, int],
    x_px: np.ndarray,
    K0: np.ndarray,
    rng: np.random.Generator,
    options: TensorEstimationOptions | None = None,
    *,
    second_start: bool = True,
) -> TripletFit | None:
    """The MSAC hypotheses of one triplet and their refined starts (see the module
    steps; arguments as :func:`estimate_triplet_tensor`); None when the triplet has
    fewer tracks than ``min_inliers`` or a minimal sample."""
    options = options or TensorEstimationOptions()
    n = x_px.shape[1]
    if n < max(options.min_inliers, MINIMAL_SAMPLE):
        return None
    pixel_scale = np.array([K0[0, 0], K0[1, 1]])
    homogeneous = np.concatenate([x_px, np.ones((3, n, 1))], axis=2)
    x = (homogeneous @ np.linalg.inv(K0).T)[..., :2]
    threshold2 = options.inlier_threshold_px**2

    scored = (
        np.arange(n)
        if n <= options.max_scored_tracks
        else np.sort(rng.choice(n, size=options.max_scored_tracks, replace=False))
    )
    P2h, P3h, calibrated = _hypotheses(x, scored, rng, options, pixel_scale)
    plane, parallax = _planar_start(x, options, pixel_scale, rng)
    planar = plane is not None
    starts: list[tuple[np.ndarray, np.ndarray]] = [] if parallax is None else [parallax]
    errors = transfer_errors(x[:, scored], P2h, P3h, pixel_scale)
    scores = np.minimum(errors, threshold2).sum(axis=1)
    best = int(np.argmin(scores))
    starts.insert(0, (P2h[best], P3h[best]))
    deferred = None
    if calibrated is not None and best != len(P2h) - 1:
        if planar or (options.calibrated_start and second_start):
            starts.append(calibrated)
        elif options.calibrated_start:
            deferred = calibrated
    fit = TripletFit(image_ids, x, pixel_scale, rng.permutation(n), options, [], deferred)
    fit.candidates = fit._refined(starts)
    logger.debug(
        "triplet %s: %s%d start(s)%s",
        image_ids,
        f"planar ({plane.share:.0%} on one plane), " if planar and plane is not None else "",
        len(starts),
        ", the calibrated one deferred" if deferred is not None else "",
    )
    return fit


def _planar_start(
    x: np.ndarray,
    options: TensorEstimationOptions,
    pixel_scale: np.ndarray,
    rng: np.random.Generator,
) -> tuple[DominantPlane | None, tuple[np.ndarray, np.ndarray] | None]:
    """The dominant plane of the tracks x (3, n, 2) when it holds ``planar_share`` of
    them (else None), and the plane + parallax start from it (None: none)."""
    if not options.planar_share <= 1.0:
        return None, None
    plane = dominant_plane(x, options.inlier_threshold_px / pixel_scale.mean())
    if plane is None or plane.share < options.planar_share:
        return None, None
    parallax = plane_parallax_cameras(
        x, plane, options.inlier_threshold_px / pixel_scale.mean(), rng
    )
    return plane, parallax


def _hypotheses(
    x: np.ndarray,
    scored: np.ndarray,
    rng: np.random.Generator,
    options: TensorEstimationOptions,
    pixel_scale: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
    """The MSAC pool's cameras P2, P3 (h, 3, 4): minimal linear tensors of random
    7-track samples, then the calibrated hypothesis where there is one (also returned
    alone)."""
    n = x.shape[1]
    samples = np.argpartition(rng.random((options.num_hypotheses, n)), MINIMAL_SAMPLE, axis=1)
    hypotheses = linear_tensor(*(x[view][samples[:, :MINIMAL_SAMPLE]] for view in range(3)))
    P2h, P3h = cameras_from_tensor(hypotheses)
    calibrated = calibrated_hypothesis(
        x[:, scored], options.inlier_threshold_px / pixel_scale.mean()
    )
    if calibrated is not None:
        P2h = np.concatenate([P2h, calibrated[0][None]])
        P3h = np.concatenate([P3h, calibrated[1][None]])
    return P2h, P3h, calibrated


def calibrated_hypothesis(
    x: np.ndarray, threshold: float, pnp_iterations: int = 100, essential_iterations: int = 1000
) -> tuple[np.ndarray, np.ndarray] | None:
    """Cameras ``[R2|t2]``, ``[R3|t3]`` of a triplet from prior-normalised tracks x (3, n, 2).

    Views 1-2: essential matrix (OpenCV's USAC with the 5-point solver: a tenth of the
    cost of its plain RANSAC at the same iteration bound, with as many inliers or more)
    and the cheirality check (:func:`.motion.recover_pose`);
    view 3: PnP RANSAC on the tracks triangulated from views 1-2 (AP3P's minimal
    four-point samples, a third of SQPnP's cost per iteration), then SQPnP on its
    inliers.
    ``threshold`` is the inlier threshold in normalised units (pixels / focal);
    ``pnp_iterations`` and ``essential_iterations`` bound the two RANSACs (which run
    to their bounds where few tracks fit: at a wrong focal length).
    Returns None where OpenCV finds no solution.
    """
    identity = np.eye(3)
    x1, x2, x3 = (np.ascontiguousarray(x[view]) for view in range(3))
    E, mask = cv2.findEssentialMat(
        x1,
        x2,
        identity,
        method=cv2.USAC_DEFAULT,
        prob=0.999,
        threshold=threshold,
        maxIters=essential_iterations,
    )
    if E is None or E.shape != (3, 3):
        return None
    _, R2, t2, good = recover_pose(E, x1, x2, mask)
    P2 = np.hstack([R2, t2[:, None]])
    if good.sum() < 6:
        return None
    X = cv2.triangulatePoints(np.eye(3, 4), P2, x1[good].T, x2[good].T)
    X = (X[:3] / X[3]).T
    try:  # SQPnP asserts on degenerate points, e.g. all on one line
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            X,
            x3[good],
            identity,
            None,
            reprojectionError=threshold,
            flags=cv2.SOLVEPNP_AP3P,
            iterationsCount=pnp_iterations,
        )
        if not ok or inliers is None or len(inliers) < 6:
            return None
        inliers = inliers.ravel()
        ok, rvec, tvec = cv2.solvePnP(
            X[inliers], x3[good][inliers], identity, None, flags=cv2.SOLVEPNP_SQPNP
        )
    except cv2.error:
        return None
    if not ok:
        return None
    P3 = np.hstack([cv2.Rodrigues(rvec)[0], tvec.reshape(3, 1)])
    return P2, P3
