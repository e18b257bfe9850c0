"""Radial distortion from the triplets, before any reconstruction.

Why. A lens whose distortion the stored camera does not hold (COLMAP's default
``SIMPLE_RADIAL`` with k = 0, or a ``PINHOLE`` camera on a real lens) bends every
track the same way: every tensor then agrees on the same wrong focal length
(docs/lenses.md), and neither the projective three-view residual nor the
constraints single out k1. A *calibrated* bundle adjustment does: the agreeing
triplets, each with its own poses and points, share one camera whose distortion
parameters are free, and their tracks together span the image up to its corners.

What. The calibrated triplets of :mod:`intrinsics.polish.bundle` (their poses and points from
the tensors at the estimate) in one pycolmap reconstruction whose camera is the
stored model (``SIMPLE_RADIAL``: k; ``RADIAL``: k1, k2; ``OPENCV``: k1, k2, p1, p2), or
for a pinhole camera ``SIMPLE_RADIAL`` (``SIMPLE_PINHOLE``) or ``OPENCV`` (``PINHOLE``);
a pinhole camera stays pinhole: the distortion found there only widens the std and
names the cause. Two rounds of "adjust every triplet at
the camera, keep those with λ < τ², adjust them together with the camera free". The
distortion counts as present when the likelihood ratio of the fits with and without
it, ``(C₀ − C_k) / σ²``, exceeds the χ² quantile ``1 − SIGNIFICANCE`` of its number of
parameters (where the adjustment's own Wald statistic is ``DECISIVE`` times beyond that
quantile, the pinhole fit C₀ is not run: a strong lens's crawls for seconds to confirm
it); the std comes from pycolmap's covariance of the adjustment
(:func:`pycolmap.estimate_ba_covariance`, each triplet's scale fixed by one of its
points), scaled by σ² of the residuals, or for
``SIMPLE_RADIAL`` / ``RADIAL`` the delete-a-group-of-images jackknife where it is larger
(as the polish's, :mod:`intrinsics.polish.bundle`).

A stored camera whose distortion is not all 0 is taken as stored: its keypoints are
already undistorted with it. Intrinsics are (fx, fy, cx, cy) in pixels, COLMAP's pixel
convention (the centre of the top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
import pycolmap
from scipy.stats import chi2

from ...common.log import keep_colmap_quiet
from ...common.parallel import Beside
from ...database.cameras import CameraInfo
from ...geometry.tensor_estimation import TripletTensor
from ..polish.calibrated_tracks import Observed, inlier_pixels
from ..polish.camera_setup import CameraSetup, Refined, pycolmap_camera_setup
from ..polish.shared_camera import (
    Agreement,
    RawObservations,
    SharedCamera,
    agree_and_adjust,
    observed_at,
    shared_camera,
)
from ..solve.observability import HELD_FOCAL_STD
from ..solve.parametrization import FreeParameters
from .fit_statistics import (
    MAX_TRACKS,
    RADIAL_MODELS,
    camera_params_std,
    cost_without_distortion,
    intrinsics_std_of,
    jackknife_std,
    screen_statistic,
)
from .search import LensSearchResult, polynomial_start

#: Probability that the test finds distortion in an undistorted lens (χ² tail): low
#: power costs more than a false alarm, whose joint estimate is still unbiased and
#: carries its own (larger) std...
SIGNIFICANCE = 0.05
#: ... and in a pinhole camera, where the finding is only a warning and OPENCV's
#: tangential terms (p1, p2) also take up systematic errors that are not the lens's.
PINHOLE_SIGNIFICANCE = 1e-6
#: The pinhole fit C₀ is skipped, and the distortion present, where the Wald statistic of
#: pycolmap's covariance exceeds the test's threshold this many times: the likelihood
#: ratio is then far beyond it too (the Wald statistic overstates it on a real lens, by
#: far less than this factor: docs/lenses.md).
DECISIVE = 100.0
#: The screen skips the adjustment where one Gauss–Newton step predicts a likelihood
#: ratio below this fraction of the test's one-parameter threshold.
SCREEN_FACTOR = 0.5
#: Ceres iterations after which the lens route's first adjustment (every triplet in
#: front of its cameras, from the warp's polynomial) leaves out the triplets whose points
#: it has carried behind their cameras, and goes on without them: such a triplet keeps
#: the others crawling (EuRoC: 103 iterations, 1.1 s, where without it 13 converge).
#: Those that converge take 9–42 on the real scenes.
FIRST_CHECK_ITERATIONS = 50
#: Triplets that must agree before the distortion is estimated at all.
MIN_TRIPLETS = 2
#: The model a pinhole camera's distortion is looked for with (its own focal lengths).
_DETECTION_MODELS = {"SIMPLE_PINHOLE": "SIMPLE_RADIAL", "PINHOLE": "OPENCV"}
#: Radial terms (k1[, k2]) of the models the lens route adjusts from a warp, COLMAP's
#: order (they come first among the model's distortion parameters).
RADIAL_PARAMETERS = {"SIMPLE_RADIAL": 1, "RADIAL": 2, "OPENCV": 2}
#: A stored model and the next one with one more radial term, fitted where the stored
#: model finds distortion: a real lens (a drone's, a wide phone's) often needs k2, and a
#: k1-only fit then takes up the rest with the focal length (docs/lenses.md).
_RICHER_MODELS = {"SIMPLE_RADIAL": "RADIAL"}


@dataclass
class LensStart:
    """Raw tracks, and where their distortion starts, for tracks that were warped.

    Attributes:
        tracks: per triplet (image ids), its tracks (3, n, 2) as observed, pixels.
        warp: the lens search's warp the tracks the tensors saw were undone with.
        intrinsics: (fx, fy, cx, cy) the lens stage starts from, pixels.
    """

    tracks: dict[tuple[int, int, int], np.ndarray]
    warp: LensSearchResult
    intrinsics: np.ndarray

    def distortion(self, model: str) -> np.ndarray:
        """``model``'s extra parameters (COLMAP's order) nearest the warp at
        :attr:`intrinsics`: its radial terms (:data:`RADIAL_PARAMETERS`) fitted out to the
        farthest raw track, the rest 0. Each model starts from its own nearest
        polynomial: a ``RADIAL`` fit started at the one-term k1 with k2 = 0 starts
        further from a strong lens's optimum, and takes longer to reach it
        (docs/lenses.md, "Each model's own start")."""
        warp = self.warp
        farthest = max(
            float(np.max(np.linalg.norm(x - warp.centre, axis=-1))) for x in self.tracks.values()
        )
        radial = polynomial_start(warp, self.intrinsics, RADIAL_PARAMETERS[model], farthest)
        start = np.zeros(len(CameraInfo.blank(model).distortion))
        start[: len(radial)] = radial
        return start


@dataclass
class LensDistortion:
    """The camera with its distortion estimated from the agreeing triplets.

    Attributes:
        camera_model: the COLMAP model the adjustment used.
        intrinsics: (fx, fy, cx, cy) adjusted jointly with the distortion, pixels.
        intrinsics_std: (4,) their std, pixels (0 for a parameter held).
        distortion: the model's extra parameters (k1, ...), as COLMAP orders them.
        distortion_std: (k,) their std.
        statistic: likelihood ratio ``(C₀ − C_k) / σ²`` of the fits without and with
            the distortion (χ² with k degrees of freedom where the lens has none); where
            the distortion is decisive (``DECISIVE``), the Wald statistic instead (C₀ is
            not computed); NaN for a fit that was not tested.
        threshold: the statistic above which the distortion counts as present.
        agreeing: triplets adjusted together (with ``screened``: the tensors the
            screen read).
        screened: the adjustment was not run: the screen's statistic (``statistic``,
            one Gauss–Newton step) showed no sign of distortion; ``distortion`` is 0
            and the std unknown (NaN).
        misfit: the model cannot hold the lens's distortion (warped tracks only: no
            triplet fits it as well as a projective camera); the values are the warped
            estimate's and the warp's nearest polynomial, each std at least its
            distance from the model's closest camera.
        richer_model: the model with one more radial term whose extra term the tracks
            determine (beyond the test's threshold), so the stored model cannot hold
            the lens; the intrinsics are that model's fit, the distortion the stored
            model's, each std at least the distance between the two fits. None where
            the stored model holds the lens (or has no richer model).
        richer_distortion: that model's fitted distortion (COLMAP's order), None
            without ``richer_model``: with ``intrinsics`` the camera to map with.
        fits: where ``intrinsics_std`` was widened to reach another fit of the same
            tracks (``richer_model``: the stored model's), each fit's (fx, fy, cx, cy)
            and its own std, pixels, the reported one first; empty where the std is
            one fit's own. A value outside every fit's own interval is one that no
            model of the lens supports, however wide the widened std.
    """

    camera_model: str
    intrinsics: np.ndarray
    intrinsics_std: np.ndarray
    distortion: np.ndarray
    distortion_std: np.ndarray
    statistic: float
    threshold: float
    agreeing: int
    screened: bool = False
    misfit: bool = False
    richer_model: str | None = None
    richer_distortion: np.ndarray | None = None
    fits: tuple[tuple[np.ndarray, np.ndarray], ...] = ()

    @property
    def present(self) -> bool:
        """Whether the tracks show distortion the stored camera does not hold."""
        return self.statistic > self.threshold

    def corner_bend(self, width: int, height: int) -> float:
        """How far the fitted lens moves the image corner farthest from its principal
        point, relative to the corner's undistorted distance from it (0: no distortion;
        inf where the model does not reach the corner). A phone's main lens moves it by
        a few percent (k1 −0.06 at 3072×2048: 2.9 %); EuRoC's drone lens by a quarter in its
        ``RADIAL`` fit, and its ``SIMPLE_RADIAL`` k (−0.18) folds before the corner (inf)."""
        fx, fy, cx, cy = map(float, self.intrinsics)
        camera = CameraInfo.of_model(
            1, self.camera_model, width, height, self.intrinsics, self.distortion
        ).to_pycolmap()
        corners = np.array([[0.0, 0.0], [width, 0.0], [0.0, height], [width, height]])
        farthest = corners[np.argmax(np.linalg.norm(corners - [cx, cy], axis=1))]
        undistorted = np.asarray(camera.cam_from_img(farthest[None]), float).reshape(-1)[:2]
        distorted = (farthest - [cx, cy]) / [fx, fy]
        ratio = np.linalg.norm(distorted) / np.linalg.norm(undistorted)
        return float(abs(ratio - 1.0)) if np.isfinite(ratio) else float("inf")

    def summary(self) -> dict[str, Any]:
        """The JSON ``lens_distortion`` report."""
        return {
            "camera_model": self.camera_model,
            "present": self.present,
            "params": [float(v) for v in self.distortion],
            "std": [float(v) if np.isfinite(v) else None for v in self.distortion_std],
            "screened": self.screened,
            "misfit": self.misfit,
            "richer_model": self.richer_model,
            "richer_params": None
            if self.richer_distortion is None
            else [float(v) for v in self.richer_distortion],
            "statistic": float(self.statistic),
            "threshold": float(self.threshold),
            "agreeing": self.agreeing,
            "intrinsics": [float(v) for v in self.intrinsics],
        }


def distortion_model(camera: CameraInfo) -> str | None:
    """The COLMAP model the distortion is estimated with, None when it is taken as stored
    (distortion parameters not all 0)."""
    if not camera.is_undistorted:
        return None
    return _DETECTION_MODELS.get(camera.model, camera.model)


@dataclass(frozen=True)
class DistortionInput:
    """What the lens stage reads.

    Attributes:
        tensors: the solve's tensors, normalised by ``start``.
        tracks: per triplet (image ids), its tracks (3, n, 2), pixels.
        start: the tensors' normalisation (fx0, fy0, cx0, cy0), pixels.
        estimate: the estimate so far (fx, fy, cx, cy), pixels.
        free_parameters: which of (fx, fy, cx, cy) are estimated (held ones stay).
        camera: the stored camera (model, size, distortion).
        tau: the MSAC threshold; triplets with ``λ < τ²`` agree.
        agreeing_tensors: (n,) bool, the tensors that agree with ``estimate`` (the
            screen reads only those; None: all).
        workers: threads for the per-triplet work (None: one per core).
        observed: where ``tracks`` were warped from the raw keypoints (the lens
            search, :mod:`intrinsics.lens.search`): the raw tracks and the distortion the
            adjustment starts from; the distortion is then known to be there (no
            screen) and is adjusted from the raw tracks.
    """

    tensors: list[TripletTensor]
    tracks: dict[tuple[int, int, int], np.ndarray]
    start: np.ndarray
    estimate: np.ndarray
    free_parameters: FreeParameters
    camera: CameraInfo
    tau: float
    agreeing_tensors: np.ndarray | None = None
    workers: int | None = None
    observed: LensStart | None = None


@dataclass(frozen=True)
class _Fits:
    """The triplets each model is fitted to: their tracks and projective costs, and
    their calibrated cameras (None where not formed) at the stage's starting K."""

    observed: list[Observed]
    cameras: list[np.ndarray | None]


