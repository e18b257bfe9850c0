"""Intrinsics from the 15 quartic constraints of calibrated trifocal tensors.

Parametrisation. Tensors live in prior-normalised coordinates ``x̂ = K0⁻¹ x``,
so a candidate K acts on them through ``M = K0⁻¹ K``. The unknowns are the
relative corrections ``θ = (fx/fx0 − 1, fy/fy0 − 1, (cx − cx0)/fx0, (cy − cy0)/fy0)``,
``M(θ) = [[1 + θ0, 0, θ2], [0, 1 + θ1, θ3], [0, 0, 1]]``: all four are
dimensionless and of the same scale, which keeps the problem well conditioned.
Which of them are estimated is a :class:`intrinsics.solve.parametrization.Parametrization`
(single-focal cameras tie fy to fx; parameters the images do not determine are
tied or held at the prior, :func:`.fallback.solve_with_fallback`).

Residual scaling. The raw constraint values of different triplets are not
comparable: a short-baseline triplet with few tracks has a noisy tensor and
large constraint values at the true K, a wide triplet tiny ones. Each tensor's
15 values are therefore *whitened* with their covariance propagated from the
covariance of the refined cameras (:mod:`.projective_ba`):
``Σ_c = J Σ_P Jᵀ`` with ``J = ∂c/∂vec(P2, P3)`` (central differences). Σ_c has
rank 7, the codimension of calibrated tensors among all tensors, and the
whitened residual ``r = Λ^{-1/2} Vᵀ c`` (its top 7 eigenpairs) is, at the true K,
approximately a standard normal 7-vector: ``‖r‖²`` ~ χ²(7), so one threshold
(``MSAC_TAU``) serves every triplet (docs/uncertainty.md, "Why these constants").

The levels: a :class:`ConstraintProblem` (one set of tensors, one parametrization)
has a :class:`ConstraintSolution` per solve (:func:`solve`); a camera's
:class:`.fallback.FallbackProblem` (its tensors, method, start and held values) is solved by
:func:`.fallback.solve_with_fallback` into a :class:`.fallback.FallbackSolution` (the parameters the
images determine), which the polish and the assessment turn into the camera's
:class:`.results.CameraCalibration`.

Variants (TrifocalCalib paper):

* ``direct``: least squares over all whitened residuals of all tensors.
* ``msac``: one estimate per tensor (minimising its own residuals from the
  prior, all tensors at once in a batched Levenberg–Marquardt), the one with the
  best MSAC score ``1 − mean_i min(‖r_i‖ / τ, 1)`` over all tensors.
* ``msac-opt``: the msac estimate refined by minimising the MSAC cost
  ``Σ_i min(‖r_i‖, τ)`` (iteratively reweighted least squares; inliers weighted
  by ``1 / ‖r_i‖``, tensors at or above τ get weight 0).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ...geometry.tensor_estimation import TripletTensor
from ...geometry.trifocal import (
    calibrate_tensor,
    quartic_constraints,
)
from .observability import (
    conditioned_covariance,
    relative_std,
)
from .parametrization import FULL, Parametrization
from .theta import theta_to_matrix
from .uncertainty import combined_information, jackknife_replicates, one_step_replicate
from .whitening import whitening_matrices

#: MSAC threshold on the whitened constraint norm ‖r_i‖ (dimensionless).
#: ‖r‖² ~ χ²(7) for an exact tensor: the 99 % quantile is 18.5 (‖r‖ = 4.3). Real
#: tensors carry unmodelled error (residual distortion, correlated keypoints), so
#: τ lies above that, within the distribution of ‖r‖ at the true K on real scenes.
MSAC_TAU = 10.0
_FD_STEP_THETA = 1e-7
#: Sensitivity of the raw constraints below which a direction of θ is null (see
#: :meth:`ConstraintProblem.insensitive_directions`).
RAW_SENSITIVITY_FLOOR = 1e-6
#: All four parameters free, θ = p.
FULL_PARAMETRIZATION = FULL.parametrization(np.ones(4), np.ones(4))


@dataclass
class ConstraintProblem:
    """Whitened constraint residuals of one set of tensors as a function of θ, and
    their minimisers; each solve of it gives a :class:`ConstraintSolution`.

    The unknowns are those of ``parametrization`` (``θ = A p + b``, see
    :mod:`intrinsics.solve.parametrization`); by default all four.
    """

    tensors: np.ndarray  # (n, 3, 3, 3) in prior-normalised coordinates
    whitening: np.ndarray  # (n, 7, 15)
    parametrization: Parametrization = field(default_factory=lambda: FULL_PARAMETRIZATION)

    @classmethod
    def build(
        cls,
        tensors: list[TripletTensor],
        theta: np.ndarray,
        parametrization: Parametrization | None = None,
    ) -> ConstraintProblem:
        return cls(
            tensors=np.stack([t.tensor for t in tensors]),
            whitening=whitening_matrices(tensors, theta),
            parametrization=parametrization or FULL_PARAMETRIZATION,
        )

    def residuals(self, theta: np.ndarray, which: np.ndarray | None = None) -> np.ndarray:
        """Whitened residuals (..., n, 7) at θ (..., 4), for tensors ``which`` (default all)."""
        tensors = self.tensors if which is None else self.tensors[which]
        whitening = self.whitening if which is None else self.whitening[which]
        M = theta_to_matrix(theta)[..., None, :, :]
        c = quartic_constraints(calibrate_tensor(tensors, M))
        return np.asarray((whitening @ c[..., None])[..., 0])

    def norms(self, theta: np.ndarray) -> np.ndarray:
        """‖r_i‖ per tensor (n,) at θ (4,)."""
        return np.asarray(np.linalg.norm(self.residuals(theta), axis=-1))

    def per_tensor_estimates(self, theta0: np.ndarray, iterations: int = 30) -> np.ndarray:
        """θ_i (n, 4) minimising each tensor's own residuals, all tensors in one batched LM."""
        parametrization = self.parametrization
        n = len(self.tensors)
        free = np.tile(parametrization.free(theta0), (n, 1))
        k = free.shape[1]
        if k == 0:
            return parametrization.theta(free)
        damping = np.full(n, 1e-3)

        def batch_residuals(values: np.ndarray) -> np.ndarray:
            # Tensor i evaluated at its own parameters values[..., i, :].
            M = theta_to_matrix(parametrization.theta(values))
            c = quartic_constraints(calibrate_tensor(self.tensors, M))
            return np.asarray((self.whitening @ c[..., None])[..., 0])

        r = batch_residuals(free)
        cost = np.einsum("na,na->n", r, r)
        for _ in range(iterations):
            J = np.moveaxis(_central_differences(batch_residuals, free), 0, -1)  # (n, 7, k)
            JtJ = np.swapaxes(J, 1, 2) @ J
            g = (np.swapaxes(J, 1, 2) @ r[..., None])[..., 0]
            diag = np.einsum("nii->ni", JtJ)
            A = JtJ + (damping[:, None] * (diag + 1e-12))[:, :, None] * np.eye(k)
            delta = -np.linalg.solve(A, g[..., None])[..., 0]
            candidate = free + delta
            r_new = batch_residuals(candidate)
            cost_new = np.einsum("na,na->n", r_new, r_new)
            better = np.isfinite(cost_new) & (cost_new < cost)
            free[better], r[better] = candidate[better], r_new[better]
            cost[better] = cost_new[better]
            damping = np.where(better, damping / 3, damping * 4)
        return parametrization.theta(free)

    def least_squares(self, theta0: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """θ minimising ``Σ_i w_i ‖r_i(θ)‖²`` (scipy Levenberg–Marquardt)."""
        parametrization = self.parametrization
        if parametrization.dimension == 0:
            return parametrization.theta(parametrization.free(theta0))
        w = np.ones(len(self.tensors)) if weights is None else weights
        active = np.flatnonzero(w > 0)
        sqrt_w = np.sqrt(w[active])[:, None]

        def batched(free: np.ndarray) -> np.ndarray:
            residuals = self.residuals(parametrization.theta(free), active) * sqrt_w
            return residuals.reshape(residuals.shape[:-2] + (-1,))

        def jacobian(free: np.ndarray) -> np.ndarray:
            return _central_differences(batched, free).T

        # x_scale=1: θ is dimensionless and of one scale. scipy's default for "lm"
        # ("jac") shrinks the first step to ~1/|J|, which stalls at the prior when
        # the whitened residuals are huge (noise-free data). "lm" needs at least as
        # many residuals as unknowns; "trf" takes the rare smaller case.
        method = "lm" if 7 * len(active) >= parametrization.dimension else "trf"
        solution = least_squares(
            batched,
            parametrization.free(theta0),
            jac=jacobian,
            method=method,
            xtol=1e-12,
            x_scale=1.0,
        )
        return parametrization.theta(solution.x)

    def minimise_msac_cost(self, theta: np.ndarray, tau: float, iterations: int) -> np.ndarray:
        """θ minimising ``Σ_i min(‖r_i‖, τ)`` from ``theta`` (IRLS, weights ``1/‖r_i‖``)."""
        for _ in range(iterations):
            norms = self.norms(theta)
            weights = np.where(norms < tau, 1.0 / np.maximum(norms, 1e-3), 0.0)
            if np.count_nonzero(weights) < min(2, len(norms)):
                break
            updated = self.least_squares(theta, weights)
            converged = np.max(np.abs(updated - theta)) < 1e-9
            theta = updated
            if converged:
                break
        return theta

    def jacobians(self, theta: np.ndarray) -> np.ndarray:
        """∂r_i/∂θ (n, 7, 4) of every tensor's whitened residuals at θ (4,)."""
        return np.moveaxis(_central_differences(self.residuals, theta), 0, -1)

    def information(
        self,
        theta: np.ndarray,
        weights: np.ndarray,
        residuals: np.ndarray | None = None,
        jacobians: np.ndarray | None = None,
    ) -> np.ndarray:
        """Information H (4, 4) about all four θ at ``theta``: ``Σ_i w_i J_iᵀ J_i``.

        The residuals are already whitened by the tensors' own covariance, so
        ``H⁻¹`` is the covariance when the keypoint noise model holds. H is divided
        by the reduced χ² of the residuals (degrees of freedom: residuals minus the
        parametrization's unknowns) only when that exceeds 1: unmodelled error on
        real data inflates the covariance, it never shrinks it; scaling by the χ²
        itself would make the std of a single triplet (3 degrees of freedom) a
        t(3) variable (coverage: docs/uncertainty.md).

        Args:
            theta: the estimate (4,).
            weights: (n,) per tensor (0 leaves it out).
            residuals, jacobians: :meth:`residuals` (n, 7) and :meth:`jacobians`
                (n, 7, 4) at ``theta`` when already computed.
        """
        residuals = self.residuals(theta) if residuals is None else residuals
        jacobians = self.jacobians(theta) if jacobians is None else jacobians
        active = np.flatnonzero(weights > 0)
        w = weights[active]
        chi2 = float(np.einsum("n,na,na->", w, residuals[active], residuals[active]))
        dof = max(7 * len(active) - self.parametrization.dimension, 1)
        J = jacobians[active]
        information = np.einsum("n,nak,nal->kl", w, J, J) / max(chi2 / dof, 1.0)
        # Directions along which the raw constraints do not change carry no
        # information, however much whitening by a tiny noise amplifies the
        # numerical noise there (noise-free data, exact pure translation).
        null = self.insensitive_directions(theta, active)
        if null.shape[1]:
            projector = np.eye(4) - null @ null.T
            information = projector @ information @ projector
        return np.asarray(information)

    def insensitive_directions(self, theta: np.ndarray, which: np.ndarray) -> np.ndarray:
        """Orthonormal directions (4, d) of θ that leave the raw constraints unchanged.

        A direction is insensitive where the singular value of ``∂c/∂θ`` (unit-norm
        tensors, rms over tensors) is below ``RAW_SENSITIVITY_FLOOR``: exact
        degeneracy (pure translation, noise-free planar motion) leaves only
        finite-difference noise there, any keypoint noise far more; weak but
        nonzero sensitivity is the std test's job (docs/uncertainty.md).
        """
        tensors = self.tensors[which]

        def raw(values: np.ndarray) -> np.ndarray:
            c = quartic_constraints(
                calibrate_tensor(tensors, theta_to_matrix(values)[..., None, :, :])
            )
            return c.reshape(c.shape[:-2] + (-1,))

        J = _central_differences(raw, theta).T / np.sqrt(max(len(tensors), 1))
        _, singular_values, vt = np.linalg.svd(J, full_matrices=False)
        return vt[singular_values < RAW_SENSITIVITY_FLOOR].T


def _central_differences(function: Callable[[np.ndarray], np.ndarray], x: np.ndarray) -> np.ndarray:
    """Central-difference derivatives (k, ..., m) of a vectorised function at x (..., k).

    ``function`` maps parameters (..., k) to values (..., m), broadcasting over
    leading dimensions, so all 2k evaluations go in one call. Entry j is ∂f/∂x_j.
    """
    k = x.shape[-1]
    steps = (_FD_STEP_THETA * np.eye(k)).reshape((k,) + (1,) * (x.ndim - 1) + (k,))
    values = function(np.concatenate([x + steps, x - steps]))
    return np.asarray((values[:k] - values[k:]) / (2 * _FD_STEP_THETA))


def msac_score(norms: np.ndarray, tau: float = MSAC_TAU) -> float:
    """The paper's MSAC score ``1 − mean(min(r_i / τ, 1))``: 1 is perfect, 0 all outliers."""
    return float(1.0 - np.mean(np.minimum(norms / tau, 1.0)))


@dataclass
class ConstraintSolution:
    """One solve of a :class:`ConstraintProblem` (one method, one parametrization): θ
    with its covariance and the per-tensor diagnostics."""

    theta: np.ndarray  # (4,)
    covariance: np.ndarray  # (4, 4) of θ (zero for held parameters and null directions)
    #: (4, 4) about θ at the estimate: curvature and jackknife combined (see uncertainty)
    information: np.ndarray
    relative_std: np.ndarray  # (4,) std of θ; 0 held, inf undetermined
    jackknife: np.ndarray | None  # (g, 4) θ of the image-jackknife replicates, if any
    inlier_tensors: np.ndarray  # (n,) bool, ‖r_i‖ < τ at the estimate
    norms: np.ndarray  # (n,) ‖r_i‖ at the estimate
    score: float  # MSAC score at the estimate
    per_tensor_theta: np.ndarray | None = None  # (n, 4) msac candidates
    per_tensor_scores: np.ndarray | None = None  # (n,) their MSAC scores


def solve(
    tensors: list[TripletTensor],
    method: str,
    parametrization: Parametrization | None = None,
    tau: float = MSAC_TAU,
    irls_iterations: int = 10,
    span: Parametrization | None = None,
) -> ConstraintSolution:
    """Run one TrifocalCalib variant (``direct``, ``msac``, ``msac-opt``) from the start.

    Args:
        tensors: tensors normalised by the start K (θ = 0).
        method: ``direct``, ``msac`` or ``msac-opt``.
        parametrization: the unknowns (default: all four free); the solve starts at
            its ``p = 0``, i.e. the start K with held parameters at their values.
        tau: MSAC threshold on ‖r_i‖.
        irls_iterations: msac-opt reweighting rounds at most.
        span: the unknowns the returned ``information`` covers (default: those of
            ``parametrization``); a larger set's lets a caller judge what fixing
            parameters costs (:func:`.fallback.solve_with_fallback`).
    """
    parametrization = parametrization or FULL_PARAMETRIZATION
    span = span or parametrization
    theta0 = parametrization.theta(np.zeros(parametrization.dimension))
    problem = ConstraintProblem.build(tensors, theta0, parametrization)
    candidates = scores = None
    if method == "direct":
        theta = problem.least_squares(theta0)
    else:
        candidates, scores = _msac_candidates(problem, theta0, tau)
        theta = candidates[int(np.argmax(scores))]
        if method == "msac-opt":
            # Re-whiten at the msac estimate: the covariance of the constraints depends on K.
            problem = ConstraintProblem.build(tensors, theta, parametrization)
            theta = problem.minimise_msac_cost(theta, tau, irls_iterations)
    residuals = problem.residuals(theta)
    jacobians = problem.jacobians(theta)
    norms = np.linalg.norm(residuals, axis=-1)
    weights, fit_weights = _weights(norms, tau, direct=method == "direct")

    def replicate(keep: np.ndarray) -> np.ndarray | None:
        return one_step_replicate(
            theta, parametrization.matrix, residuals[keep], jacobians[keep], fit_weights[keep]
        )

    replicates = jackknife_replicates([t.image_ids for t in tensors], replicate)
    curvature = problem.information(theta, weights, residuals, jacobians)
    information = combined_information(curvature, replicates, span)
    return ConstraintSolution(
        theta=theta,
        covariance=conditioned_covariance(information, parametrization)[0],
        information=information,
        relative_std=relative_std(information, parametrization),
        jackknife=replicates,
        inlier_tensors=norms < tau,
        norms=norms,
        score=msac_score(norms, tau),
        per_tensor_theta=candidates,
        per_tensor_scores=scores,
    )


def _msac_candidates(
    problem: ConstraintProblem, theta0: np.ndarray, tau: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each tensor's own estimate (n, 4) and its MSAC score over all tensors (n,; -inf
    where not finite)."""
    candidates = problem.per_tensor_estimates(theta0)
    # ‖r_j(θ_i)‖ for every candidate i (rows) and tensor j (columns).
    all_norms = np.linalg.norm(problem.residuals(candidates), axis=-1)
    scores = 1.0 - np.mean(np.minimum(all_norms / tau, 1.0), axis=1)
    scores[~np.all(np.isfinite(candidates), axis=1)] = -np.inf
    return candidates, scores


def _weights(norms: np.ndarray, tau: float, *, direct: bool) -> tuple[np.ndarray, np.ndarray]:
    """The information's weights (all tensors for direct, else the MSAC inliers) and the
    fit's own (IRLS: 1/‖r_i‖ on inliers) for the jackknife replicates."""
    inliers = norms < tau
    if direct or not inliers.any():
        ones = np.ones(len(norms))
        return ones, ones
    return inliers.astype(float), np.where(inliers, 1.0 / np.maximum(norms, 1e-3), 0.0)
