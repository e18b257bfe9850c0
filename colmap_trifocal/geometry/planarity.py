"""Planar-dominant triplets: the dominant plane of three views, and plane + parallax cameras.

When most tracks of a triplet lie on one plane (a facade), the 7-point tensors
of the MSAC pool fit the plane and a few off-plane points, and the projective
bundle adjustment started from them ends in a local minimum or along a flat
valley far from any calibrated tensor, at a cost above the one reached from the
true cameras (docs/planar_and_sequences.md).

Plane + parallax gives another start (with a dominant plane and a few discrete
relief layers, such as a door, its epipoles are poorly determined, so it is one
start among several, not a replacement). With the homographies
``H2, H3`` of the dominant plane from view 1 to views 2 and 3, every track obeys
``x_j ~ H_j x1 + ρ e_j`` (``ρ``: the track's projective depth off the plane,
``e_j``: the epipole of view 1 in view j), so the cameras ``P2 = [H2 | e2]``,
``P3 = [H3 | μ e3]`` (``P1 = [I | 0]``) explain the plane exactly and the relief
through ``e2, e3`` (each a 2-point RANSAC on the lines through ``x_j`` and
``H_j x1``) and the one scale ``μ`` (ratio of the depths seen in views 2 and 3).

Coordinates are prior-normalised (``x̂ = K0⁻¹ x``, :mod:`.tensor_estimation`);
thresholds are given in those units (pixels / focal length).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: A triplet is planar-dominant when at least this share of its tracks fits the
#: plane's homographies in both views 2 and 3.
PLANAR_SHARE = 0.5
#: 2-point samples of the epipole RANSAC.
EPIPOLE_SAMPLES = 200
#: Off-plane tracks (parallax above 2 thresholds) needed for the epipoles.
MIN_PARALLAX_TRACKS = 8


@dataclass(frozen=True)
class DominantPlane:
    """Homographies of a triplet's dominant plane and the tracks on it."""

    H2: np.ndarray  # (3, 3): view 1 -> view 2
    H3: np.ndarray  # (3, 3): view 1 -> view 3
    on_plane: np.ndarray  # (n,) bool: within the threshold of both homographies
    #: (n,) parallax of each track off the plane, the larger of views 2 and 3
    #: (normalised units).
    parallax: np.ndarray

    @property
    def share(self) -> float:
        """Share of the tracks on the plane (0..1)."""
        return float(self.on_plane.mean()) if len(self.on_plane) else 0.0

    @property
    def planar(self) -> bool:
        """Whether the plane explains at least :data:`PLANAR_SHARE` of the tracks."""
        return self.share >= PLANAR_SHARE


def _homogeneous(points: np.ndarray) -> np.ndarray:
    return np.concatenate([points, np.ones((len(points), 1))], axis=1)


