"""Three-view projective bundle adjustment (the Gold Standard trifocal tensor).

Minimises the reprojection error of n point tracks in three views over the
projective cameras ``P2``, ``P3`` (``P1 = [I | 0]`` fixes the frame) and the
points, with Levenberg–Marquardt and the Schur complement on the 3x3 point
blocks. The tensor of the refined cameras is geometrically valid by
construction and is the maximum-likelihood tensor under Gaussian pixel noise
(H&Z Algorithm 16.2).

Points are parametrised as ``X = (u, v, 1, ρ)``: (u, v) is the point in view 1
and ρ an inverse depth, so points at infinity (ρ = 0) need no special case.

Coordinates are *prior-normalised* (``x̂ = K0⁻¹ x``); residuals are scaled back
to pixels by ``pixel_scale = (fx0, fy0)``, so costs and the noise estimate are
in pixels.

The camera covariance (24x24, for ``vec(P2), vec(P3)`` row-major) is
``σ² S⁺``, with S the reduced camera matrix at the optimum. S has a 6-dimensional
null space: the 4 projective gauge freedoms that keep ``P1 = [I|0]`` and the
scales of P2 and P3. The tensor is invariant along all six, so the pseudo-inverse
without those directions is the covariance of everything the tensor depends on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GAUGE_DIMENSION = 6
_POINT_COLUMNS = [0, 1, 3]  # dX/d(u, v, ρ) picks these columns of P
#: The Levenberg–Marquardt damping λ of the first step (λ·I added to the normal
#: equations, px² per normalised unit²: far below their curvature, a Gauss–Newton step).
INITIAL_DAMPING = 1e-3
#: The refinement stops once the Gauss–Newton step from the current point predicts a
#: cost decrease below this fraction of σ²: the optimum is within √0.01 = 0.1 σ
#: (Mahalanobis, over cameras and points) of where it stops. On a near-planar triplet
#: the relative cost decrease keeps above the tolerance for many more steps there.
DECREMENT_STOP = 0.01
#: The pixel noise σ (px) is at least this: the precision of a keypoint that COLMAP stores
#: as float32, at a few thousand pixels. Exact tracks (a model's own projections) would
#: otherwise give a σ of round-off (10⁻¹³ px), and a camera covariance by which the
#: round-off in every tensor's constraints lies many σ out, so that no tensor agrees.
MIN_SIGMA_PX = 1e-4


@dataclass
class ProjectiveBAResult:
    """Refined cameras, points and second-order information of a triplet."""

    P2: np.ndarray  # (3, 4), unit Frobenius norm
    P3: np.ndarray  # (3, 4), unit Frobenius norm
    points: np.ndarray  # (n, 3): u, v, ρ
    squared_errors: np.ndarray  # (n,) sum over the 3 views of squared pixel errors
    camera_covariance: np.ndarray  # (24, 24), in units of P entries², noise included
    sigma: float  # estimated pixel noise (per coordinate), px, at least MIN_SIGMA_PX
    iterations: int


def initial_points(x: np.ndarray, P2: np.ndarray, P3: np.ndarray) -> np.ndarray:
    """Closed-form (u, v, ρ) for tracks x (3, n, 2): u, v from view 1, ρ from views 2 and 3.

    ρ minimises the algebraic error ``Σ_views |[x_j]× (P_j[:, :3] x1 + ρ P_j[:, 3])|²``.
    """
    p1 = np.concatenate([x[0], np.ones((x.shape[1], 1))], axis=1)
    numerator = np.zeros(x.shape[1])
    denominator = np.zeros(x.shape[1])
    for view, P in ((1, P2), (2, P3)):
        pj = np.concatenate([x[view], np.ones((x.shape[1], 1))], axis=1)
        c = np.cross(pj, p1 @ P[:, :3].T)
        d = np.cross(pj, np.broadcast_to(P[:, 3], pj.shape))
        numerator += np.einsum("na,na->n", c, d)
        denominator += np.einsum("na,na->n", d, d)
    rho = -numerator / np.maximum(denominator, 1e-300)
    return np.column_stack([x[0], rho])


def _projections(
    points: np.ndarray, P2: np.ndarray, P3: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The points' homogeneous coordinates ``Xh = (u, v, 1, ρ)`` (4, n), from points in
    columns (3, n), and their homogeneous images in views 2 and 3, ``Y[j] = P_(j+2) Xh``
    (2, 3, n)."""
    Xh = np.empty((4, points.shape[1]))
    Xh[:2] = points[:2]
    Xh[2] = 1.0
    Xh[3] = points[2]
    return Xh, (np.concatenate([P2, P3]) @ Xh).reshape(2, 3, -1)


