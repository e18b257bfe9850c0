"""Why the images do not determine some intrinsics: the cause the tracks show.

:mod:`intrinsics.solve.observability` says *which* parameters the triplets leave undetermined;
this module says *why*, from the triplets' tracks measured with the estimate K
(pixels, K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]):

* **too few tracks**: the median triplet has fewer than ``MIN_TRACKS`` tracks;
* **too similar images**: the keypoints of most view pairs move less than
  ``MIN_DISPLACEMENT_PX`` (median over the tracks): copies of one image, or a camera
  that did not move; no motion can be measured then, so nothing else is said;
* **planar structure**: a homography (OpenCV RANSAC, ``HOMOGRAPHY_PX``) explains
  at least ``PLANAR_FRACTION`` of the tracks between the views of most triplets
  (a facade, or too little translation to see depth);
* **pure translation / forward motion**: the relative rotations (essential matrix,
  OpenCV 5-point RANSAC and its cheirality) are mostly (75th percentile) below
  ``MIN_ROTATION_DEG``;
  forward when the translation is mostly along the optical axis;
* **rotation about one axis**: at least ``ONE_AXIS_FRACTION`` of the squared
  rotation (rotation vectors of all pairs) is about one axis (planar motion: a
  car turning, an orbit at constant height); the axis is named in camera
  coordinates. Small rotations have noisy axes, so the vectors are weighted by
  their angle rather than each axis counted alike.

Rotations only need K roughly right (a few percent), which every estimate that
reaches this stage is. Each finding is a short phrase with the measured figure.
"""

from __future__ import annotations

import cv2
import numpy as np

from ...common.parallel import map_jobs
from ...geometry.motion import FORWARD_COSINE, normalised_coordinates, relative_motion
from ...geometry.planarity import plane_homography
from ...geometry.trifocal import intrinsics_matrix

MIN_TRACKS = 80
#: Median keypoint displacement (pixels) below which two views show no motion at all.
MIN_DISPLACEMENT_PX = 3.0
HOMOGRAPHY_PX = 2.0
PLANAR_FRACTION = 0.8
MIN_ROTATION_DEG = 1.0
ONE_AXIS_FRACTION = 0.95
#: Triplets examined at most (the first selected ones).
MAX_TRIPLETS = 8


def homography_fraction(x1: np.ndarray, x2: np.ndarray) -> float:
    """Fraction of the tracks (pixels, (n, 2)) one homography explains within HOMOGRAPHY_PX."""
    if len(x1) < 8:
        return 0.0
    H, inliers = plane_homography(x1, x2, HOMOGRAPHY_PX, method=cv2.USAC_DEFAULT)
    return 0.0 if H is None else float(inliers.mean())


def diagnose(tracks: list[np.ndarray], intrinsics: np.ndarray, workers: int | None = None) -> str:
    """The causes of weak self-calibration the tracks show, as one phrase.

    Args:
        tracks: per triplet, undistorted pixel tracks (3, n, 2).
        intrinsics: (fx, fy, cx, cy) of the estimate, pixels.
        workers: threads over the view pairs (None: one per core).

    Returns:
        e.g. ``"rotation about one axis (planar motion; camera y, up to 12° between views)"``; ``"no
        degenerate motion found"`` when none of the causes applies.
    """
    K_inv = np.linalg.inv(intrinsics_matrix(np.asarray(intrinsics, float)))
    counts = [x.shape[1] for x in tracks]
    findings = []
    if np.median(counts) < MIN_TRACKS:
        findings.append(f"too few tracks (median {np.median(counts):.0f} per triplet)")
    examined = [np.asarray(x, dtype=np.float64) for x in tracks[:MAX_TRIPLETS]]
    displacements = [
        float(np.median(np.linalg.norm(x[view] - x[0], axis=-1)))
        for x in examined
        for view in (1, 2)
    ]
    if displacements and np.percentile(displacements, 75) < MIN_DISPLACEMENT_PX:
        findings.append(
            "too similar images (keypoints move "
            f"{np.percentile(displacements, 75):.1f} px between views: copies of one image?)"
        )
        return "; ".join(findings)
    jobs = [(np.ascontiguousarray(x[[0, view]]), K_inv) for x in examined for view in (1, 2)]
    pairs = map_jobs(_pair_job, jobs, workers)
    fractions = [fraction for fraction, _ in pairs]
    if fractions and np.median(fractions) >= PLANAR_FRACTION:
        findings.append(
            f"planar structure (a homography explains {100 * np.median(fractions):.0f} % "
            "of the tracks)"
        )
    motion = _motion_finding([motion for _, motion in pairs if motion is not None])
    if motion is not None:
        findings.append(motion)
    return "; ".join(findings) if findings else "no degenerate motion found"


def _motion_finding(motions: list[tuple[np.ndarray, np.ndarray]]) -> str | None:
    """What the view pairs' relative motions (R, unit t) show: pure translation or
    forward motion, rotation about one axis, or nothing (None)."""
    if not motions:
        return None
    vectors = [cv2.Rodrigues(R)[0].ravel() for R, _ in motions]
    angles = [np.rad2deg(np.linalg.norm(vector)) for vector in vectors]
    forward = [abs(t[2]) for _, t in motions]
    largest = float(np.max(angles))
    # The 75th percentile: one pair's spurious rotation (an essential matrix measured
    # with a K a few percent off) must not hide a translating camera.
    typical = float(np.percentile(angles, 75))
    if typical < MIN_ROTATION_DEG:
        if np.median(forward) >= FORWARD_COSINE:
            return f"forward motion with little rotation (mostly below {typical:.1f}°)"
        return f"pure translation (rotation mostly below {typical:.1f}°)"
    if _one_axis(np.array(vectors)):
        mean = _principal_axis(np.array(vectors))
        name = "xyz"[int(np.argmax(np.abs(mean)))]
        return (
            f"rotation about one axis (planar motion; camera {name}, up to {largest:.0f}° "
            "between views)"
        )
    return None


def _pair_job(
    job: tuple[np.ndarray, np.ndarray],
) -> tuple[float, tuple[np.ndarray, np.ndarray] | None]:
    """The homography fraction and the relative motion of a view pair (2, n, 2), pixels."""
    pixels, K_inv = job
    normalised = normalised_coordinates(pixels, K_inv)
    return (
        homography_fraction(pixels[0], pixels[1]),
        relative_motion(normalised[0], normalised[1]),
    )


def _principal_axis(vectors: np.ndarray) -> np.ndarray:
    """Principal direction (3,) of rotation vectors (m, 3) (sign-free)."""
    return np.linalg.eigh(vectors.T @ vectors)[1][:, -1]


def _one_axis(vectors: np.ndarray) -> bool:
    """Whether ONE_AXIS_FRACTION of the squared rotation (m, 3) is about one axis."""
    scatter = vectors.T @ vectors
    total = float(np.trace(scatter))
    return total > 0 and float(np.linalg.eigvalsh(scatter)[-1]) >= ONE_AXIS_FRACTION * total
