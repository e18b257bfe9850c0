"""What one calibrated triplet's tracks say about the shared camera: its Schur complement.

A triplet of the polish (:mod:`intrinsics.polish.bundle`) has three calibrated cameras
``[R_v | t_v]`` (view 1 fixed), n points ``X_j`` and their pixels ``x_vj``; the
residuals are ``π(K (R_v X_j + t_v)) − x_vj`` in pixels, ``K = [[fx, 0, cx],
[0, fy, cy], [0, 0, 1]]``. Linearised at a solution, the normal equations of
(intrinsics, poses of views 2 and 3, points) are reduced to the intrinsics by
eliminating the points (3x3 blocks) and then the poses (12x12, less the triplet's
scale, a gauge direction that leaves K unchanged). What is left is the triplet's
information on (fx, fy, cx, cy) and its gradient there, so that

* the covariance of the camera shared by many triplets is ``σ² (Σ_t H_t)⁻¹``, and
* leaving triplets out moves the estimate, to first order, by one Gauss–Newton step
  ``−(Σ_kept H_t)⁻¹ Σ_kept g_t`` (the jackknife without new adjustments).

Poses are perturbed on the left: ``X_c = exp([ω]ₓ)(R X + t) + δt``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...geometry.projective_ba import gauge_free_inverse, inverse_3x3


def reduced_information(
    intrinsics: np.ndarray,
    poses: np.ndarray,
    points: np.ndarray,
    pixels: np.ndarray,
    radial: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """One triplet's information and gradient on the camera, and its cost.

    The camera is (fx, fy, cx, cy) and, with ``radial``, COLMAP's radial distortion
    ``(k1[, k2])`` of ``SIMPLE_RADIAL`` / ``RADIAL``: a point at normalised ``(u, v)``,
    ``ρ = u² + v²``, is seen at ``(fx u s + cx, fy v s + cy)``, ``s = 1 + k1 ρ + k2 ρ²``.

    Args:
        intrinsics: (fx, fy, cx, cy), pixels.
        poses: (3, 3, 4) ``[R | t]`` world-to-camera of views 1, 2, 3 (view 1 held).
        points: (n, 3) the tracks' points, world coordinates.
        pixels: (3, n, 2) the observations, pixels.
        radial: (m,) the radial coefficients (m = 1 or 2), None for a pinhole camera.

    Returns:
        H (q, q) = ``J_kᵀ J_k`` with poses and points eliminated, g (q,) = the reduced
        ``J_kᵀ r`` (the gradient of half the squared error), and ``Σ r²`` (px²);
        q = 4 + m, the camera's parameters in the order above.
    """
    k = np.zeros(2) if radial is None else np.r_[np.asarray(radial, float), 0.0][:2]
    m = 0 if radial is None else len(radial)
    q = 4 + m
    normal = _NormalEquations.zeros(len(points), q)
    for view in range(3):
        normal.add(*_view_terms(intrinsics, k, m, view, poses[view], points, pixels[view]))
    return normal.reduced()


@dataclass
class _NormalEquations:
    """The normal equations of (camera, poses of views 2 and 3) and the points, summed
    over a triplet's views: the camera-and-pose block U, the point blocks V (n, 3, 3),
    their cross terms W (n, q + 12, 3), the gradients and the squared error."""

    q: int
    U: np.ndarray
    V: np.ndarray
    W: np.ndarray
    g_y: np.ndarray
    g_p: np.ndarray
    cost: float = 0.0

    @classmethod
    def zeros(cls, n: int, q: int) -> _NormalEquations:
        return cls(
            q,
            np.zeros((q + 12, q + 12)),
            np.zeros((n, 3, 3)),
            np.zeros((n, q + 12, 3)),
            np.zeros(q + 12),
            np.zeros((n, 3)),
        )

    def add(self, r: np.ndarray, J_y: np.ndarray, J_p: np.ndarray) -> None:
        """Add one view's residuals r (n, 2) and their derivatives by the camera and
        poses J_y (n, 2, q + 12) and by the points J_p (n, 2, 3)."""
        n = len(r)
        self.cost += float(np.sum(r * r))
        flat = J_y.reshape(2 * n, self.q + 12)
        self.U += flat.T @ flat
        self.g_y += flat.T @ r.reshape(2 * n)
        J_pt = np.swapaxes(J_p, 1, 2)  # (n, 3, 2)
        self.V += J_pt @ J_p
        self.W += np.swapaxes(J_y, 1, 2) @ J_p
        self.g_p += (J_pt @ r[:, :, None])[:, :, 0]

    def reduced(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(H, g, cost) with the points, then the poses eliminated (their null
        direction is the triplet's scale)."""
        q = self.q
        V_inverse = inverse_3x3(self.V + 1e-12 * np.eye(3))
        WV = self.W @ V_inverse  # (n, q + 12, 3)
        S = self.U - np.einsum("nak,nbk->ab", WV, self.W)
        g = self.g_y - np.einsum("nak,nk->a", WV, self.g_p)
        S_cc_inverse = gauge_free_inverse(S[q:, q:], 1)
        H = S[:q, :q] - S[:q, q:] @ S_cc_inverse @ S[q:, :q]
        gradient = g[:q] - S[:q, q:] @ S_cc_inverse @ g[q:]
        return 0.5 * (H + H.T), gradient, self.cost