def _residuals(
    x: np.ndarray, P2: np.ndarray, P3: np.ndarray, points: np.ndarray, scale: np.ndarray
) -> np.ndarray:
    """Pixel residuals (3 views, 2, n) of the points in columns (3, n), for observations
    in columns (3 views, 2, n)."""
    return _residuals_at(x, points, _projections(points, P2, P3)[1], scale)


def _residuals_at(
    x: np.ndarray, points: np.ndarray, Y: np.ndarray, scale: np.ndarray
) -> np.ndarray:
    """:func:`_residuals`, given the points' images ``Y`` (2, 3, n) in views 2 and 3."""
    out = np.empty((3, 2, points.shape[1]))
    out[0] = points[:2] - x[0]
    out[1:] = Y[:, :2] / Y[:, 2:] - x[1:]
    out *= scale[:, None]
    return out


class _Buffers:
    """The large per-track arrays of one refinement, allocated once and written in place
    at every iteration: fresh temporaries of a few hundred kB each are page-faulted in
    anew by every allocation (glibc returns them to the system when freed), which took
    more time than the arithmetic. ``camera_jacobian`` keeps its zero entries."""

    def __init__(self, n: int) -> None:
        self.camera_jacobian = np.zeros((2, 3, 4, 2, n))  # view, row r, column c of P, a, n
        self.W = np.empty((2, 3, 4, 3, n))  # view, r, c, point parameter k, n
        self.product = np.empty((24, 3, n))


