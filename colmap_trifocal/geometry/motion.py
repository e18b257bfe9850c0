"""The relative motion of two views from their matches, and whether a camera moves forward.

Points are normalised camera coordinates (pixels through K⁻¹, K = [[fx, 0, cx],
[0, fy, cy], [0, 0, 1]]) unless named pixels. The relative motion is OpenCV's 5-point
essential matrix (RANSAC) and ``recoverPose``: it needs K only roughly right (a few
percent).
"""

from __future__ import annotations

import cv2
import numpy as np

from ..common.parallel import map_jobs
from ..common.sampling import evenly_spaced
from .trifocal import intrinsics_matrix

#: Median ``|t_z|`` of the unit translations at and above which a camera moves forward.
FORWARD_COSINE = 0.9


def relative_motion(x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Rotation (3, 3) and unit translation (3,) of view 2 from normalised points (n, 2)."""
    E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.RANSAC, threshold=1e-3)
    if E is None or E.shape != (3, 3):
        return None
    _, R, t, _ = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask.copy())
    return R, t.ravel() / max(float(np.linalg.norm(t)), 1e-12)


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
