"""One triplet's trifocal tensor: its settings, the estimated tensor, the transfer error.

:class:`TensorEstimationOptions` are the per-triplet estimation's settings,
:class:`TripletTensor` its result (the refined cameras in coordinates normalised by the
start K0, their covariance, the inliers), :func:`transfer_errors` the reprojection
error of tracks through a pair of cameras. The estimation itself:
:mod:`.triplet_fit`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .trifocal import normalize_tensor, tensor_from_cameras

#: Relative cost decrease below which the bundle adjustment stops (general triplets).
BA_TOLERANCE = 1e-4


@dataclass
class TensorEstimationOptions:
    """Settings of the per-triplet estimation (pixels are those of the keypoints)."""

    num_hypotheses: int = 32
    #: A track is an inlier when its reprojection error over views 2 and 3,
    #: sqrt(e2² + e3²), is below this, in pixels. COLMAP verifies pairs at 4 px.
    inlier_threshold_px: float = 4.0
    min_inliers: int = 30
    #: Bundle adjustment / inlier re-selection rounds at most (stops when at most
    #: 0.5 % of the tracks change side; usually after 2).
    refinement_rounds: int = 5
    max_ba_iterations: int = 30
    #: Tracks on which the hypotheses are scored (a random subset).
    max_scored_tracks: int = 500
    #: Tracks used by the bundle adjustment (a random subset of the inliers).
    #: The covariance passed on accounts for how many were used.
    max_refined_tracks: int = 500
    #: A triplet is planar-dominant when this share of its tracks fits one plane's
    #: homographies (:mod:`.planarity`; e.g. ``PLANAR_SHARE`` = 0.5); it then gets a
    #: plane + parallax start as well. Off by default (above 1): besides the two
    #: converged starts it makes more facade triplets agree but not the estimate
    #: more accurate (docs/planar_and_sequences.md).
    planar_share: float = 2.0
    #: Refine the calibrated hypothesis (prior K, 5-point + PnP) as a second start
    #: besides the best MSAC hypothesis (always done for planar-dominant triplets).
    calibrated_start: bool = True
    #: Every start is refined on with this BA stopping rule (relative cost decrease,
    #: iterations at most) and the lowest MSAC score wins; a tolerance at or above
    #: ``BA_TOLERANCE`` (1e-4) skips it: each start then keeps its refinement at
    #: ``BA_TOLERANCE``, which can stop along a facade's flat valley.
    final_ba_tolerance: float = 1e-9
    final_ba_iterations: int = 200


@dataclass
class TripletTensor:
    """A refined, geometrically valid trifocal tensor in prior-normalised coordinates."""

    image_ids: tuple[int, int, int]
    tensor: np.ndarray  # (3, 3, 3), unit Frobenius norm, slices T[i] (see trifocal.py)
    P2: np.ndarray  # (3, 4) with P1 = [I|0]
    P3: np.ndarray  # (3, 4)
    camera_covariance: np.ndarray  # (24, 24) covariance of vec(P2), vec(P3)
    num_tracks: int
    num_inliers: int
    sigma_px: float  # estimated keypoint noise, px
    inliers: np.ndarray = field(repr=False)  # (num_tracks,) bool

    def renormalised(self, K_old: np.ndarray, K_new: np.ndarray) -> TripletTensor:
        """The same tensor in coordinates normalised by ``K_new`` instead of ``K_old`` (3x3).

        Normalised points change by ``N = K_new⁻¹ K_old``; with the world changed by
        ``diag(N, 1)`` view 1 stays ``[I | 0]`` and ``P = [A | a]`` becomes
        ``[N A N⁻¹ | N a]``, scaled to unit norm. The covariance follows linearly
        (row-major ``vec(N P H⁻¹) = (N ⊗ H⁻ᵀ) vec(P)``), each camera's scale direction
        projected out. The fit is the maximum-likelihood fit in pixels whatever the
        normalisation, so this is the tensor re-estimation from ``K_new`` converges to
        when it reaches the same minimum.
        """
        N = np.linalg.solve(K_new, K_old)
        H_inverse = np.eye(4)
        H_inverse[:3, :3] = np.linalg.inv(N)
        cameras, jacobian = [], np.zeros((24, 24))
        for block, P in enumerate((self.P2, self.P3)):
            moved = N @ P @ H_inverse
            scale = np.linalg.norm(moved)
            unit = moved / scale
            projector = np.eye(12) - np.outer(unit.ravel(), unit.ravel())
            rows = slice(12 * block, 12 * block + 12)
            jacobian[rows, rows] = projector @ np.kron(N, H_inverse.T) / scale
            cameras.append(unit)
        P2, P3 = cameras
        return TripletTensor(
            image_ids=self.image_ids,
            tensor=normalize_tensor(tensor_from_cameras(P2, P3)),
            P2=P2,
            P3=P3,
            camera_covariance=jacobian @ self.camera_covariance @ jacobian.T,
            num_tracks=self.num_tracks,
            num_inliers=self.num_inliers,
            sigma_px=self.sigma_px,
            inliers=self.inliers,
        )


def transfer_errors(
    x: np.ndarray, P2: np.ndarray, P3: np.ndarray, pixel_scale: np.ndarray
) -> np.ndarray:
    """Squared reprojection errors (…, n) of tracks x (3, n, 2) under cameras (…, 3, 4).

    Each track keeps its view-1 point; its inverse depth ρ minimises the algebraic
    error in views 2 and 3; the errors of views 2 and 3 are summed (pixels²).
    Leading dimensions of P2/P3 (hypotheses) broadcast against the tracks.
    """
    # Component by component over (…, n) arrays: the tracks' 3-vectors are far too
    # short for products over a last axis of 3 to pay.
    u1, v1 = x[0, :, 0], x[0, :, 1]
    views = []
    numerator: np.ndarray | float = 0.0
    denominator: np.ndarray | float = 0.0
    for view, P in ((1, P2), (2, P3)):
        A = P[..., None]  # (…, 3, 4, 1): each entry against the n tracks
        c = [A[..., k, 0, :] * u1 + A[..., k, 1, :] * v1 + A[..., k, 2, :] for k in range(3)]
        d = [A[..., k, 3, :] for k in range(3)]  # a4
        px, py = x[view, :, 0], x[view, :, 1]
        # (x, y, 1) × c and (x, y, 1) × d
        cx = (py * c[2] - c[1], c[0] - px * c[2], px * c[1] - py * c[0])
        dx = (py * d[2] - d[1], d[0] - px * d[2], px * d[1] - py * d[0])
        numerator = numerator + (cx[0] * dx[0] + cx[1] * dx[1] + cx[2] * dx[2])
        denominator = denominator + (dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2])
        views.append((c, d, px, py))
    rho = -numerator / np.maximum(denominator, 1e-300)
    errors: np.ndarray | float = 0.0
    for c, d, px, py in views:
        y = [c[k] + rho * d[k] for k in range(3)]
        with np.errstate(divide="ignore", invalid="ignore"):
            du = (y[0] / y[2] - px) * pixel_scale[0]
            dv = (y[1] / y[2] - py) * pixel_scale[1]
        errors = errors + du * du + dv * dv
    return np.where(np.isfinite(errors), errors, np.inf)