@dataclass(frozen=True)
class _Adjustment:
    """The lens stage's adjustment: the shared camera, its model, what it refines, the
    agreeing triplets, pycolmap's covariance, and on warped tracks the distortion it
    started from (the warp's nearest polynomial, :meth:`LensStart.distortion`)."""

    shared: SharedCamera
    camera_model: str
    refined: Refined
    agreement: Agreement
    covariance: pycolmap.BACovariance | None
    start_distortion: np.ndarray | None = None


def estimate_distortion(lens: DistortionInput) -> LensDistortion | None:
    """The camera's distortion, focal length and principal point from its triplets.

    Returns None when the distortion is taken as stored, the solve estimates nothing,
    fewer than ``MIN_TRIPLETS`` triplets agree, or Ceres fails.
    """
    camera = lens.camera
    camera_model = distortion_model(camera)
    if camera_model is None or not lens.tensors:
        return None
    setup = _lens_setup(lens.free_parameters)
    if setup is None:
        return None
    intrinsics = np.asarray(lens.estimate, float).copy()
    if camera.single_focal:
        intrinsics[1] = intrinsics[0]
    significance = SIGNIFICANCE if camera_model == camera.model else PINHOLE_SIGNIFICANCE
    mask = (
        np.ones(len(lens.tensors), bool) if lens.agreeing_tensors is None else lens.agreeing_tensors
    )
    if lens.observed is None:
        screened = _screened(lens, mask, intrinsics, setup, camera_model, significance)
        if screened is not None:
            return screened
    # Each tensor's tracks and projective cost, the same for every model fitted below.
    fits = _Fits(
        *observed_at(lens.tensors, lens.tracks, lens.start, intrinsics, MAX_TRACKS, lens.workers)
    )
    richer = _RICHER_MODELS.get(camera_model) if camera_model == camera.model else None
    # The richer model's fit does not depend on the stored model's, which decides whether
    # it is used: it runs beside it, in a forked process where that is safe.
    richer_fit = (
        _no_fit
        if richer is None
        else partial(_richer_fit, lens, fits, mask, intrinsics, setup.refined, richer)
    )
    with Beside(richer_fit, workers=1 if richer is None else lens.workers) as beside:
        adjustment = _adjust(lens, fits, mask, intrinsics, setup.refined, camera_model)
        if adjustment is None:
            return None
        fitted = _fitted(lens, adjustment, intrinsics, significance)
        if richer is None or not fitted.present or fitted.misfit:
            return fitted
        wider = beside.result()
    return fitted if wider is None else _with_richer_model(fitted, wider, richer)


