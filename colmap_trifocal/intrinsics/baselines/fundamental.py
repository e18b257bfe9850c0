"""FundamentalCalib: self-calibration from fundamental matrices (Mendonça & Cipolla, 1999).

Classical baseline of P. R. S. Mendonça and R. Cipolla, "A simple technique for
self-calibration", CVPR 1999. All views share one calibration matrix

.. code-block:: text

    K = [[fx,  0, cx],
         [ 0, fy, cy],
         [ 0,  0,  1]]

and for the true ``K`` every ``E_ij = Kᵀ F_ij K`` is an essential matrix, i.e. its two
non-zero singular values are equal. We minimise over ``θ = (fx, fy, cx, cy)``

.. code-block:: text

    C(K) = Σ_ij w_ij · c_ij²,    c_ij = (σ1 − σ2) / σ2,

where ``σ1 ≥ σ2`` are the two largest singular values of ``Kᵀ F_ij K`` (the
Mendonça–Cipolla ratio; it is invariant to the scale of ``F_ij``).

Conventions
-----------
* ``F`` maps image-1 pixels to epipolar lines in image 2: ``x2ᵀ F x1 = 0`` with
  homogeneous pixel coordinates ``x = (u, v, 1)``. Because ``C`` depends on ``F`` only via
  ``Kᵀ F K`` the cost is the same for ``Fᵀ``, so the direction does not matter here.
* Pixel coordinates follow COLMAP: the centre of the top-left pixel is at ``(0.5, 0.5)``;
  ``cx, cy`` are reported in that convention (whatever convention the ``F`` matrices and the
  prior use, the result uses the same one).
* Focal lengths and principal point are in pixels.

Conditioning
------------
Each ``F`` is first scaled to unit Frobenius norm, then pre-conditioned with the prior
``K0``: ``G = K0ᵀ F K0`` (again unit Frobenius norm). With ``M = K0⁻¹ K``,
``Kᵀ F K ∝ Mᵀ G M`` and

.. code-block:: text

    M = [[fx/fx0,      0, (cx − cx0)/fx0],
         [     0, fy/fy0, (cy − cy0)/fy0],
         [     0,      0,              1]],

so the optimisation variables are exactly the relative changes
``(fx/fx0, fy/fy0, (cx − cx0)/fx0, (cy − cy0)/fy0)``, all O(1) and starting at
``(1, 1, 0, 0)``. The Jacobian is analytic (``dσ_k = u_kᵀ dE v_k``) and everything is
evaluated with one batched SVD of the ``(n, 3, 3)`` stack.

Robustness
----------
With ``robust=True`` scipy's ``'cauchy'`` loss ``ρ(z) = log(1 + z)`` is used with
``f_scale = 0.02`` (:data:`ROBUST_LOSS`, :data:`ROBUST_F_SCALE`), in units of the per-pair
residual ``sqrt(w_ij / mean(w)) · c_ij`` (weights are rescaled to mean one, so the scale
does not depend on how the weights are normalised). A pair with ``c_ij = 0.02`` (a 2 % gap
between σ1 and σ2) gets half the weight of a perfect one; a wrong F (``c`` ≈ 0.3–4) is
essentially ignored. With 0.5–2 px noise on well-spread views the correct pairs have
``c`` ≈ 0.001–0.02, while on real data (distortion, short baselines) it can be larger, hence
0.02 rather than the slightly better synthetic optimum 0.01.

Why Cauchy: its influence decays for large residuals, so wrong F's stop pulling K;
``soft_l1`` and ``huber`` keep a constant influence and the wrong pairs still drag K
away. The ratio and the normalised form ``(σ1−σ2)/(σ1+σ2)`` behave the same once
``f_scale`` is halved for the latter (``(σ1−σ2)/(σ1+σ2) ≈ c/2`` near the solution), so
the Mendonça–Cipolla ratio is used. The errors of each loss and scale:
docs/accuracy.md, "Why these constants".
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.common.log import logger

from ..inputs.camera_input import CameraInput
from ..results import PARAMETER_NAMES, CameraCalibration, Provenance, Timing
from .essential_cost import (
    CostForm,
    EssentialProblem,
    calibration_matrix,
    essential_cost,
    unit_frobenius,
)

__all__ = [
    "ROBUST_F_SCALE",
    "ROBUST_LOSS",
    "FundamentalCalibResult",
    "calibrate_from_fundamentals",
    "calibrate_fundamental",
    "essential_cost",
]

#: Robust loss passed to :func:`scipy.optimize.least_squares` when ``robust=True``.
ROBUST_LOSS = "cauchy"
#: Soft threshold of the robust loss, in units of the (mean-one weighted) per-pair cost.
ROBUST_F_SCALE = 0.02


# F's with σ2 <= _MIN_SIGMA2 · σ1 (rank < 2) are ignored: their cost would be unbounded.
_MIN_SIGMA2 = 1e-9
# Bounds on the relative focal changes fx/fx0, fy/fy0 (keep K invertible, focal positive).
_REL_FOCAL_BOUNDS = (0.05, 20.0)


@dataclass
class FundamentalCalibResult:
    """Result of :func:`calibrate_from_fundamentals`.

    Attributes:
        intrinsics: ``(4,)`` array ``fx, fy, cx, cy`` in pixels (COLMAP pixel convention:
            centre of the top-left pixel at ``(0.5, 0.5)``). With ``single_focal=True``
            ``fx == fy``.
        cost: Final weighted cost ``Σ w_ij · c_ij²`` with the weights as given (not the
            robustified value, not normalised), ``c_ij = (σ1 − σ2)/σ2``.
        num_pairs: Number of fundamental matrices used (positive weight and rank 2).
        success: ``True`` if the optimiser converged to a finite solution with positive
            focal lengths strictly inside the search bounds.
    """

    intrinsics: np.ndarray
    cost: float
    num_pairs: int
    success: bool


def _validate(
    fundamentals: np.ndarray, prior: np.ndarray, weights: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Check the inputs; return ``(F stack, prior, weights)`` as float arrays."""
    f = np.asarray(fundamentals, dtype=float)
    if f.ndim == 2 and f.shape == (3, 3):
        f = f[None]
    if f.ndim != 3 or f.shape[1:] != (3, 3):
        raise CalibrationError(f"fundamental matrices must have shape (n, 3, 3), got {f.shape}")
    if len(f) < 2:
        raise CalibrationError(
            f"FundamentalCalib needs at least 2 fundamental matrices, got {len(f)}"
        )
    if not np.all(np.isfinite(f)):
        raise CalibrationError("fundamental matrices contain non-finite values")
    if np.any(np.linalg.norm(f.reshape(len(f), -1), axis=1) == 0.0):
        raise CalibrationError("a fundamental matrix is all zeros")

    p = np.asarray(prior, dtype=float)
    if p.shape != (4,) or not np.all(np.isfinite(p)) or p[0] <= 0.0 or p[1] <= 0.0:
        raise CalibrationError(
            "prior must be 4 finite values fx, fy, cx, cy with positive focal lengths, "
            f"got {np.asarray(prior).tolist()}"
        )

    if weights is None:
        w = np.ones(len(f))
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape != (len(f),) or not np.all(np.isfinite(w)) or np.any(w < 0.0):
            raise CalibrationError(
                f"weights must be {len(f)} finite non-negative values, got shape {w.shape}"
            )
    if np.count_nonzero(w > 0.0) < 2:
        raise CalibrationError("FundamentalCalib needs at least 2 pairs with positive weight")
    return f, p, w