def _transfer(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Inhomogeneous images (n, 2) of points (n, 2) under a homography H."""
    y = _homogeneous(points) @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(y[:, :2] / y[:, 2:3])


def plane_homography(
    x1: np.ndarray,
    x2: np.ndarray,
    threshold: float,
    iterations: int = 2000,
    confidence: float = 0.995,
    method: int = cv2.RANSAC,
) -> tuple[np.ndarray | None, np.ndarray]:
    """The homography (3, 3) most of the points x1 -> x2 (n, 2) fit, and which fit it
    (n,) bool; (None, all False) when OpenCV finds none.

    ``method``: OpenCV's robust estimator, plain RANSAC by default; ``cv2.USAC_DEFAULT``
    (SPRT verification, local optimisation) costs a sixth on 300 tracks and 500
    iterations and finds more inliers, for questions that only need the share of
    tracks on a plane (the diagnosis).

    ``threshold`` is the inlier distance in the points' units; every caller passes the
    one its question needs (pixels for the tracks' parallax and the diagnosis, normalised
    units for the plane + parallax start).
    """
    H, mask = cv2.findHomography(
        np.ascontiguousarray(x1, dtype=np.float64),
        np.ascontiguousarray(x2, dtype=np.float64),
        method,
        threshold,
        maxIters=iterations,
        confidence=confidence,
    )
    if H is None or mask is None:
        return None, np.zeros(len(x1), dtype=bool)
    return H, mask.ravel() > 0


def uniform_ransac_homography(
    x1: np.ndarray,
    x2: np.ndarray,
    threshold: float,
    iterations: int,
    confidence: float,
    seed: int = 0,
) -> tuple[np.ndarray | None, np.ndarray]:
    """Plain RANSAC's homography of x1 -> x2 (n, 2) and its inliers (n,) bool, run by
    OpenCV's USAC framework: uniform 4-point samples, the inlier count as score, no
    local optimisation; then, as ``cv2.findHomography`` does after ``cv2.RANSAC``, a
    least-squares fit with Levenberg–Marquardt refinement on the inliers. ``seed``
    draws the samples. None (and no inliers) where OpenCV finds none.

    The estimator is :func:`plane_homography`'s with ``cv2.RANSAC`` with other random
    samples; USAC's minimal solver and its early exit from counting a sample that
    cannot beat the best make it 1/25 of the cost where the plane holds few of the
    points (the parallax ranking of :mod:`.tracks`, docs/accuracy.md).
    """
    params = cv2.UsacParams()
    params.threshold = threshold
    params.confidence = confidence
    params.maxIterations = iterations
    params.sampler = cv2.SAMPLING_UNIFORM
    params.score = cv2.SCORE_METHOD_RANSAC
    params.loMethod = cv2.LOCAL_OPTIM_NULL
    params.final_polisher = cv2.LSQ_POLISHER
    params.isParallel = False
    params.randomGeneratorState = int(seed) % (2**31)
    try:
        H, mask = cv2.findHomography(
            np.ascontiguousarray(x1, dtype=np.float64),
            np.ascontiguousarray(x2, dtype=np.float64),
            params,
        )
    except cv2.error:
        return None, np.zeros(len(x1), dtype=bool)
    if H is None or mask is None:
        return None, np.zeros(len(x1), dtype=bool)
    inliers = mask.ravel() > 0
    if inliers.sum() > 4:
        refit = cv2.findHomography(
            np.ascontiguousarray(x1[inliers], dtype=np.float64),
            np.ascontiguousarray(x2[inliers], dtype=np.float64),
            0,
        )[0]
        if refit is not None:
            H = refit
    return H, inliers


def transfer_distances(H: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Distances (n,) of points x2 from the images of x1 under H (inf where undefined)."""
    distance = np.linalg.norm(_transfer(H, x1) - x2, axis=1)
    return np.asarray(np.nan_to_num(distance, nan=np.inf))


def dominant_plane(x: np.ndarray, threshold: float) -> DominantPlane | None:
    """The plane most tracks x (3, n, 2) lie on (OpenCV RANSAC homographies 1->2, 1->3).

    The view 1->3 homography is fitted on the view 1->2 inliers, so both belong to
    the same plane. ``threshold``: inlier distance in normalised units. None when
    OpenCV finds no homography.
    """
    x1, x2, x3 = (np.ascontiguousarray(x[view], dtype=np.float64) for view in range(3))
    if len(x1) < 8:
        return None
    H2, first = plane_homography(x1, x2, threshold, confidence=0.999)
    if H2 is None or first.sum() < 4:
        return None
    H3, _ = plane_homography(x1[first], x3[first], threshold)
    if H3 is None:
        return None
    # Relief within the threshold tilts a homography fitted to all inliers; refit
    # both on the tracks closest to the plane (least squares, half the threshold).
    for _ in range(2):
        distance2 = np.linalg.norm(_transfer(H2, x1) - x2, axis=1)
        distance3 = np.linalg.norm(_transfer(H3, x1) - x3, axis=1)
        close = (distance2 < threshold / 2.0) & (distance3 < threshold / 2.0)
        if close.sum() < 8:
            break
        H2 = cv2.findHomography(x1[close], x2[close], 0)[0]
        H3 = cv2.findHomography(x1[close], x3[close], 0)[0]
        if H2 is None or H3 is None:
            return None
    distance2 = np.linalg.norm(_transfer(H2, x1) - x2, axis=1)
    distance3 = np.linalg.norm(_transfer(H3, x1) - x3, axis=1)
    parallax = np.nan_to_num(np.maximum(distance2, distance3), nan=np.inf)
    return DominantPlane(H2, H3, parallax < threshold, parallax)


def _epipole(
    x1: np.ndarray, xj: np.ndarray, H: np.ndarray, threshold: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray] | None:
    """Epipole e (3,) with ``x_j`` on the line through ``H x1`` and e, and its inliers.

    2-point RANSAC (each pair of lines ``x_j × H x1`` meets in a candidate), the
    distance of ``x_j`` to the line through ``H x1`` and the candidate as error,
    then a least-squares fit on the inliers.
    """
    lines = np.cross(_homogeneous(xj), _homogeneous(x1) @ H.T)
    lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True) + 1e-300
    n = len(lines)
    pairs = np.argpartition(rng.random((EPIPOLE_SAMPLES, n)), 2, axis=1)[:, :2]
    candidates = np.cross(lines[pairs[:, 0]], lines[pairs[:, 1]])
    candidates /= np.linalg.norm(candidates, axis=1, keepdims=True) + 1e-300
    errors = _line_distances(x1, xj, H, candidates)
    threshold2 = threshold**2
    scores = np.minimum(errors**2, threshold2).sum(axis=1)
    best = int(np.argmin(scores))
    inliers = errors[best] < threshold
    if inliers.sum() < MIN_PARALLAX_TRACKS // 2:
        return None
    _, _, vt = np.linalg.svd(lines[inliers], full_matrices=False)
    return vt[-1], inliers