def _no_fit() -> None:
    """Nothing fitted beside (:class:`..common.parallel.Beside` of nothing)."""
    return None


def _richer_fit(
    lens: DistortionInput,
    fits: _Fits,
    mask: np.ndarray,
    intrinsics: np.ndarray,
    refined: Refined,
    richer: str,
) -> LensDistortion | None:
    """``richer``'s fit of the same triplets (started from the warp's nearest polynomial
    with its terms on the lens route, else with its extra terms at 0), None where its
    adjustment fails."""
    adjustment = _adjust(lens, fits, mask, intrinsics, refined, richer)
    return None if adjustment is None else _fitted(lens, adjustment, intrinsics, significance=None)


def _with_richer_model(
    fitted: LensDistortion, wider: LensDistortion, richer: str
) -> LensDistortion:
    """``fitted`` (the stored model's fit), or where ``richer``'s extra radial term is
    determined in its fit ``wider`` (a Wald test at ``SIGNIFICANCE``: |k| / std beyond
    the normal quantile) the intrinsics of ``richer``'s fit with the stored model's
    distortion.

    The two fits are two answers to which camera made the tracks; the data reject the
    stored model's, and the richer one may itself miss a term (tangential, k3), so each
    std is at least the distance between them. A stored model's fit whose f is known no
    better than a held start's (``HELD_FOCAL_STD``) is no answer: the richer fit's own
    std stands.
    """
    extra, extra_std = wider.distortion[-1], wider.distortion_std[-1]
    if wider.misfit or not (np.isfinite(extra_std) and extra_std > 0):
        return fitted
    if (extra / extra_std) ** 2 <= chi2.isf(SIGNIFICANCE, 1):
        return fitted
    stored_terms = len(fitted.distortion)
    richer_fit = replace(
        fitted,
        intrinsics=wider.intrinsics,
        intrinsics_std=wider.intrinsics_std,
        distortion_std=np.fmax(
            fitted.distortion_std, np.abs(wider.distortion[:stored_terms] - fitted.distortion)
        ),
        agreeing=wider.agreeing,
        richer_model=richer,
        richer_distortion=wider.distortion.copy(),
    )
    if fitted.intrinsics_std[0] >= HELD_FOCAL_STD * fitted.intrinsics[0]:
        # The stored model's fit knows f no better than a held start: it ran off along
        # the focal length and answers nothing (EuRoC's first 5 frames: 834 ± 420 px,
        # the RADIAL fit 474 ± 18, truth 459).
        return richer_fit
    # Adding a term to a fit cannot make K better known than the fit without it.
    own_std = np.fmax(wider.intrinsics_std, fitted.intrinsics_std)
    return replace(
        richer_fit,
        intrinsics_std=np.fmax(own_std, np.abs(wider.intrinsics - fitted.intrinsics)),
        fits=((wider.intrinsics, own_std), (fitted.intrinsics, fitted.intrinsics_std)),
    )