@dataclass(frozen=True)
class _Settings:
    """How the cost is formed and made robust (see the module docstring)."""

    single_focal: bool
    form: CostForm = "ratio"
    loss: str = ROBUST_LOSS
    f_scale: float = ROBUST_F_SCALE


def _usable(
    fundamentals: np.ndarray, prior: np.ndarray, weights: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The checked F stack, prior and weights of the pairs that count (rank 2, weight
    above 0); CalibrationError with fewer than 2."""
    f_all, p, w_all = _validate(fundamentals, prior, weights)
    sig_all = np.linalg.svd(unit_frobenius(f_all), compute_uv=False)
    rank_deficient = sig_all[:, 1] <= _MIN_SIGMA2 * sig_all[:, 0]
    if np.any(rank_deficient & (w_all > 0.0)):
        logger.warning(
            "FundamentalCalib: ignoring %d fundamental matrices of rank < 2",
            int(np.count_nonzero(rank_deficient & (w_all > 0.0))),
        )
    keep = (w_all > 0.0) & ~rank_deficient
    if np.count_nonzero(keep) < 2:
        raise CalibrationError(
            "FundamentalCalib needs at least 2 fundamental matrices of rank 2 with positive "
            f"weight, got {int(np.count_nonzero(keep))}"
        )
    return f_all[keep], p, w_all[keep]


def _calibrate(
    fundamentals: np.ndarray, prior: np.ndarray, weights: np.ndarray | None, settings: _Settings
) -> FundamentalCalibResult:
    """Implementation of :func:`calibrate_from_fundamentals` with an explicit cost/loss."""
    f, p, w = _usable(fundamentals, prior, weights)
    single_focal = settings.single_focal
    fx0, fy0, cx0, cy0 = p
    if single_focal:
        fx0 = fy0 = 0.5 * (fx0 + fy0)
    k0 = calibration_matrix(np.array([fx0, fy0, cx0, cy0]))
    problem = EssentialProblem(
        unit_frobenius(k0.T @ unit_frobenius(f) @ k0),
        np.sqrt(w / np.mean(w)),  # mean-one weights so f_scale has a fixed meaning
        single_focal,
        settings.form,
    )
    focals = 1 if single_focal else 2
    x0 = np.array([1.0] * focals + [0.0, 0.0])
    lo = np.array([_REL_FOCAL_BOUNDS[0]] * focals + [-np.inf] * 2)
    hi = np.array([_REL_FOCAL_BOUNDS[1]] * focals + [np.inf] * 2)
    sol = least_squares(
        problem.residuals,
        x0,
        jac=problem.jacobian,
        bounds=(lo, hi),
        method="trf",
        loss=settings.loss,
        f_scale=settings.f_scale,
        ftol=1e-12,
        xtol=1e-12,
        gtol=1e-12,
        max_nfev=500,
    )
    x = sol.x
    a, b = (x[0], x[0]) if single_focal else (x[0], x[1])
    u, v = x[focals], x[focals + 1]
    intrinsics = np.array([a * fx0, b * fy0, cx0 + u * fx0, cy0 + v * fy0])
    cost = essential_cost(f, intrinsics, w, settings.form)
    inside = bool(np.all(x[:focals] > lo[:focals] * 1.001)) and bool(
        np.all(x[:focals] < hi[:focals] * 0.999)
    )
    success = bool(sol.success) and bool(np.all(np.isfinite(intrinsics))) and inside
    success = success and bool(np.isfinite(cost))
    logger.debug(
        "FundamentalCalib: %d pairs, cost %.3g, nfev %d, status %d, K = %s",
        len(f),
        cost,
        sol.nfev,
        sol.status,
        np.array2string(intrinsics, precision=2),
    )
    return FundamentalCalibResult(
        intrinsics=intrinsics, cost=cost, num_pairs=len(f), success=success
    )


def calibrate_from_fundamentals(
    fundamentals: np.ndarray,
    prior: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    single_focal: bool = False,
    robust: bool = True,
) -> FundamentalCalibResult:
    """Estimate shared intrinsics ``fx, fy, cx, cy`` from fundamental matrices.

    Minimises ``Σ w_ij c_ij²`` with ``c_ij = (σ1 − σ2)/σ2`` of ``Kᵀ F_ij K`` (see the module
    docstring) with :func:`scipy.optimize.least_squares`, starting from ``prior``.

    Args:
        fundamentals: ``(n, 3, 3)`` fundamental matrices with ``x2ᵀ F x1 = 0`` for pixel
            coordinates (COLMAP convention). Each is scaled to unit Frobenius norm; the
            rank is not enforced (the two largest singular values are used).
        prior: ``(4,)`` initial ``fx, fy, cx, cy`` in pixels (e.g. from EXIF and the image
            centre). Only used as the starting point and for conditioning. With
            ``single_focal`` the start focal is ``(fx + fy)/2``.
        weights: ``(n,)`` non-negative weights per pair, e.g. inlier match counts; ``None``
            means all equal. Pairs with weight 0 are ignored, and so are (with a logged
            warning) F's of numerical rank < 2.
        single_focal: Estimate one focal length (``fx == fy``) plus ``cx, cy``.
        robust: Use the ``cauchy`` loss with ``f_scale = 0.02`` (see
            :data:`ROBUST_LOSS`, :data:`ROBUST_F_SCALE`) instead of plain least squares.

    Returns:
        A :class:`FundamentalCalibResult`.

    Raises:
        CalibrationError: Fewer than 2 usable (rank-2, positively weighted) F's, a
            malformed/non-finite input, or a prior that is not 4 finite values with
            positive focal lengths.
    """
    settings = _Settings(single_focal, loss=ROBUST_LOSS if robust else "linear")
    return _calibrate(fundamentals, prior, weights, settings)


def calibrate_fundamental(data: CameraInput) -> CameraCalibration:
    """The Mendonça–Cipolla baseline on F re-estimated from the undistorted verified matches.

    F is re-fitted (normalised 8-point on COLMAP's inliers) rather than read from
    the database because the stored F relates raw, distorted keypoints. ``seconds``
    is this baseline's own time.
    """
    clock = time.perf_counter()
    camera, prior, keypoints = data.camera, data.prior, data.keypoints
    fundamentals, weights = [], []
    for (a, b), m in data.matches.items():
        if len(m) < 15:
            continue
        F, _ = cv2.findFundamentalMat(keypoints[a][m[:, 0]], keypoints[b][m[:, 1]], cv2.FM_8POINT)
        if F is not None and F.shape == (3, 3):
            fundamentals.append(F)
            weights.append(len(m))
    if len(fundamentals) < 2:
        raise CalibrationError(
            f"camera {camera.camera_id}: fewer than 2 image pairs with enough verified matches"
        )
    result = calibrate_from_fundamentals(
        np.stack(fundamentals),
        prior,
        np.asarray(weights, float),
        single_focal=camera.single_focal,
    )
    return CameraCalibration(
        camera_id=camera.camera_id,
        model=camera.model,
        method="fundamental",
        fx=float(result.intrinsics[0]),
        fy=float(result.intrinsics[1]),
        cx=float(result.intrinsics[2]),
        cy=float(result.intrinsics[3]),
        std={name: None for name in PARAMETER_NAMES},
        observable={name: bool(result.success) for name in PARAMETER_NAMES},
        num_triplets=0,
        num_inlier_triplets=0,
        timing=Timing(seconds=time.perf_counter() - clock),
        prior=tuple(map(float, prior)),  # type: ignore[arg-type]
        start=tuple(map(float, prior)),  # type: ignore[arg-type]
        provenance=Provenance(stored_camera=camera),
    )
