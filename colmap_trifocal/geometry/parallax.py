"""How much a triplet's tracks stand off the plane that explains most of them.

The view graph's triplets are chosen by what they say about K, and a near-planar
triplet says little: :func:`plane_parallax` is the ``PARALLAX_PERCENTILE`` percentile of
the tracks' distance (pixels) from the dominant homography between the triplet's
outer views (OpenCV RANSAC, ``PLANE_THRESHOLD_PX``), and :func:`parallax_score` weighs
a triplet's track count by it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..common.sampling import evenly_spaced
from .planarity import transfer_distances, uniform_ransac_homography

if TYPE_CHECKING:  # tracks.py chooses triplets by the parallax this module measures
    from .tracks import Triplet

#: RANSAC threshold (pixels) of the dominant-plane homographies of :func:`plane_parallax`.
PLANE_THRESHOLD_PX = 3.0
#: Percentile of the tracks' distances from that plane that :func:`plane_parallax` reports.
PARALLAX_PERCENTILE = 75.0
#: Tracks (evenly spaced) and RANSAC iterations :func:`plane_parallax` uses per pair.
#: The ranking of candidate triplets follows the parallax closely, so fewer of
#: either pick weaker triplets on narrow scenes (docs/accuracy.md).
PARALLAX_MAX_TRACKS = 300


PARALLAX_RANSAC_ITERATIONS = 500


def triplet_points(triplet: Triplet, keypoints: dict[int, np.ndarray]) -> np.ndarray:
    """Pixel coordinates (3, n, 2) of a triplet's tracks."""
    return np.stack(
        [
            keypoints[image][triplet.keypoint_indices[:, view], :2]
            for view, image in enumerate(triplet.image_ids)
        ]
    ).astype(np.float64)


def _parallax_job(job: tuple[np.ndarray, int]) -> float:
    return plane_parallax(*job)


def plane_parallax(points: np.ndarray, seed: int = 0) -> float:
    """Parallax (pixels) of a triplet's tracks off the dominant plane of its widest pair.

    For each of the three view pairs: a plain RANSAC homography
    (:func:`.planarity.uniform_ransac_homography`, threshold :data:`PLANE_THRESHOLD_PX`,
    samples drawn from ``seed``) and the :data:`PARALLAX_PERCENTILE` percentile of the
    tracks' distances from it in the pair's second view; the largest of the three
    (the widest pair: relief parallax grows with the baseline). In a scene spread
    through depth there is no dominant plane, RANSAC's plane holds a few tracks and
    differs from draw to draw, and the value is large for every triplet with a
    baseline. ``points``: (3, n, 2) pixels; at most :data:`PARALLAX_MAX_TRACKS` of
    them are used.
    """
    points = points[:, evenly_spaced(points.shape[1], PARALLAX_MAX_TRACKS)]
    parallax = 0.0
    for a, b in ((0, 1), (0, 2), (1, 2)):
        H, _ = uniform_ransac_homography(
            points[a], points[b], PLANE_THRESHOLD_PX, PARALLAX_RANSAC_ITERATIONS, 0.999, seed
        )
        if H is None:
            continue
        distance = transfer_distances(H, points[a], points[b])
        parallax = max(parallax, float(np.percentile(distance, PARALLAX_PERCENTILE)))
    return parallax


def parallax_score(num_tracks: int, parallax_px: float) -> float:
    """``num_tracks · parallax`` (pixels): the weight of a candidate triplet in the spread.

    A facade triplet says about K what its tracks' parallax off the plane says
    (:func:`plane_parallax`), and that parallax grows with the baseline, so wide
    triplets with fewer tracks beat narrow ones with many (what it gains:
    docs/planar_and_sequences.md).
    """
    return float(num_tracks * parallax_px)