def _screened(
    lens: DistortionInput,
    mask: np.ndarray,
    intrinsics: np.ndarray,
    setup: CameraSetup,
    camera_model: str,
    significance: float,
) -> LensDistortion | None:
    """The stage's result where the screen finds freeing k would not lower the cost by a
    fraction of what counts (the adjustment is then not run), else None."""
    screen_tensors = [t for t, keep in zip(lens.tensors, mask, strict=True) if keep]
    screened = screen_statistic(
        screen_tensors,
        lens.tracks,
        lens.start,
        intrinsics,
        setup.refined,
        tied=camera_model in RADIAL_MODELS or lens.camera.single_focal,
        workers=lens.workers,
    )
    if screened is None or screened >= SCREEN_FACTOR * chi2.isf(significance, 1):
        return None
    zeros = np.zeros(len(CameraInfo.blank(camera_model).distortion))
    return LensDistortion(
        camera_model=camera_model,
        intrinsics=intrinsics,
        intrinsics_std=np.full(4, np.nan),
        distortion=zeros,
        distortion_std=np.full(len(zeros), np.nan),
        statistic=screened,
        threshold=float(chi2.isf(significance, len(zeros))),
        agreeing=len(screen_tensors),
        screened=True,
    )


def _adjust(
    lens: DistortionInput,
    fits: _Fits,
    mask: np.ndarray,
    intrinsics: np.ndarray,
    refined: Refined,
    camera_model: str,
) -> _Adjustment | None:
    """The agreeing triplets (of ``fits``) adjusted with the camera's distortion free,
    and the adjustment's covariance; None where too few triplets agree or Ceres fails."""
    camera, observed = lens.camera, lens.observed
    raw = None
    if observed is not None:
        keypoints = [
            inlier_pixels(fit.tensor, observed.tracks, MAX_TRACKS) for fit in fits.observed
        ]
        raw = RawObservations(keypoints, observed.distortion(camera_model))
    start_distortion = None if raw is None else raw.distortion
    size = (camera.width, camera.height)
    shared = shared_camera(fits.observed, fits.cameras, intrinsics, camera_model, size, raw)
    if shared is None:
        return None
    with_distortion = replace(refined, distortion=True)
    # Triplets the first joint adjustment fitted to convergence with the camera are each
    # at their own optimum for it: the rounds do not adjust them again one by one, nor
    # together where they are the agreeing ones.
    adjusted: list[int] = []
    with keep_colmap_quiet():
        if observed is not None:
            # The start's distortion is the warp's nearest polynomial, not the
            # camera's: every triplet adjusted with it first, so that λ compares fits.
            # A triplet with a point behind its cameras has no calibrated fit to start
            # from; in a joint problem it keeps Ceres iterating for all to its bound.
            # It stays out (its λ is inf: :meth:`SharedCamera.adjust_each`).
            valid = [p for p, triplet in enumerate(shared.triplets) if triplet.in_front]
            if len(valid) < MIN_TRIPLETS:
                return None
            first = shared.solve(valid, with_distortion, max_iterations=FIRST_CHECK_ITERATIONS)
            if first.termination_type == pycolmap.BundleAdjustmentTerminationType.NO_CONVERGENCE:
                # A triplet whose points it carried behind their cameras keeps it
                # crawling: such triplets leave (marked, their λ inf), and the others'
                # adjustment goes on from where it is.
                valid = shared.still_in_front(valid)
                if len(valid) < MIN_TRIPLETS:
                    return None
                first = shared.solve(valid, with_distortion)
            if not first.is_solution_usable():
                return None
            if first.termination_type == pycolmap.BundleAdjustmentTerminationType.CONVERGENCE:
                adjusted = valid
        # No triplet fitting the model as well as a projective camera: the model cannot
        # hold this lens. The tensors that agreed on the warped tracks give its closest
        # camera, which sets the reported std (:func:`_fitted`).
        agreement = agree_and_adjust(
            shared,
            lens.tau**2,
            with_distortion,
            minimum=MIN_TRIPLETS,
            fallback=None
            if observed is None
            else (lambda: [p for p, t in enumerate(shared.triplets) if mask[t.index]]),
            adjusted=adjusted,
        )
        if agreement is None:
            return None
        # At the optimum already: the covariance of the adjustment with its gauge fixed.
        adjuster = shared.adjuster(agreement.agreeing, with_distortion, fix_scale=True)
        covariance = pycolmap.estimate_ba_covariance(
            pycolmap.BACovarianceOptions(), shared.reconstruction, adjuster
        )
    return _Adjustment(shared, camera_model, refined, agreement, covariance, start_distortion)


