"""The relative motion of two views from their matches, and whether a camera moves forward.

Points are normalised camera coordinates (pixels through K⁻¹, K = [[fx, 0, cx],
[0, fy, cy], [0, 0, 1]]) unless named pixels. The relative motion is OpenCV's 5-point
essential matrix (RANSAC) and its decomposition by cheirality (:func:`recover_pose`): it
needs K only roughly right (a few percent).
"""

from __future__ import annotations

import cv2
import numpy as np

from ..common.parallel import map_jobs
from ..common.sampling import evenly_spaced
from .trifocal import intrinsics_matrix

#: Depth beyond which a point counts as at infinity and does not vote for a
#: decomposition, in units of the baseline (OpenCV's ``recoverPose`` default).
CHEIRALITY_DISTANCE = 50.0


def recover_pose(
    E: np.ndarray, x1: np.ndarray, x2: np.ndarray, mask: np.ndarray | None = None
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """The decomposition ``[R | t]`` of an essential matrix that puts the most points in
    front of both views: OpenCV's ``recoverPose`` for normalised points, vectorised.

    The four candidates are ``cv2.decomposeEssentialMat``'s (R1, t), (R2, t), (R1, −t),
    (R2, −t); a point votes for one where its depths in both views lie in
    (0, ``CHEIRALITY_DISTANCE``); ties go to the earlier candidate, as OpenCV's do. A
    point's depth d₁ in view 1 is the least-squares solution of ``d₂ x₂ = d₁ R x₁ + t``
    (cross both sides with x₂), d₂ the third row; negating t negates both. OpenCV
    triangulates every point by the DLT (an SVD per point, per candidate): the votes
    differ only for points whose depth lies at a bound (noisy or far ones), at a third
    of the cost.

    Args:
        E: (3, 3) essential matrix, ``x2ᵀ E x1 = 0``.
        x1, x2: (n, 2) normalised camera coordinates of the matches in views 1 and 2.
        mask: (n,) the points that may vote (non-zero), None: all.

    Returns:
        (votes, R (3, 3), t (3,) unit, voters (n,) bool): the chosen candidate, its
        number of votes and which points cast them.
    """
    R1, R2, t = cv2.decomposeEssentialMat(E)
    t = t.ravel()
    rotations = np.stack([R1, R2])
    n = len(x1)
    h1 = np.concatenate([x1, np.ones((n, 1))], axis=1)
    h2 = np.concatenate([x2, np.ones((n, 1))], axis=1)
    rays = np.einsum("kij,nj->kni", rotations, h1)  # R x₁ for R1 and R2: (2, n, 3)
    a = np.cross(h2, rays)
    b = np.cross(h2, t)
    depth1 = -np.einsum("kni,ni->kn", a, b) / np.maximum(np.einsum("kni,kni->kn", a, a), 1e-300)
    depth2 = depth1 * rays[..., 2] + t[2]
    allowed = np.ones(n, bool) if mask is None else np.asarray(mask).ravel() != 0
    voters = [
        allowed
        & (sign * depth1[k] > 0)
        & (sign * depth1[k] < CHEIRALITY_DISTANCE)
        & (sign * depth2[k] > 0)
        & (sign * depth2[k] < CHEIRALITY_DISTANCE)
        for sign in (1.0, -1.0)
        for k in (0, 1)
    ]
    votes = [int(np.count_nonzero(v)) for v in voters]
    chosen = next(k for k in range(4) if all(votes[k] >= v for v in votes[k + 1 :]))
    return votes[chosen], rotations[chosen % 2], t if chosen < 2 else -t, voters[chosen]


#: Median ``|t_z|`` of the unit translations at and above which a camera moves forward.
FORWARD_COSINE = 0.9


def relative_motion(x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Rotation (3, 3) and unit translation (3,) of view 2 from normalised points (n, 2)."""
    E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.RANSAC, threshold=1e-3)
    if E is None or E.shape != (3, 3):
        return None
    _, R, t, _ = recover_pose(E, x1, x2, mask)
    return R, t


#: Consecutive image pairs :func:`moves_forward` looks at (evenly spread).
FORWARD_PAIRS = 12
#: Matches per pair :func:`moves_forward` reads at most (evenly spaced): a relative
#: translation's direction is as clear from 500 matches as from thousands.
FORWARD_MAX_MATCHES = 500


def moves_forward(
    keypoints: dict[int, np.ndarray],
    matches: dict[tuple[int, int], np.ndarray],
    intrinsics: np.ndarray,
    min_matches: int = 30,
    workers: int | None = None,
) -> bool:
    """Whether the camera moves along its optical axis between consecutive images.

    Over up to ``FORWARD_PAIRS`` pairs of consecutive image ids with ``min_matches``
    verified matches (at most ``FORWARD_MAX_MATCHES`` of each): the median ``|t_z|``
    of their relative translation (OpenCV's essential matrix in coordinates
    normalised by ``intrinsics``, pixels) is at least ``FORWARD_COSINE``. A drive or a
    walk-through video moves forward (its adjacent frames barely differ, so triplets
    must span wider gaps); a turntable or an orbit moves sideways (adjacent frames
    already do): the median ``|t_z|`` is about 1 for a drive and near 0 for a
    turntable (docs/planar_and_sequences.md). The pairs run over ``workers`` threads
    (None: one per core).
    """
    ids = sorted(keypoints)
    consecutive = [
        (a, b)
        for a, b in zip(ids, ids[1:], strict=False)
        if len(matches.get((a, b), ())) >= min_matches
    ]
    if not consecutive:
        return False
    chosen = evenly_spaced(len(consecutive), FORWARD_PAIRS)
    K_inv = np.linalg.inv(intrinsics_matrix(np.asarray(intrinsics, float)))
    jobs = []
    for a, b in (consecutive[i] for i in chosen):
        m = matches[(a, b)]
        m = m[evenly_spaced(len(m), FORWARD_MAX_MATCHES)]
        x1 = normalised_coordinates(keypoints[a][m[:, 0], :2], K_inv)
        x2 = normalised_coordinates(keypoints[b][m[:, 1], :2], K_inv)
        jobs.append((x1, x2))
    motions = map_jobs(_relative_motion_job, jobs, workers)
    forward = [abs(float(motion[1][2])) for motion in motions if motion is not None]
    return bool(forward) and float(np.median(forward)) >= FORWARD_COSINE


def _relative_motion_job(
    job: tuple[np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray] | None:
    return relative_motion(*job)


def normalised_coordinates(pixels: np.ndarray, K_inv: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) in normalised camera coordinates (n, 2)."""
    return np.asarray(pixels @ K_inv[:2, :2].T + K_inv[:2, 2])
