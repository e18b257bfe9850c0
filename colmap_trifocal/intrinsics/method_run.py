"""One trifocal method on one camera's tracks: attempts from start candidates, the
solve, and what follows the chosen attempt (the held estimate, polish, lens stage).

An attempt is the tensors at a start K and their solve; where the estimate lands far
from the start, the disagreeing tensors are estimated again from it (a restart); where
enough tensors agree, the disagreeing ones are also refined from both starts. Other
starts (the focal search's candidates) follow while most tensors disagree. Intrinsics
(fx, fy, cx, cy) in pixels, COLMAP's pixel convention (the centre of the top-left pixel
at (0.5, 0.5)).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..common.errors import CalibrationError
from ..common.log import logger
from ..common.timing import StageClock
from .camera_input import CameraInput
from .focal_search import FocalSearchResult
from .lens_distortion import LensDistortion, LensStart, estimate_distortion
from .observability import tolerance
from .options import CalibrationOptions
from .parametrization import FULL, HELD, SINGLE_FOCAL, FreeParameters
from .polish import Polished, polish
from .selfcalibration import (
    FallbackProblem,
    FallbackSolution,
    fold_focal_sign,
    solve_with_fallback,
    theta_to_intrinsics,
)
from .start_candidates import StartCandidate, moved_far, other_starts, restart_point
from .tensor_set import TensorEstimator, TensorSet
from .triplet_selection import CameraTracks

#: Tensors that must agree with an estimate for it to stand (fewer when the camera
#: has fewer triplets): below, every value is held at the start.
MIN_AGREEING = 3


@dataclass
class Attempt:
    """The solve from one start candidate: its tensors, where they ended normalised, the solve."""

    candidate: StartCandidate
    tensors: TensorSet
    fallback: FallbackSolution

    @property
    def agreeing(self) -> int:
        """Tensors that agree with (are MSAC inliers at) the estimate."""
        return int(self.fallback.solution.inlier_tensors.sum())

    @property
    def majority_agrees(self) -> bool:
        """At least half the tensors agree: no other start is tried."""
        return majority(self.fallback.solution.inlier_tensors)


@dataclass
class Finished:
    """The chosen attempt (its values held where nothing agrees), its polish and the
    lens stage (None where it does not apply)."""

    attempt: Attempt
    polished: Polished
    lens: LensDistortion | None


@dataclass
class MethodRun:
    """One trifocal method on one camera's tracks: what each of its steps reads.

    Attributes:
        data: the camera's input (prior, keypoints, matches).
        tracks: its triplets and their tracks, pixels.
        estimator: the tensors of those tracks at any start (reused between starts).
        method: the trifocal variant (``msac-opt``, ``msac``, ``direct``).
        options: the calibration's options.
        clock: where the seconds of each stage go.
    """

    data: CameraInput
    tracks: CameraTracks
    estimator: TensorEstimator
    method: str
    options: CalibrationOptions
    clock: StageClock

    def attempt(
        self,
        candidate: StartCandidate,
        previous: TensorSet | None = None,
        restart: bool = True,
        complete: bool = True,
    ) -> Attempt:
        """The tensors at a start (those of ``previous`` that agree there carried over),
        their solve, completed (``complete``, :meth:`completed`), and (``restart``) the
        restart when the estimate lands far.

        Where the estimate lands far and most tensors already agree, the second starts
        wait for the restart: at a start about to be left they would refine the
        disagreeing tensors from a K the restart replaces.
        """
        with self.clock("tensors"):
            tensors = self.estimator.at(candidate.start, previous)
        with self.clock("solve"):
            attempt = Attempt(candidate, tensors, self.solve(candidate, tensors))
        if complete and not (attempt.majority_agrees and self._restart_point(attempt) is not None):
            attempt = self.completed(attempt)
        return self.restarted(attempt) if restart else attempt

    def first_tensors_disagree(self, candidate: StartCandidate, count: int) -> bool:
        """Whether most of the first ``count`` triplets' tensors, solved alone, disagree
        at ``candidate``: the cue for the lens search before the other tensors are
        estimated (on bent tracks they would all disagree, slowly); the attempt that
        follows reuses these."""
        with self.clock("tensors"):
            tensors = self.estimator.first(candidate.start, count)
        if not tensors.tensors:
            return False
        with self.clock("solve"):
            # The solve of every parameter the model has (no fallback: only how many
            # tensors agree is read).
            problem = self._problem(candidate, tensors)
            span = problem.parametrization(self._base())
            inliers = problem.solve(span, span=span).inlier_tensors
        return not majority(inliers)

    def restarted(self, attempt: Attempt) -> Attempt:
        """The attempt with its disagreeing tensors estimated again from its estimate and
        solved again, where the estimate landed far from the start (else as it is)."""
        point = self._restart_point(attempt)
        if point is None:
            return attempt
        logger.info(
            "camera %d: estimate far from the start; estimating the disagreeing tensors again",
            self.data.camera.camera_id,
        )
        with self.clock("tensors"):
            tensors = self.estimator.at(point, attempt.tensors)
        return self.solved(attempt.candidate, tensors)

    def _restart_point(self, attempt: Attempt) -> np.ndarray | None:
        """Where the attempt's tensors are estimated again from (:func:`.restart_point`),
        or None where there is no restart: the estimate stayed near the start, the
        method or options do not restart, or the budget cannot pay for it."""
        tensors = attempt.tensors
        point = restart_point(attempt.fallback, tensors.start)
        if (
            self.options.restart
            and self.method != "direct"
            and moved_far(point, tensors.start)
            and self.estimator.can_afford(len(tensors.by_triplet))
        ):
            return point
        return None

    def solved(self, candidate: StartCandidate, tensors: TensorSet) -> Attempt:
        """The solve of ``tensors``, completed (:meth:`completed`)."""
        with self.clock("solve"):
            fallback = self.solve(candidate, tensors)
        return self.completed(Attempt(candidate, tensors, fallback))

    def completed(self, attempt: Attempt) -> Attempt:
        """The attempt with its disagreeing tensors refined from both starts and solved
        again, where enough tensors agree to say which K the second start is from (with
        fewer than ``MIN_AGREEING`` the start is as doubtful as the tensors: other starts
        follow)."""
        if not consensus(attempt.fallback):
            return attempt
        candidate, tensors = attempt.candidate, attempt.tensors
        with self.clock("tensors"):
            second = self.estimator.with_second_starts(
                tensors, ~attempt.fallback.solution.inlier_tensors
            )
        if second is None:
            return attempt
        with self.clock("solve"):
            return Attempt(candidate, second, self.solve(candidate, second))

    def solve(
        self, candidate: StartCandidate, tensors: TensorSet, base: FreeParameters | None = None
    ) -> FallbackSolution:
        """The 15 constraints of ``tensors`` solved with the method for the parameters of
        ``base`` (default: the camera model's); undetermined parameters tied (fy = fx) or
        held at the candidate's values (:func:`.solve_with_fallback`)."""
        if base is None:
            base = self._base()
        return solve_with_fallback(self._problem(candidate, tensors), base)

    def _problem(self, candidate: StartCandidate, tensors: TensorSet) -> FallbackProblem:
        """The constraint problem of ``tensors`` from ``candidate`` (its held values)."""
        camera = self.data.camera
        return FallbackProblem(
            tensors.tensors,
            self.method,
            tensors.start,
            candidate.held,
            tolerance(tensors.start, camera.width, camera.height),
            self.options.tau,
            candidate.held_std,
        )

    def _base(self) -> FreeParameters:
        """The parameters the camera model has: one focal length or all four."""
        return SINGLE_FOCAL if self.data.camera.single_focal else FULL

    def best_attempt(self, first: Attempt, search: FocalSearchResult | None) -> Attempt:
        """``first``, or the best of the other starts while most tensors disagree."""
        best = first
        options = self.options
        for candidate in other_starts(
            search, first.candidate, best.tensors.start, self.method, options
        ):
            if best.majority_agrees or not self.estimator.can_afford(len(self.tracks.triplets)):
                break
            logger.info(
                "camera %d: %d of %d tensors agree; estimating them again from f = %.1f px "
                "(focal search)",
                self.data.camera.camera_id,
                best.agreeing,
                len(best.fallback.solution.inlier_tensors),
                candidate.start[0],
            )
            other = self.attempt(candidate, best.tensors)
            if other.agreeing > best.agreeing:
                best = other
        return best

    def nothing_agrees(self, attempt: Attempt) -> bool:
        """Whether fewer than ``MIN_AGREEING`` tensors agree with the estimate of a robust
        method that estimated something: the tracks single out no K (strong unmodelled
        lens distortion, wrong matches, no parallax), and the start is the best evidence
        the run has."""
        return (
            self.method != "direct"
            and attempt.fallback.free_parameters.dimension > 0
            and not consensus(attempt.fallback)
        )

    def finish(
        self,
        best: Attempt,
        lens_start: Callable[[np.ndarray], LensStart] | None = None,
    ) -> Finished:
        """The estimate (every value held where nothing agrees), its polish and the lens
        stage; ``lens_start`` (the estimate -> raw tracks and a distortion to start from)
        where the tracks were warped (:mod:`.lens_route`), which the lens stage alone
        adjusts (no polish)."""
        camera, options, method = self.data.camera, self.options, self.method
        with self.clock("solve"):
            if self.nothing_agrees(best):
                logger.info(
                    "camera %d: %d of %d tensors agree with the estimate: every value held",
                    camera.camera_id,
                    best.agreeing,
                    len(best.tensors.tensors),
                )
                best = Attempt(
                    best.candidate,
                    best.tensors,
                    self.solve(best.candidate, best.tensors, HELD),
                )
            start, fallback = best.tensors.start, best.fallback
            estimate = checked_estimate(best, camera.camera_id, method)
        with self.clock("polish"):
            polished = Polished(estimate, fallback.relative_std, best.agreeing, None)
            if method != "msac-opt" or not options.triplet_bundle:
                return Finished(best, polished, None)
            by_images = self.tracks.by_images()
            if lens_start is None:
                # On warped tracks the lens stage adjusts K with the distortion from the
                # raw tracks: polishing K on the warped ones first would only move its start.
                polished = polish(
                    best.tensors.tensors,
                    by_images,
                    start,
                    estimate,
                    fallback,
                    best.agreeing,
                    (camera.width, camera.height),
                    options.tau,
                    camera.camera_id,
                    options.workers,
                )
            lens = estimate_distortion(
                best.tensors.tensors,
                by_images,
                start,
                polished.intrinsics,
                fallback.free_parameters,
                camera,
                options.tau,
                fallback.solution.inlier_tensors,
                options.workers,
                None if lens_start is None else lens_start(polished.intrinsics),
            )
        return Finished(best, polished, lens)


def majority(inliers: np.ndarray) -> bool:
    """Whether at least half the tensors (bool per tensor) agree."""
    return 2 * int(inliers.sum()) >= len(inliers)


def consensus(fallback: FallbackSolution) -> bool:
    """Whether at least ``MIN_AGREEING`` tensors (all, when there are fewer) agree with
    the estimate: one or two tensors among many that agree with a K are as likely to
    agree by chance as because it is the camera's."""
    inliers = fallback.solution.inlier_tensors
    return int(inliers.sum()) >= min(MIN_AGREEING, len(inliers))


def checked_estimate(best: Attempt, camera_id: int, method: str) -> np.ndarray:
    """The estimate (fx, fy, cx, cy) in pixels, or CalibrationError when it is garbage
    (not finite, a focal length ≤ 0 that tensors agree with)."""
    fallback = best.fallback
    estimate = fold_focal_sign(theta_to_intrinsics(fallback.solution.theta, best.tensors.start))
    checked = method != "direct" and fallback.free_parameters.dimension > 0
    if not (
        np.all(np.isfinite(estimate)) and min(estimate[:2]) > 0 and (best.agreeing or not checked)
    ):
        raise CalibrationError(
            f"camera {camera_id}: no valid estimate (fx {estimate[0]:.4g}, fy "
            f"{estimate[1]:.4g}; {best.agreeing} of {len(best.tensors.tensors)} tensors agree): "
            "too little parallax or wrong matches"
        )
    if fallback.free_parameters.assumptions():
        logger.info(
            "camera %d: assumed %s", camera_id, "; ".join(fallback.free_parameters.assumptions())
        )
    return estimate