def _fitted(
    lens: DistortionInput,
    adjustment: _Adjustment,
    intrinsics: np.ndarray,
    significance: float | None,
) -> LensDistortion:
    """The stage's result from its adjustment: the fitted camera, its std (pycolmap's
    covariance and the image jackknife, the larger), and the test's statistic at
    ``significance`` (None: no test, the statistic NaN)."""
    camera, observed = lens.camera, lens.observed
    shared, agreeing = adjustment.shared, adjustment.agreement.agreeing
    misfit = adjustment.agreement.fallback
    refined = adjustment.refined
    adjusted = shared.camera
    params = np.asarray(adjusted.params, dtype=float)
    with_distortion = shared.cost(agreeing)
    extra = list(adjusted.extra_params_idxs())
    points = sum(len(shared.triplets[p].point_ids) for p in agreeing)
    free = len(params) if refined.principal_point else len(params) - 2
    variance = with_distortion / max(6 * points - (3 * points + 11 * len(agreeing)) - free, 1)
    refined_idxs = (list(adjusted.focal_length_idxs()) if refined.focal else []) + (
        list(adjusted.principal_point_idxs()) if refined.principal_point else []
    )
    params_std = camera_params_std(
        adjustment.covariance, adjusted, variance, sorted(refined_idxs + extra)
    )
    threshold = statistic = float("nan")
    if significance is not None:
        threshold = float(chi2.isf(significance, len(extra)))
        statistic = _test_statistic(
            adjustment, params[extra], params_std[extra], with_distortion, variance, threshold
        )
    fitted = CameraInfo(
        camera.camera_id, adjustment.camera_model, camera.width, camera.height, params
    )
    intrinsics_std = intrinsics_std_of(fitted, params_std)
    distortion_std = params_std[extra]
    jackknife = jackknife_std(
        shared, agreeing, fitted, lens.tensors, refine_principal_point=refined.principal_point
    )
    if jackknife is not None:
        intrinsics_std = np.maximum(intrinsics_std, jackknife[:4])
        distortion_std = np.maximum(distortion_std, jackknife[4:])
    reported, distortion_reported = fitted.intrinsics, params[extra]
    if misfit and observed is not None:
        # Two cameras explain the tracks: the warp's (``estimate``, on which the tensors
        # agreed) and the model's closest; the warp's is reported, with the warp's
        # nearest polynomial, each std at least the distance between the two.
        nearest = adjustment.start_distortion
        assert nearest is not None  # set wherever the tracks were warped
        reported, distortion_reported = intrinsics, nearest
        intrinsics_std = np.maximum(intrinsics_std, np.abs(fitted.intrinsics - intrinsics))
        distortion_std = np.maximum(distortion_std, np.abs(params[extra] - nearest))
    return LensDistortion(
        camera_model=adjustment.camera_model,
        intrinsics=reported,
        intrinsics_std=intrinsics_std,
        distortion=distortion_reported,
        distortion_std=distortion_std,
        statistic=statistic,
        threshold=threshold,
        agreeing=len(agreeing),
        misfit=misfit,
    )


