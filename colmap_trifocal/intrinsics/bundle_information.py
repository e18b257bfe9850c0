"""What one calibrated triplet's tracks say about the shared camera: its Schur complement.

A triplet of the polish (:mod:`.triplet_bundle`) has three calibrated cameras
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

import numpy as np

from ..geometry.projective_ba import gauge_free_inverse, inverse_3x3


def reduced_information(
    intrinsics: np.ndarray, poses: np.ndarray, points: np.ndarray, pixels: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """One triplet's information and gradient on (fx, fy, cx, cy), and its cost.

    Args:
        intrinsics: (fx, fy, cx, cy), pixels.
        poses: (3, 3, 4) ``[R | t]`` world-to-camera of views 1, 2, 3 (view 1 held).
        points: (n, 3) the tracks' points, world coordinates.
        pixels: (3, n, 2) the observations, pixels.

    Returns:
        H (4, 4) = ``J_kᵀ J_k`` with poses and points eliminated, g (4,) = the reduced
        ``J_kᵀ r`` (the gradient of half the squared error), and ``Σ r²`` (px²).
    """
    fx, fy, cx, cy = intrinsics
    n = len(points)
    V = np.zeros((n, 3, 3))  # point blocks
    W = np.zeros((n, 16, 3))  # (intrinsics, poses of views 2 and 3) x point
    U = np.zeros((16, 16))
    g_y = np.zeros(16)
    g_p = np.zeros((n, 3))
    cost = 0.0
    for view in range(3):
        R, t = poses[view][:, :3], poses[view][:, 3]
        local = points @ R.T + t  # (n, 3)
        z = local[:, 2]
        u, v = local[:, 0] / z, local[:, 1] / z
        r = np.stack([fx * u + cx, fy * v + cy], axis=1) - pixels[view]  # (n, 2)
        cost += float(np.sum(r * r))
        # d pixel / d camera-frame point, (n, 2, 3)
        D = np.zeros((n, 2, 3))
        D[:, 0, 0], D[:, 0, 2] = fx / z, -fx * u / z
        D[:, 1, 1], D[:, 1, 2] = fy / z, -fy * v / z
        J_k = np.zeros((n, 2, 4))
        J_k[:, 0, 0], J_k[:, 1, 1], J_k[:, 0, 2], J_k[:, 1, 3] = u, v, 1.0, 1.0
        J_p = D @ R  # (n, 2, 3)
        J_y = np.zeros((n, 2, 16))
        J_y[:, :, :4] = J_k
        if view > 0:
            skew = np.zeros((n, 3, 3))  # −[X_c]ₓ
            skew[:, 0, 1], skew[:, 0, 2] = local[:, 2], -local[:, 1]
            skew[:, 1, 0], skew[:, 1, 2] = -local[:, 2], local[:, 0]
            skew[:, 2, 0], skew[:, 2, 1] = local[:, 1], -local[:, 0]
            columns = slice(4 + 6 * (view - 1), 10 + 6 * (view - 1))
            J_y[:, :, columns] = np.concatenate([D @ skew, D], axis=2)
        flat = J_y.reshape(2 * n, 16)
        U += flat.T @ flat
        g_y += flat.T @ r.reshape(2 * n)
        J_pt = np.swapaxes(J_p, 1, 2)  # (n, 3, 2)
        V += J_pt @ J_p
        W += np.swapaxes(J_y, 1, 2) @ J_p
        g_p += (J_pt @ r[:, :, None])[:, :, 0]
    V_inverse = inverse_3x3(V + 1e-12 * np.eye(3))
    WV = W @ V_inverse  # (n, 16, 3)
    S = U - np.einsum("nak,nbk->ab", WV, W)
    g = g_y - np.einsum("nak,nk->a", WV, g_p)
    # Eliminate the poses (rows 4..15); their null direction is the triplet's scale.
    S_cc_inverse = gauge_free_inverse(S[4:, 4:], 1)
    H = S[:4, :4] - S[:4, 4:] @ S_cc_inverse @ S[4:, :4]
    gradient = g[:4] - S[:4, 4:] @ S_cc_inverse @ g[4:]
    return 0.5 * (H + H.T), gradient, cost