def _line_distances(
    x1: np.ndarray, xj: np.ndarray, H: np.ndarray, epipoles: np.ndarray
) -> np.ndarray:
    """Distances (m, n) of x_j to the lines through ``H x1`` and each epipole (m, 3)."""
    y = _homogeneous(x1) @ H.T  # (n, 3)
    lines = np.cross(y[None, :, :], epipoles[:, None, :])  # (m, n, 3)
    norm = np.linalg.norm(lines[..., :2], axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = np.abs(np.einsum("mna,na->mn", lines, _homogeneous(xj))) / norm
    return np.asarray(np.nan_to_num(distance, nan=np.inf))


def _depths(x1: np.ndarray, xj: np.ndarray, H: np.ndarray, e: np.ndarray) -> np.ndarray:
    """ρ (n,) minimising ``|x_j × (H x1 + ρ e)|`` per track (algebraic)."""
    p = _homogeneous(xj)
    c = np.cross(p, _homogeneous(x1) @ H.T)
    d = np.cross(p, np.broadcast_to(e, p.shape))
    return np.asarray(
        -np.einsum("na,na->n", c, d) / np.maximum(np.einsum("na,na->n", d, d), 1e-300)
    )


def plane_parallax_cameras(
    x: np.ndarray, plane: DominantPlane, threshold: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray] | None:
    """Projective cameras ``P2 = [H2 | e2]``, ``P3 = [H3 | μ e3]`` from plane + parallax.

    Args:
        x: prior-normalised tracks (3, n, 2).
        plane: the triplet's dominant plane (:func:`dominant_plane`).
        threshold: inlier distance, normalised units.
        rng: random generator (epipole RANSAC).

    Returns:
        The cameras (3, 4) each, unit Frobenius norm, or None when fewer than
        :data:`MIN_PARALLAX_TRACKS` tracks have parallax or no epipole is found.
    """
    off = np.flatnonzero(np.isfinite(plane.parallax) & (plane.parallax > 2.0 * threshold))
    if len(off) < MIN_PARALLAX_TRACKS:
        return None
    x1, x2, x3 = (x[view][off] for view in range(3))
    found2 = _epipole(x1, x2, plane.H2, threshold, rng)
    found3 = _epipole(x1, x3, plane.H3, threshold, rng)
    if found2 is None or found3 is None:
        return None
    (e2, in2), (e3, in3) = found2, found3
    both = in2 & in3
    if both.sum() < MIN_PARALLAX_TRACKS // 2:
        return None
    rho2 = _depths(x1[both], x2[both], plane.H2, e2)
    rho3 = _depths(x1[both], x3[both], plane.H3, e3)
    # ρ3 = μ ρ2 for every track: the median ratio resists the remaining outliers.
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = rho3 / rho2
    ratios = ratios[np.isfinite(ratios)]
    if len(ratios) == 0:
        return None
    mu = float(np.median(ratios))
    P2 = np.hstack([plane.H2, e2[:, None]])
    P3 = np.hstack([plane.H3, mu * e3[:, None]])
    if not (np.all(np.isfinite(P2)) and np.all(np.isfinite(P3))):
        return None
    return P2 / np.linalg.norm(P2), P3 / np.linalg.norm(P3)