def _linearise(
    x: np.ndarray,
    P2: np.ndarray,
    P3: np.ndarray,
    points: np.ndarray,
    scale: np.ndarray,
    buffers: _Buffers,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Normal-equation blocks: U (24,24), V (3,3,n), W (24,3,n), g_c (24,), g_p (3,n), r.

    Everything per track is laid out with the tracks last ("columns"), so that each
    product below is one element-wise operation over n contiguous values: a track's
    2x3 and 2x12 Jacobian blocks are far too small for matrix products to pay.
    ``W[i, k, n] = Σ_a ∂r_na/∂c_i ∂r_na/∂X_nk``; r is (3 views, 2, n). W is a view
    of ``buffers``, valid until the next linearisation.
    """
    n = points.shape[1]
    Xh, Y = _projections(points, P2, P3)
    r = _residuals_at(x, points, Y, scale)
    inv_z = 1.0 / Y[:, 2]
    image = Y[:, :2] * inv_z[:, None]  # (2 views, 2 a, n)
    weight = scale[None, :, None] * inv_z[:, None]  # ∂(pixel a)/∂y_a = s_a / z
    # ∂(pixel a)/∂X_k = w_a (P[a, k] − p_a P[2, k]) over the point columns k of P.
    Pc = np.stack([P2[:, _POINT_COLUMNS], P3[:, _POINT_COLUMNS]])
    J_pt = weight[:, :, None] * (Pc[:, :2, :, None] - image[:, :, None] * Pc[:, 2, None, :, None])
    # ∂(pixel a)/∂P[r, c] = w_a Xh_c where r = a, −w_a p_a Xh_c where r = 2, else 0.
    scaled = weight[:, :, None] * Xh  # (2, 2, 4, n)
    J_cam = buffers.camera_jacobian
    J_cam[:, 0, :, 0] = scaled[:, 0]
    J_cam[:, 1, :, 1] = scaled[:, 1]
    np.multiply(scaled[:, 0], -image[:, 0, None], out=J_cam[:, 2, :, 0])
    np.multiply(scaled[:, 1], -image[:, 1, None], out=J_cam[:, 2, :, 1])
    U = np.zeros((24, 24))
    g_c = np.empty(24)
    for view in range(2):
        flat = J_cam[view].reshape(12, 2 * n)
        block = slice(12 * view, 12 * view + 12)
        U[block, block] = flat @ flat.T
        g_c[block] = -(flat @ r[view + 1].reshape(2 * n))
    # W by the rows r of P: pixel a alone at r = a; at r = 2, −p_a times those terms.
    W = buffers.W
    np.multiply(scaled[:, 0, :, None], J_pt[:, 0, None], out=W[:, 0])
    np.multiply(scaled[:, 1, :, None], J_pt[:, 1, None], out=W[:, 1])
    np.multiply(W[:, 0], -image[:, 0, None, None], out=W[:, 2])
    W[:, 2] -= W[:, 1] * image[:, 1, None, None]
    V = np.einsum("vajn,vakn->jkn", J_pt, J_pt)
    V[0, 0] += scale[0] ** 2
    V[1, 1] += scale[1] ** 2
    g_p = -np.einsum("vakn,van->kn", J_pt, r[1:])
    g_p[:2] -= r[0] * scale[:, None]
    return U, V, W.reshape(24, 3, n), g_c, g_p, r


def refine_triplet(
    x: np.ndarray,
    P2: np.ndarray,
    P3: np.ndarray,
    pixel_scale: np.ndarray,
    points: np.ndarray | None = None,
    max_iterations: int = 30,
    tolerance: float = 1e-4,
) -> ProjectiveBAResult:
    """Levenberg–Marquardt refinement of P2, P3 and the points of one triplet.

    The damping is Levenberg's, λ·I in the normalised coordinates of the cameras and
    points, updated by the gain ratio (Nielsen's rule: the actual over the predicted
    cost decrease). Marquardt's scaling by the diagonal leaves the weakly determined
    directions of a near-planar triplet almost undamped: their steps overshoot along
    the curved valley, and the refinement crawls.

    Args:
        x: prior-normalised observations (3, n, 2) of n tracks in views 1, 2, 3.
        P2, P3: initial cameras (3, 4) in the same coordinates, ``P1 = [I|0]``.
        pixel_scale: (2,) pixels per normalised unit in x and y (fx0, fy0).
        points: initial (u, v, ρ) per track (n, 3); by default :func:`initial_points`.
        max_iterations: LM iterations at most.
        tolerance: stop when the relative cost decrease falls below this (or the
            Gauss–Newton step predicts less than ``DECREMENT_STOP`` σ²).
    """
    scale = np.asarray(pixel_scale, dtype=float)
    columns = _columns(x)
    state, iteration, dof = _minimise(columns, P2, P3, scale, points, max_iterations, tolerance)
    U, V, W, _, _, r = _linearise(columns, state.P2, state.P3, state.points, scale, state.buffers)
    V_inverse = np.ascontiguousarray(point_block_inverses(V.transpose(2, 0, 1)).transpose(1, 2, 0))
    S = U - _schur_product(W, V_inverse, state.buffers)[0]
    sigma2 = max(state.cost / dof, MIN_SIGMA_PX**2)
    return ProjectiveBAResult(
        P2=state.P2,
        P3=state.P3,
        points=np.ascontiguousarray(state.points.T),
        squared_errors=np.einsum("van,van->n", r, r),
        camera_covariance=sigma2 * gauge_free_inverse(S),
        sigma=float(np.sqrt(sigma2)),
        iterations=iteration,
    )


def refined_cost(
    x: np.ndarray,
    P2: np.ndarray,
    P3: np.ndarray,
    pixel_scale: np.ndarray,
    max_iterations: int = 30,
    tolerance: float = 1e-4,
) -> tuple[np.ndarray, float]:
    """:func:`refine_triplet`'s squared errors (n,) px² (summed over the 3 views) and its
    σ (px), the same values, without the cameras' covariance it does not need (one
    linearisation and the Schur complement fewer): the cost of the projective fit that
    a calibrated fit of the same tracks is compared with."""
    scale = np.asarray(pixel_scale, dtype=float)
    columns = _columns(x)
    state, _, dof = _minimise(columns, P2, P3, scale, None, max_iterations, tolerance)
    r = _residuals(columns, state.P2, state.P3, state.points, scale)
    return np.einsum("van,van->n", r, r), float(np.sqrt(max(state.cost / dof, MIN_SIGMA_PX**2)))


def _columns(x: np.ndarray) -> np.ndarray:
    """Observations (3 views, n, 2) laid out with the tracks last: (3 views, 2, n)."""
    return np.ascontiguousarray(np.asarray(x, dtype=float).transpose(0, 2, 1))


def _minimise(
    columns: np.ndarray,
    P2: np.ndarray,
    P3: np.ndarray,
    scale: np.ndarray,
    points: np.ndarray | None,
    max_iterations: int,
    tolerance: float,
) -> tuple[_State, int, int]:
    """The Levenberg–Marquardt iterations of :func:`refine_triplet`: where they end
    (points in columns, (3, n)), how many ran and the residuals' degrees of freedom.
    ``columns`` are the observations (3 views, 2, n), as :func:`_columns` lays them out."""
    P2 = P2 / np.linalg.norm(P2)
    P3 = P3 / np.linalg.norm(P3)
    start = initial_points(columns.transpose(0, 2, 1), P2, P3) if points is None else points
    state_points = np.ascontiguousarray(start.T, dtype=float)
    cost = float(np.sum(_residuals(columns, P2, P3, state_points, scale) ** 2))
    state = _State(P2, P3, state_points, cost, _Buffers(state_points.shape[1]))
    iteration = 0
    n = state_points.shape[1]
    dof = max(6 * n - (3 * n + 24 - GAUGE_DIMENSION), 1)
    for iteration in range(1, max_iterations + 1):  # noqa: B007 - returned below
        improved, relative_decrease, near_minimum = _iterate(state, columns, scale, dof)
        if not improved or relative_decrease < tolerance or near_minimum:
            break
    return state, iteration, dof


@dataclass
class _State:
    """Where the refinement is: the cameras (unit norm), the points in columns (3, n),
    the cost (px²), and Levenberg's damping λ with its growth factor after a rejected
    step."""

    P2: np.ndarray
    P3: np.ndarray
    points: np.ndarray
    cost: float
    buffers: _Buffers
    damping: float = INITIAL_DAMPING
    growth: float = 2.0


def _iterate(state: _State, x: np.ndarray, scale: np.ndarray, dof: int) -> tuple[bool, float, bool]:
    """One Levenberg–Marquardt iteration on ``state``, in place: damped steps until one
    lowers the cost. Returns whether one did, its relative decrease, and whether the
    optimum is near (the Gauss–Newton step predicts less than ``DECREMENT_STOP`` σ²).
    ``x`` are the observations in columns (3 views, 2, n)."""
    system = _NormalEquations(
        *_linearise(x, state.P2, state.P3, state.points, scale, state.buffers)[:5], state.buffers
    )
    while state.damping < 1e12:
        step = system.step(state.damping)
        if step is None:
            break
        delta_c, delta_p, predicted = step
        P2_new = state.P2 + delta_c[:12].reshape(3, 4)
        P3_new = state.P3 + delta_c[12:].reshape(3, 4)
        points_new = state.points + delta_p
        new_cost = float(np.sum(_residuals(x, P2_new, P3_new, points_new, scale) ** 2))
        if np.isfinite(new_cost) and new_cost < state.cost:
            cost = state.cost
            # The decrease over the predicted one, at most 1: Nielsen's update below
            # shrinks the damping by 1/3 for any gain from 1 on, and a predicted decrease
            # near 0 would otherwise give a gain whose cube overflows.
            gain = min((cost - new_cost) / max(predicted, 1e-300), 1.0)
            state.P2, state.P3 = P2_new / np.linalg.norm(P2_new), P3_new / np.linalg.norm(P3_new)
            state.points = points_new
            relative_decrease = (cost - new_cost) / max(cost, 1e-300)
            threshold = DECREMENT_STOP * new_cost / dof
            near_minimum = False
            if predicted < threshold:
                # The damped step predicted little: so does the Gauss–Newton step from
                # the same point where the optimum is near (checked, not assumed, since
                # damping shortens the step along a flat valley).
                gauss_newton = system.step(0.0)
                near_minimum = gauss_newton is not None and gauss_newton[2] < threshold
            state.cost = new_cost
            state.damping *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            state.growth = 2.0
            return True, relative_decrease, near_minimum
        state.damping *= state.growth
        state.growth *= 2.0
    return False, 0.0, False


@dataclass
class _NormalEquations:
    """The normal equations of one linearisation (:func:`_linearise`'s blocks, tracks
    last), solved for a damping λ by the Schur complement on the 3x3 point blocks."""

    U: np.ndarray  # (24, 24)
    V: np.ndarray  # (3, 3, n)
    W: np.ndarray  # (24, 3, n)
    g_c: np.ndarray  # (24,)
    g_p: np.ndarray  # (3, n)
    buffers: _Buffers  # where W and the step's products are written

    def step(self, damping: float) -> tuple[np.ndarray, np.ndarray, float] | None:
        """(δ cameras (24,), δ points (3, n), the cost decrease the step's quadratic
        model predicts, gᵀδ + λ|δ|²) at damping λ; None where the system is not finite."""
        V_inv = inverse_3x3_columns(self.V + (damping + 1e-12) * np.eye(3)[:, :, None])
        reduced, WV = _schur_product(self.W, V_inv, self.buffers)
        S = self.U + damping * np.eye(24) - reduced
        b = self.g_c - WV @ self.g_p.ravel()
        if not (np.all(np.isfinite(S)) and np.all(np.isfinite(b))):
            return None
        delta_c = np.linalg.lstsq(S, b, rcond=None)[0]
        rhs = self.g_p - (delta_c @ self.W.reshape(24, -1)).reshape(3, -1)
        delta_p = V_inv[:, 0] * rhs[0] + V_inv[:, 1] * rhs[1] + V_inv[:, 2] * rhs[2]
        predicted = float(
            self.g_c @ delta_c
            + np.sum(self.g_p * delta_p)
            + damping * (delta_c @ delta_c + np.sum(delta_p * delta_p))
        )
        return delta_c, delta_p, predicted


def _schur_product(
    W: np.ndarray, M: np.ndarray, buffers: _Buffers
) -> tuple[np.ndarray, np.ndarray]:
    """``Σ_n W_n M_n W_nᵀ`` (24, 24) for W (24, 3, n) and symmetric point blocks M
    (3, 3, n), and ``W M`` flattened to (24, 3n), the factor of the right-hand side
    (a view of ``buffers``)."""
    WM_flat = np.einsum("ajn,jkn->akn", W, M, out=buffers.product).reshape(24, -1)
    return WM_flat @ W.reshape(24, -1).T, WM_flat


def inverse_3x3(M: np.ndarray) -> np.ndarray:
    """Inverses of a stack of 3x3 matrices (n, 3, 3) by cofactors (inf/nan where singular).

    Several times faster than ``np.linalg.inv`` on small blocks, and it never raises.
    """
    return inverse_3x3_columns(M.transpose(1, 2, 0)).transpose(2, 0, 1)


def inverse_3x3_columns(M: np.ndarray) -> np.ndarray:
    """:func:`inverse_3x3` of matrices laid out with the stack last, (3, 3, n)."""
    adjugate, determinant = _adjugate_and_determinant(M)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(adjugate / determinant)


def _adjugate_and_determinant(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The adjugates (3, 3, n) of 3x3 matrices stacked last (3, 3, n) and their
    determinants (n,)."""
    a, b, c = M[0, 0], M[0, 1], M[0, 2]
    d, e, f = M[1, 0], M[1, 1], M[1, 2]
    g, h, i = M[2, 0], M[2, 1], M[2, 2]
    out = np.empty_like(M)
    out[0, 0], out[0, 1], out[0, 2] = e * i - f * h, c * h - b * i, b * f - c * e
    out[1, 0], out[1, 1], out[1, 2] = f * g - d * i, a * i - c * g, c * d - a * f
    out[2, 0], out[2, 1], out[2, 2] = d * h - e * g, b * g - a * h, a * e - b * d
    return out, a * out[0, 0] + b * out[1, 0] + c * out[2, 0]


