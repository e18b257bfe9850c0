"""Attempts: one camera's tensors at a start K and their solve, from start to start.

An attempt is the tensors at a start K (:mod:`.estimator`) and their solve
(:mod:`..solve.constraints`). Where the estimate lands far from the start, the
disagreeing tensors are estimated again from it (a restart); where enough tensors agree,
the disagreeing ones are also refined from both starts (second starts). Other starts
(the focal search's candidates) follow while most tensors disagree. Where too few
tensors agree with the chosen attempt, every value is held at the best evidence.

Every function takes the method's :class:`AttemptInputs` (what it reads) and returns
an :class:`Attempt`; none calls back into the pipeline. Intrinsics (fx, fy, cx, cy) in
pixels, COLMAP's pixel convention (the centre of the top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...common.errors import NoEstimate
from ...common.log import logger
from ...common.timing import StageClock
from ..inputs.camera_input import CameraInput
from ..inputs.triplet_selection import CameraTracks
from ..options import CalibrationOptions
from ..solve.fallback import FallbackProblem, FallbackSolution, solve_with_fallback
from ..solve.observability import default_held_std, tolerance
from ..solve.parametrization import FULL, HELD, SINGLE_FOCAL, FreeParameters
from ..solve.theta import fold_focal_sign, theta_to_intrinsics
from ..start.candidates import StartCandidate, moved_far, other_starts, restart_point
from ..start.focal_search import FocalSearchResult
from .estimator import TensorEstimator, TensorSet

#: Tensors that must agree with an estimate for it to stand (fewer when the camera
#: has fewer triplets): below, every value is held at the start.
MIN_AGREEING = 3


@dataclass(frozen=True)
class AttemptInputs:
    """What one trifocal method's attempts read.

    Attributes:
        data: the camera's input (prior, keypoints, matches).
        tracks: its triplets and their tracks, pixels.
        estimator: the tensors of those tracks at any start (reused between starts).
        method: the trifocal variant (``msac-opt``, ``msac``, ``direct``).
        options: the calibration's options.
        clock: where the seconds of the ``tensors`` and ``solve`` stages go.
    """

    data: CameraInput
    tracks: CameraTracks
    estimator: TensorEstimator
    method: str
    options: CalibrationOptions
    clock: StageClock


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


def attempt(
    inputs: AttemptInputs,
    candidate: StartCandidate,
    previous: TensorSet | None = None,
    *,
    restart: bool = True,
    complete: bool = True,
) -> Attempt:
    """The tensors at a start (those of ``previous`` that agree there carried over),
    their solve, completed (``complete``, :func:`completed`), and (``restart``) the
    restart when the estimate lands far.

    Where the estimate lands far and most tensors already agree, the second starts
    wait for the restart: at a start about to be left they would refine the
    disagreeing tensors from a K the restart replaces.
    """
    with inputs.clock("tensors"):
        tensors = inputs.estimator.at(candidate.start, previous)
    with inputs.clock("solve"):
        first = Attempt(candidate, tensors, solve(inputs, candidate, tensors))
    if complete and not (first.majority_agrees and _restart_point(inputs, first) is not None):
        first = completed(inputs, first)
    return restarted(inputs, first) if restart else first


def first_tensors_disagree(inputs: AttemptInputs, candidate: StartCandidate, count: int) -> bool:
    """Whether most of the first ``count`` triplets' tensors, solved alone, disagree at
    ``candidate``: the cue for the lens search before the other tensors are estimated
    (on bent tracks they would all disagree, slowly); the attempt that follows reuses
    these."""
    with inputs.clock("tensors"):
        tensors = inputs.estimator.first(candidate.start, count)
    if not tensors.tensors:
        return False
    with inputs.clock("solve"):
        # The solve of every parameter the model has (no fallback: only how many
        # tensors agree is read).
        problem = _problem(inputs, candidate, tensors)
        span = problem.parametrization(_base(inputs))
        inliers = problem.solve(span, span=span).inlier_tensors
    return not majority(inliers)


def restarted(inputs: AttemptInputs, first: Attempt) -> Attempt:
    """The attempt with its disagreeing tensors estimated again from its estimate and
    solved again, where the estimate landed far from the start (else as it is)."""
    point = _restart_point(inputs, first)
    if point is None:
        return first
    logger.info(
        "camera %d: estimate far from the start; estimating the disagreeing tensors again",
        inputs.data.camera.camera_id,
    )
    with inputs.clock("tensors"):
        tensors = inputs.estimator.at(point, first.tensors)
    with inputs.clock("solve"):
        fallback = solve(inputs, first.candidate, tensors)
    return completed(inputs, Attempt(first.candidate, tensors, fallback))


def _restart_point(inputs: AttemptInputs, first: Attempt) -> np.ndarray | None:
    """Where the attempt's tensors are estimated again from (:func:`.restart_point`),
    or None where there is no restart: the estimate stayed near the start, the
    method or options do not restart, or the budget cannot pay for it."""
    tensors = first.tensors
    point = restart_point(first.fallback, tensors.start)
    if (
        inputs.options.restart
        and inputs.method != "direct"
        and moved_far(point, tensors.start)
        and inputs.estimator.can_afford(len(tensors.by_triplet))
    ):
        return point
    return None


def completed(inputs: AttemptInputs, first: Attempt) -> Attempt:
    """The attempt with its disagreeing tensors refined from both starts and solved
    again, where enough tensors agree to say which K the second start is from (with
    fewer than ``MIN_AGREEING`` the start is as doubtful as the tensors: other starts
    follow)."""
    if not consensus(first.fallback):
        return first
    candidate, tensors = first.candidate, first.tensors
    with inputs.clock("tensors"):
        second = inputs.estimator.with_second_starts(
            tensors, ~first.fallback.solution.inlier_tensors
        )
    if second is None:
        return first
    with inputs.clock("solve"):
        return Attempt(candidate, second, solve(inputs, candidate, second))


def solve(
    inputs: AttemptInputs,
    candidate: StartCandidate,
    tensors: TensorSet,
    base: FreeParameters | None = None,
) -> FallbackSolution:
    """The 15 constraints of ``tensors`` solved with the method for the parameters of
    ``base`` (default: the camera model's); undetermined parameters tied (fy = fx) or
    held at the candidate's values (:func:`.solve_with_fallback`)."""
    if base is None:
        base = _base(inputs)
    return solve_with_fallback(_problem(inputs, candidate, tensors), base)


def _problem(
    inputs: AttemptInputs, candidate: StartCandidate, tensors: TensorSet
) -> FallbackProblem:
    """The constraint problem of ``tensors`` from ``candidate`` (its held values)."""
    camera = inputs.data.camera
    return FallbackProblem(
        tensors.tensors,
        inputs.method,
        tensors.start,
        candidate.held,
        tolerance(tensors.start, camera.width, camera.height),
        inputs.options.tau,
        candidate.held_std,
    )


def _base(inputs: AttemptInputs) -> FreeParameters:
    """The parameters the camera model has: one focal length or all four."""
    return SINGLE_FOCAL if inputs.data.camera.single_focal else FULL


def best_attempt(
    inputs: AttemptInputs, first: Attempt, search: FocalSearchResult | None
) -> Attempt:
    """``first``, or the best of the other starts while most tensors disagree."""
    best = first
    for candidate in other_starts(
        search, first.candidate, best.tensors.start, inputs.method, inputs.options
    ):
        if best.majority_agrees or not inputs.estimator.can_afford(len(inputs.tracks.triplets)):
            break
        logger.info(
            "camera %d: %d of %d tensors agree; estimating them again from f = %.1f px "
            "(focal search)",
            inputs.data.camera.camera_id,
            best.agreeing,
            len(best.fallback.solution.inlier_tensors),
            candidate.start[0],
        )
        other = attempt(inputs, candidate, best.tensors)
        if other.agreeing > best.agreeing:
            best = other
    return best


def held_where_nothing_agrees(inputs: AttemptInputs, best: Attempt) -> Attempt:
    """``best``, or its values all held where fewer than ``MIN_AGREEING`` tensors agree
    with the estimate of a robust method that estimated something: the tracks single
    out no K (strong unmodelled lens distortion, wrong matches, no parallax), and the
    start is the best evidence the run has.

    Where enough agree but the focal length is held at the focal search's value that
    most tensors disagree with, it is held at the start instead
    (:func:`held_at_the_start`): on near-straight driving (KITTI's last 11 frames, 4°
    of turn) the search found a decisive curve at 282 px on one seed of five (truth
    719), 3 of 19 tensors agreed there, and f was reported at it with the search's 7 %
    std."""
    if inputs.method == "direct":
        return best
    candidate = held_at_the_start(best.candidate, inputs.data.prior)
    if consensus(best.fallback):
        if not focal_held_against_most(best):
            return best
        what = "the focal search's focal length: held at the start"
        return _solved_at(inputs, best, candidate, best.fallback.free_parameters, what)
    if best.fallback.free_parameters.dimension == 0 and candidate is best.candidate:
        return best  # already held, at the start's values
    return _solved_at(inputs, best, candidate, HELD, "the estimate: every value held")


def _solved_at(
    inputs: AttemptInputs,
    best: Attempt,
    candidate: StartCandidate,
    free_parameters: FreeParameters,
    what: str,
) -> Attempt:
    """``best``'s tensors solved again from ``candidate`` for ``free_parameters``; the log
    says how many tensors agree with ``what``.

    The solve of every parameter the camera model has stays ``best``'s: it is of the same
    tensors from the same start (held values do not enter it), and what the report calls
    each parameter's unconstrained std; the solve for ``free_parameters`` alone would give
    a held value's std as 0.
    """
    logger.info(
        "camera %d: %d of %d tensors agree with %s",
        inputs.data.camera.camera_id,
        best.agreeing,
        len(best.tensors.tensors),
        what,
    )
    fallback = solve(inputs, candidate, best.tensors, free_parameters)
    fallback = replace(fallback, unconstrained=best.fallback.unconstrained)
    return Attempt(candidate, best.tensors, fallback)


def held_at_the_start(candidate: StartCandidate, prior: np.ndarray) -> StartCandidate:
    """``candidate`` holding the start's values where it held the focal search's: with no
    tensors, or only a minority, agreeing at that focal length, the search (whose
    hypotheses assume the tracks are a pinhole camera's) is not evidence against the
    start; the start is known no better than its disagreement with the search."""
    if candidate.held_source != "focal-search":
        return candidate
    prior = np.asarray(prior, float)
    held_std = default_held_std()
    searched = float(np.sqrt(candidate.held[0] * candidate.held[1]))
    disagreement = abs(searched / float(np.sqrt(prior[0] * prior[1])) - 1.0)
    held_std[:2] = np.maximum(held_std[:2], disagreement)
    return StartCandidate(candidate.start, prior.copy(), held_std, "prior")


def focal_held_against_most(best: Attempt) -> bool:
    """Whether enough tensors agree with ``best`` (:func:`consensus`) while its focal
    length is held at the focal search's value, which most of them disagree with."""
    return (
        consensus(best.fallback)
        and not best.majority_agrees
        and best.fallback.free_parameters.focal == "held"
        and best.candidate.held_source == "focal-search"
    )


def majority(inliers: np.ndarray) -> bool:
    """Whether at least half the tensors (bool per tensor) agree."""
    return majority_of(int(inliers.sum()), len(inliers))


def majority_of(agreeing: int, total: int) -> bool:
    """Whether ``agreeing`` is at least half of ``total``."""
    return 2 * agreeing >= total


def consensus(fallback: FallbackSolution) -> bool:
    """Whether at least ``MIN_AGREEING`` tensors (all, when there are fewer) agree with
    the estimate: one or two tensors among many that agree with a K are as likely to
    agree by chance as because it is the camera's."""
    inliers = fallback.solution.inlier_tensors
    return int(inliers.sum()) >= min(MIN_AGREEING, len(inliers))


def checked_estimate(best: Attempt, camera_id: int, method: str) -> np.ndarray:
    """The estimate (fx, fy, cx, cy) in pixels, or NoEstimate when it is garbage
    (not finite, a focal length ≤ 0 that tensors agree with)."""
    fallback = best.fallback
    estimate = fold_focal_sign(theta_to_intrinsics(fallback.solution.theta, best.tensors.start))
    checked = method != "direct" and fallback.free_parameters.dimension > 0
    if not (
        np.all(np.isfinite(estimate)) and min(estimate[:2]) > 0 and (best.agreeing or not checked)
    ):
        raise NoEstimate(
            f"camera {camera_id}: no valid estimate (fx {estimate[0]:.4g}, fy "
            f"{estimate[1]:.4g}; {best.agreeing} of {len(best.tensors.tensors)} tensors agree): "
            "too little parallax or wrong matches"
        )
    if fallback.free_parameters.assumptions():
        logger.info(
            "camera %d: assumed %s", camera_id, "; ".join(fallback.free_parameters.assumptions())
        )
    return estimate
