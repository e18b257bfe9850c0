"""The Mendonça–Cipolla cost of intrinsics for a set of fundamental matrices, and its
problem in the conditioned parameters (see :mod:`.fundamental` for the conventions).

``c_ij = (σ1 − σ2) / σ2`` (``"ratio"``) or ``(σ1 − σ2) / (σ1 + σ2)``
(``"normalized"``) of ``Kᵀ F_ij K``; in the conditioned form ``Mᵀ G M`` with
``G = K0ᵀ F K0`` and ``M = K0⁻¹ K``, with the analytic Jacobian
(``dσ_k = u_kᵀ dE v_k``) over one batched SVD of the ``(n, 3, 3)`` stack.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

CostForm = Literal["ratio", "normalized"]


def calibration_matrix(theta: np.ndarray) -> np.ndarray:
    """Return the ``(3, 3)`` calibration matrix for ``theta = (fx, fy, cx, cy)`` (pixels)."""
    fx, fy, cx, cy = (float(v) for v in theta)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def unit_frobenius(mats: np.ndarray) -> np.ndarray:
    """Scale every matrix of an ``(n, 3, 3)`` stack to unit Frobenius norm."""
    norms = np.linalg.norm(mats.reshape(len(mats), -1), axis=1)
    return np.asarray(mats / norms[:, None, None])


def pair_costs(s1: np.ndarray, s2: np.ndarray, form: CostForm) -> np.ndarray:
    """Per-pair cost from the two largest singular values (``s1 >= s2``)."""
    if form == "ratio":
        return np.asarray((s1 - s2) / s2)
    return np.asarray((s1 - s2) / (s1 + s2))


def essential_cost(
    fundamentals: np.ndarray,
    intrinsics: np.ndarray,
    weights: np.ndarray | None = None,
    form: CostForm = "ratio",
) -> float:
    """Mendonça–Cipolla cost ``Σ w_ij c_ij²`` of the intrinsics for a set of F matrices.

    Args:
        fundamentals: ``(n, 3, 3)`` fundamental matrices, ``x2ᵀ F x1 = 0`` in pixels.
        intrinsics: ``(4,)`` ``fx, fy, cx, cy`` in pixels.
        weights: ``(n,)`` non-negative pair weights; ``None`` means all ones.
        form: ``"ratio"`` for ``c = (σ1 − σ2)/σ2`` (Mendonça–Cipolla) or ``"normalized"``
            for ``c = (σ1 − σ2)/(σ1 + σ2)``.

    Returns:
        The weighted sum of squared per-pair costs (dimensionless, 0 for exact data at the
        true ``K``).
    """
    f = unit_frobenius(np.asarray(fundamentals, dtype=float).reshape(-1, 3, 3))
    k = calibration_matrix(np.asarray(intrinsics, dtype=float))
    e = k.T @ f @ k
    sig = np.linalg.svd(e, compute_uv=False)
    c = pair_costs(sig[:, 0], sig[:, 1], form)
    w = np.ones(len(f)) if weights is None else np.asarray(weights, dtype=float)
    return float(np.sum(w * c**2))


def _basis(*, single_focal: bool) -> np.ndarray:
    """Derivatives ``dM/dθ_p`` as a ``(P, 3, 3)`` stack for the relative parametrisation."""
    rows = [[0, 0], [1, 1], [0, 2], [1, 2]]
    b = np.zeros((4, 3, 3))
    for p, (r, c) in enumerate(rows):
        b[p, r, c] = 1.0
    if single_focal:
        return np.stack([b[0] + b[1], b[2], b[3]])
    return b


@dataclass(frozen=True)
class EssentialProblem:
    """The weighted per-pair residuals ``sqrt(w) c`` of the conditioned matrices ``g``
    (n, 3, 3), ``K0ᵀ F K0``, as a function of the relative parameters x:
    ``(fx/fx0, fy/fy0, (cx − cx0)/fx0, (cy − cy0)/fy0)``, or ``(f/f0, u, v)`` with one
    focal length."""

    g: np.ndarray
    sqrt_w: np.ndarray
    single_focal: bool
    form: CostForm = "ratio"

    def matrix(self, x: np.ndarray) -> np.ndarray:
        """``M = K0⁻¹ K`` from the relative parameters."""
        if self.single_focal:
            a = b = x[0]
            u, v = x[1], x[2]
        else:
            a, b, u, v = x
        return np.array([[a, 0.0, u], [0.0, b, v], [0.0, 0.0, 1.0]])

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """(n,) weighted per-pair residuals at x."""
        m = self.matrix(x)
        sig = np.linalg.svd(m.T @ self.g @ m, compute_uv=False)
        return np.asarray(self.sqrt_w * pair_costs(sig[:, 0], sig[:, 1], self.form))

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """(n, P) derivatives of :meth:`residuals` by x."""
        m = self.matrix(x)
        g = self.g
        u, sig, vt = np.linalg.svd(m.T @ g @ m)
        s1, s2 = sig[:, 0], sig[:, 1]
        # dσ_k = u_kᵀ dE v_k with dE = dMᵀ G M + Mᵀ G dM, so
        # dσ_k/dM[r, c] = (G M v_k)[r] u_k[c] + (Gᵀ M u_k)[r] v_k[c].
        uk = u[:, :, :2]  # (n, 3, 2) columns u_1, u_2
        vk = np.swapaxes(vt[:, :2, :], 1, 2)  # (n, 3, 2) columns v_1, v_2
        gmv = g @ (m @ vk)  # (n, 3, 2)
        gtmu = np.swapaxes(g, 1, 2) @ (m @ uk)  # (n, 3, 2)
        dsig_dm = np.einsum("nrk,nck->nkrc", gmv, uk) + np.einsum("nrk,nck->nkrc", gtmu, vk)
        dsig = np.einsum(
            "nkrc,prc->nkp", dsig_dm, _basis(single_focal=self.single_focal)
        )  # (n, 2, P)
        d1, d2 = dsig[:, 0, :], dsig[:, 1, :]
        if self.form == "ratio":
            dc = (d1 * s2[:, None] - d2 * s1[:, None]) / (s2**2)[:, None]
        else:
            dc = 2.0 * (d1 * s2[:, None] - d2 * s1[:, None]) / ((s1 + s2) ** 2)[:, None]
        return np.asarray(self.sqrt_w[:, None] * dc)