#: A point block whose determinant is below this fraction of its diagonal's product
#: (Hadamard's bound: the fraction is 1 for a diagonal block, 0 for a singular one) is
#: inverted by SVD: cofactors lose about −log10(fraction) significant digits, SVD none.
CONDITIONED_BLOCK = 1e-6


def point_block_inverses(V: np.ndarray) -> np.ndarray:
    """Pseudo-inverses of the symmetric PSD point blocks V (n, 3, 3).

    A point seen along its own epipolar direction has a singular block, whose
    pseudo-inverse leaves the undetermined direction out. Cofactors (as
    :func:`inverse_3x3`; their determinant also judges the conditioning) where the
    block is well conditioned, SVD (``np.linalg.pinv``) where not: the same
    pseudo-inverse to rounding, at a tenth of the cost of SVD for every block.
    """
    adjugate, determinant = _adjugate_and_determinant(V.transpose(1, 2, 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        inverses = np.asarray(adjugate / determinant).transpose(2, 0, 1)
    diagonal = np.einsum("nii->ni", V).prod(axis=1)
    conditioned = (determinant > CONDITIONED_BLOCK * diagonal) & (diagonal > 0)
    conditioned &= np.isfinite(inverses).all(axis=(1, 2))
    if not conditioned.all():
        inverses[~conditioned] = np.linalg.pinv(V[~conditioned])
    return inverses


def gauge_free_inverse(S: np.ndarray, gauge_dimension: int = GAUGE_DIMENSION) -> np.ndarray:
    """Pseudo-inverse of a symmetric PSD matrix without its ``gauge_dimension`` weakest
    directions (the gauge null space)."""
    eigenvalues, eigenvectors = np.linalg.eigh(0.5 * (S + S.T))
    keep = eigenvectors[:, gauge_dimension:]
    return np.asarray((keep / eigenvalues[gauge_dimension:]) @ keep.T)