def _test_statistic(
    adjustment: _Adjustment,
    distortion: np.ndarray,
    distortion_std: np.ndarray,
    with_distortion: float,
    variance: float,
    threshold: float,
) -> float:
    """The distortion test's statistic: the Wald statistic of pycolmap's covariance where
    it exceeds ``DECISIVE`` times the ``threshold`` (the largest z² of one term, a lower
    bound of the terms' joint one), else the likelihood ratio ``(C₀ − C_k) / σ²``
    (``with_distortion``: C_k, px²)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        wald = float(np.max((distortion / distortion_std) ** 2))
    if np.isfinite(wald) and wald > DECISIVE * threshold:
        return wald
    shared, agreeing = adjustment.shared, adjustment.agreement.agreeing
    without = cost_without_distortion(shared, agreeing, adjustment.refined)
    return (without - with_distortion) / variance


def _lens_setup(free_parameters: FreeParameters) -> CameraSetup | None:
    """(pinhole model, refine the focal length, refine the principal point) of the
    adjustment, None where the solve estimates nothing.

    pycolmap refines the principal point as one: where the solve held one coordinate
    (a lens whose unmodelled distortion left it undetermined is the case that needs
    the distortion most), both are refined from the estimate; the held coordinate
    keeps its start's std, which the adjustment's cannot undercut.
    """
    if free_parameters.dimension == 0:
        return None
    setup = pycolmap_camera_setup(free_parameters)
    if setup is not None:
        return setup
    model = "SIMPLE_PINHOLE" if free_parameters.focal == "tied" else "PINHOLE"
    return CameraSetup(model, Refined(focal=free_parameters.focal != "held", principal_point=True))