def _view_terms(
    intrinsics: np.ndarray,
    k: np.ndarray,
    m: int,
    view: int,
    pose: np.ndarray,
    points: np.ndarray,
    pixels: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view's residuals (n, 2), their derivatives by the camera's q = 4 + m
    parameters and the poses of views 2 and 3 (n, 2, q + 12; view 1's pose is held)
    and by the points (n, 2, 3)."""
    fx, fy, cx, cy = intrinsics
    q, n = 4 + m, len(points)
    R, t = pose[:, :3], pose[:, 3]
    local = points @ R.T + t  # (n, 3)
    z = local[:, 2]
    u, v = local[:, 0] / z, local[:, 1] / z
    rho = u * u + v * v
    scale = 1.0 + k[0] * rho + k[1] * rho * rho
    slope = k[0] + 2.0 * k[1] * rho  # d scale / d rho
    r = np.stack([fx * u * scale + cx, fy * v * scale + cy], axis=1) - pixels
    # d pixel / d (u, v), (n, 2, 2), then d pixel / d camera-frame point, (n, 2, 3)
    M = np.empty((n, 2, 2))
    M[:, 0, 0] = fx * (scale + 2.0 * u * u * slope)
    M[:, 0, 1] = fx * 2.0 * u * v * slope
    M[:, 1, 0] = fy * 2.0 * u * v * slope
    M[:, 1, 1] = fy * (scale + 2.0 * v * v * slope)
    P = np.zeros((n, 2, 3))
    P[:, 0, 0], P[:, 0, 2] = 1.0 / z, -u / z
    P[:, 1, 1], P[:, 1, 2] = 1.0 / z, -v / z
    D = M @ P
    J_y = np.zeros((n, 2, q + 12))
    J_y[:, 0, 0], J_y[:, 1, 1] = u * scale, v * scale
    J_y[:, 0, 2], J_y[:, 1, 3] = 1.0, 1.0
    for power in range(1, m + 1):
        J_y[:, 0, 3 + power] = fx * u * rho**power
        J_y[:, 1, 3 + power] = fy * v * rho**power
    if view > 0:
        skew = np.zeros((n, 3, 3))  # −[X_c]ₓ
        skew[:, 0, 1], skew[:, 0, 2] = local[:, 2], -local[:, 1]
        skew[:, 1, 0], skew[:, 1, 2] = -local[:, 2], local[:, 0]
        skew[:, 2, 0], skew[:, 2, 1] = local[:, 1], -local[:, 0]
        columns = slice(q + 6 * (view - 1), q + 6 + 6 * (view - 1))
        J_y[:, :, columns] = np.concatenate([D @ skew, D], axis=2)
    return r, J_y, D @ R
