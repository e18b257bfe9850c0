"""A camera's constraint solve with the fallback: what the images determine, estimated;
the rest tied (fy = fx) or held at the best evidence.

:func:`solve_with_fallback` solves a camera's :class:`FallbackProblem` (its tensors,
method, start and held values) into a :class:`FallbackSolution`: the unconstrained
solve of every parameter the camera model has, then, where some are not determined
(:mod:`.observability`), the solve of those that are, the others tied or held with
their held values' std. A determined parameter must also be one the data moves
(:func:`data_moves`): a parameter held at a start that happens to be right would
otherwise read as estimated. θ are the relative corrections of :mod:`.theta`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ...geometry.tensor_estimation import TripletTensor
from .constraints import MSAC_TAU, ConstraintSolution, solve
from .observability import (
    default_held_std,
    effective_std,
    select_free_parameters,
)
from .parametrization import FreeParameters, Parametrization


@dataclass
class FallbackSolution:
    """How :func:`solve_with_fallback` solved a camera's :class:`FallbackProblem`: the
    solve of every parameter the camera model has, and the one finally kept.

    Its std and the test of what the data moves each take solves of their own, and
    only the solution a camera's estimate is polished and assessed from needs them,
    not the attempts it was chosen among: they are computed when first read."""

    solution: ConstraintSolution  # of ``free_parameters``
    free_parameters: FreeParameters  # the parameters the images determine
    unconstrained: ConstraintSolution  # of ``base``: every parameter the camera model has
    problem: FallbackProblem = field(repr=False, compare=False)  # the problem solved
    base: FreeParameters  # the parameters the camera model has

    @property
    def tolerances(self) -> np.ndarray:
        """(4,) the std of θ below which a parameter counted as determined."""
        return self.problem.tolerances

    @property
    def partly_held(self) -> bool:
        """Whether a robust method estimated some of the model's parameters and held or
        tied the others (what the held values' std then moves is part of the std)."""
        return (
            self.problem.method != "direct"
            and 0 < self.free_parameters.dimension < self.base.dimension
        )

    @cached_property
    def held_shift(self) -> np.ndarray:
        """(4,) how much each estimated θ moves when the held values are moved by their
        std (:func:`held_value_sensitivity`; zero where nothing is held)."""
        if not self.partly_held:
            return np.zeros(4)
        return held_value_sensitivity(
            self.problem, self.free_parameters, self.base, self.solution.theta
        )

    @cached_property
    def relative_std(self) -> np.ndarray:
        """(4,) std of θ of ``solution``, its ties and holds counted as uncertain: to first
        order through the information (:func:`intrinsics.solve.observability.effective_std`),
        and beyond it by :attr:`held_shift`; the larger of the two. Meaningful for the
        estimated parameters."""
        problem, solution = self.problem, self.solution
        std = effective_std(
            solution.information,
            self.free_parameters,
            self.base,
            problem.start,
            problem.held,
            problem.held_std,
        )
        if self.partly_held:
            finite = np.isfinite(solution.relative_std)
            conditional = np.where(finite, solution.relative_std, np.inf)
            std = np.maximum(std, np.hypot(conditional, self.held_shift))
        return np.asarray(std)

    @cached_property
    def moved(self) -> np.ndarray:
        """(4,) whether the data pulls each estimated parameter back when the solve
        starts away from the estimate (:func:`data_moves`); True for held ones."""
        if self.problem.method == "direct" or self.free_parameters.dimension == 0:
            return np.ones(4, dtype=bool)
        return data_moves(self.problem, self.free_parameters, self.solution.theta)


@dataclass(frozen=True)
class FallbackProblem:
    """One camera's constraint solve: what its solves (:func:`solve_with_fallback`,
    one :class:`ConstraintProblem` each) share: its tensors, the method, and the
    values the parameters start from or are held at.

    Attributes:
        tensors: tensors normalised by ``start``.
        method: ``direct``, ``msac`` or ``msac-opt``.
        start: (fx0, fy0, cx0, cy0) of the normalisation, pixels (θ = 0 there).
        held: the values held parameters keep (the best the run has: the prior, or
            the focal search's focal length), pixels.
        tolerances: (4,) std of θ below which a parameter is determined
            (:func:`intrinsics.solve.observability.tolerance`).
        tau: MSAC threshold on the whitened residual norm.
        held_std: (4,) how well the held values are known, relative to the focal
            length (None: a prior's, :func:`intrinsics.solve.observability.default_held_std`).
    """

    tensors: list[TripletTensor]
    method: str
    start: np.ndarray
    held: np.ndarray
    tolerances: np.ndarray
    tau: float = MSAC_TAU
    held_std: np.ndarray | None = None

    def solve(
        self, parametrization: Parametrization, span: Parametrization | None = None
    ) -> ConstraintSolution:
        """:func:`solve` of these tensors with this method for one parametrization."""
        return solve(self.tensors, self.method, parametrization, self.tau, span=span)

    def parametrization(
        self, free_parameters: FreeParameters, held: np.ndarray | None = None
    ) -> Parametrization:
        """``free_parameters``' parametrization around ``start`` (held values: ``held``
        or the own)."""
        return free_parameters.parametrization(self.start, self.held if held is None else held)


def solve_with_fallback(problem: FallbackProblem, base: FreeParameters) -> FallbackSolution:
    """Solve ``base``; while parameters are undetermined, re-solve without them.

    Each round keeps the largest set of parameters the information at the current
    estimate determines (:func:`intrinsics.solve.observability.select_free_parameters`), so every
    round estimates strictly fewer parameters and the loop ends (at worst with
    everything held). ``direct`` keeps ``base``: it has no outlier defence, so
    outlier tensors inflate its reduced χ² by orders of magnitude and its std says
    nothing about which parameters the images determine; it is the paper's
    non-robust variant and returns its own least-squares estimate.

    Args:
        problem: the tensors, method, start, held values and tolerances.
        base: the parameters the camera model has (all four, or one focal length).

    The returned std of the estimated parameters includes what the held values'
    uncertainty does to them: to first order through the information
    (:func:`intrinsics.solve.observability.effective_std`), and beyond it by re-solving with the
    held values moved by their std (:func:`held_value_sensitivity`); the larger
    of the two counts.
    """
    method, start, held = problem.method, problem.start, problem.held
    span = problem.parametrization(base)
    free_parameters = base
    solution = unconstrained = problem.solve(span, span=span)
    while method != "direct":
        reduced = select_free_parameters(
            solution.information,
            free_parameters,
            base,
            start,
            held,
            problem.tolerances,
            problem.held_std,
        )
        if reduced == free_parameters:
            break
        free_parameters = reduced
        solution = problem.solve(problem.parametrization(free_parameters), span=span)
    return FallbackSolution(solution, free_parameters, unconstrained, problem, base)


#: :func:`data_moves` starts this many tolerances away from the estimate ...
MOVE_TEST_OFFSET = 3.0


#: ... and a parameter counts as moved by the data when the solve brings it back
#: by at least this fraction of the offset.
MOVE_TEST_RECOVERY = 0.5


def data_moves(
    problem: FallbackProblem, free_parameters: FreeParameters, theta: np.ndarray
) -> np.ndarray:
    """Whether the data moves each estimated parameter (4,): a parameter the data does
    not move from its start is not determined, whatever its std says.

    ``free_parameters`` are solved again from the estimate ``theta`` with every
    estimated parameter offset by ``MOVE_TEST_OFFSET`` tolerances (alternating
    signs); a parameter the constraints determine returns at least
    ``MOVE_TEST_RECOVERY`` of the way.
    Held parameters count as moved (they are not estimated).
    """
    parametrization = problem.parametrization(free_parameters)
    free = parametrization.free(theta)
    signs = np.array([1.0, 1.0, -1.0, 1.0])
    offset_theta = MOVE_TEST_OFFSET * problem.tolerances * signs
    offset_free = parametrization.free(theta + offset_theta) - free
    # Same unknowns, p = 0 now at the offset estimate.
    shifted = Parametrization(parametrization.matrix, parametrization.theta(free + offset_free))
    result = problem.solve(shifted).theta
    applied = shifted.offset - theta
    recovered = np.abs(applied) - np.abs(result - theta)
    estimated = np.abs(parametrization.matrix).sum(axis=1) > 0
    moved = recovered >= MOVE_TEST_RECOVERY * np.abs(applied)
    return np.asarray(moved | ~(estimated & (np.abs(applied) > 0)))


def held_value_sensitivity(
    problem: FallbackProblem,
    free_parameters: FreeParameters,
    base: FreeParameters,
    theta: np.ndarray,
) -> np.ndarray:
    """How far (4,) the estimated θ (``theta``) move when the held values move by their std.

    Each held group (the focal length; cx; cy) is moved by its std in turn and
    ``free_parameters`` solved again; the moves add in quadrature. This is the coupling the
    linearised information misses when the held direction carries no
    information at all (there the curvature has no cross term, yet the
    estimated principal point follows a wrong focal length). Zero for held
    parameters themselves.
    """
    held_std = default_held_std() if problem.held_std is None else np.asarray(problem.held_std)
    fx0, fy0 = float(problem.start[0]), float(problem.start[1])
    groups = []
    if free_parameters.focal == "held" and base.focal != "held":
        groups.append(np.array([held_std[0] * fx0, held_std[1] * fy0, 0.0, 0.0]))
    for index, kept, base_kept in (
        (2, free_parameters.cx, base.cx),
        (3, free_parameters.cy, base.cy),
    ):
        if base_kept and not kept:
            step = np.zeros(4)
            step[index] = held_std[index] * (fx0 if index == 2 else fy0)
            groups.append(step)
    squared = np.zeros(4)
    for step in groups:
        moved = problem.solve(problem.parametrization(free_parameters, problem.held + step)).theta
        squared += (moved - theta) ** 2
    estimated = np.array(
        [free_parameters.focal != "held"] * 2 + [free_parameters.cx, free_parameters.cy]
    )
    return np.where(estimated, np.sqrt(squared), 0.0)
