"""The lens search: a division-model warp and a focal length where tensors disagree.

Why. Strong barrel distortion (a 100° lens, an action or drone camera: a fifth to a
third of the radius in the image corners) bends the tracks so far from any pinhole
camera that the projective tensors disagree with each other, and the lens stage
(:mod:`.lens_distortion`), which starts from agreeing tensors, never runs: the run
can only hold the start.

How. Fitzgibbon's one-parameter division model (CVPR 2001),
``x_u = c + (x_d − c) / (1 + λ r²)`` with ``r = |x_d − c| / s`` (``c``: the start's
principal point, ``s``: its distance to the farthest image corner, half the diagonal
for a centred one, so ``r ≤ 1`` in the image), is a warp of the pixels that needs no
focal length and can be undone in closed form for every ``λ > −1`` (barrel
distortion: ``λ < 0``). Fitzgibbon's observation is that only
the right ``λ`` lets straight epipolar geometry explain the matches, whatever the
focal length: for each ``λ`` of :data:`LAMBDAS` every view pair of the first triplets
gets a robust fundamental matrix (OpenCV's USAC) on the warped tracks, and ``λ`` costs
the truncated Sampson errors summed over the pairs (each error scaled back to the
raw pixels by the warp's magnification there). A parabola through the grid's
minimum and its neighbours gives ``λ``; the focal search
(:func:`.focal_search.search_focal`) then runs on the tracks warped with it. The
warp is taken when the unwarped tracks cost :data:`CLEAR_RATIO` times more.

The warp only lets the tensors and the solve see nearly pinhole tracks: the camera's
own model (``SIMPLE_RADIAL`` k, ``RADIAL`` k1 k2, ``OPENCV`` k1 k2 p1 p2) is adjusted
afterwards from the raw tracks (:mod:`.lens_distortion`), started from the warp's
least-squares polynomial at the estimated focal length (:func:`polynomial_start`).
Pixels in COLMAP's convention (the centre of the top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..common.parallel import map_jobs
from ..common.sampling import evenly_spaced
from .focal_search import FocalSearchResult, search_focal

#: Division parameters searched: pincushion (+0.2) to a strong barrel (−0.8: a
#: corner's radius 1 / (1 − 0.8) = 5× shorter than its undistorted one; a 100° lens
#: with k1 = −0.25, k2 = 0.05 is about −0.6 over its tracks).
LAMBDAS = tuple(np.round(np.arange(-0.8, 0.21, 0.1), 2))
#: The unwarped tracks must cost this many times more than the warped ones for the
#: warp to be taken (as the focal search's own :data:`.focal_search.CLEAR_RATIO`).
CLEAR_RATIO = 1.5
#: Tracks per view pair (evenly spaced), RANSAC iterations, inlier threshold (pixels)
#: of the fundamental matrices, and the Sampson distance (pixels) errors are
#: truncated at.
PAIR_TRACKS = 100
PAIR_ITERATIONS = 200
PAIR_THRESHOLD_PX = 1.0
TRUNCATION_PX = 2.0
#: Distorted radii the polynomial is fitted at (evenly spaced out to the farthest track).
FIT_SAMPLES = 64


@dataclass
class LensSearchResult:
    """Outcome of :func:`search_lens`.

    Attributes:
        division: λ of the best warp (0: none).
        centre: (2,) the warp's centre, pixels.
        scale: s, the distance from ``centre`` to the farthest image corner, pixels.
        focal: the focal search on the tracks warped with ``division``.
        lambdas: (m,) every λ evaluated; ``costs`` (m,) the minimum of its focal search.
        ratio: the cost at λ = 0 over the cost at ``division``.
    """

    division: float
    centre: np.ndarray
    scale: float
    focal: FocalSearchResult
    lambdas: np.ndarray
    costs: np.ndarray
    ratio: float

    @property
    def clear(self) -> bool:
        """Whether the warp explains the tracks clearly better than none (whether its
        focal length is decisive or not: the warped tensors decide that)."""
        return self.division != 0.0 and self.ratio >= CLEAR_RATIO

    def candidates(self) -> list[float]:
        """λ to warp with, in order: ``division``, then one grid step either side of
        it, the side whose tracks cost less first (the cost is flat near its minimum,
        and a polynomial lens is only approximately a division one)."""
        step = float(self.lambdas[1] - self.lambdas[0])
        near = [
            round(self.division + side * step, 4)
            for side in (-1.0, 1.0)
            if self.lambdas[0] <= self.division + side * step <= self.lambdas[-1]
        ]
        near.sort(key=lambda d: float(np.interp(d, self.lambdas, self.costs)))
        return [self.division, *near]

    def undistort(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 2) in pixels, warped (:func:`division_undistort`)."""
        return division_undistort(points, self.centre, self.scale, self.division)


def division_undistort(
    points: np.ndarray, centre: np.ndarray, scale: float, division: float
) -> np.ndarray:
    """``c + (x − c) / (1 + λ r²)``, ``r = |x − c| / s``: distorted pixels (..., 2) to
    undistorted ones under the division model (λ = ``division``, s = ``scale``)."""
    offset, denominator = _division(points, centre, scale, division)
    return centre + offset / denominator[..., None]


def _division(
    points: np.ndarray, centre: np.ndarray, scale: float, division: float
) -> tuple[np.ndarray, np.ndarray]:
    """The points' offsets from the centre (..., 2) and the division model's
    ``1 + λ r²`` at each (...,): the warp divides the offset by it, so it magnifies the
    image around the point by its inverse."""
    offset = np.asarray(points, float) - centre
    r2 = np.sum(offset**2, axis=-1) / scale**2
    # Within the image r ≤ 1 (``scale`` reaches its farthest corner) and λ ≥ −0.8 keep
    # the denominator ≥ 0.2; points outside stay finite.
    return offset, np.maximum(1.0 + division * r2, 0.05)


def search_lens(
    tracks: list[np.ndarray],
    start: np.ndarray,
    rng: np.random.Generator,
    threshold_px: float,
    image_size: tuple[int, int],
    workers: int | None = None,
) -> LensSearchResult:
    """The division warp and focal length that best explain the triplets' tracks.

    Args:
        tracks: per triplet, its tracks (3, n, 2), pixels as observed (distorted).
        start: (fx, fy, cx, cy) the search starts from, pixels; the warp is centred
            on its principal point.
        rng: draws the focal search's track subsets.
        threshold_px: the focal search's inlier threshold, pixels.
        image_size: (width, height), pixels.
        workers: threads (None: one per core).
    """
    centre = np.asarray(start[2:4], float)
    corners = np.array([[0.0, 0.0], [image_size[0], 0.0], [0.0, image_size[1]], image_size])
    scale = float(np.max(np.linalg.norm(corners - centre, axis=1)))
    pairs = [
        (x[a][chosen], x[b][chosen])
        for x in tracks
        for chosen in [evenly_spaced(x.shape[1], PAIR_TRACKS)]
        for a, b in ((0, 1), (0, 2), (1, 2))
    ]
    lambdas = np.array(LAMBDAS)
    jobs = [(pairs, centre, scale, float(division)) for division in lambdas]
    costs = np.array(map_jobs(_epipolar_job, jobs, workers))
    best = int(np.argmin(costs))
    division = float(lambdas[best])
    if 0 < best < len(lambdas) - 1:
        division = _parabola_minimum(lambdas[best - 1 : best + 2], costs[best - 1 : best + 2])
    # The grid's own cost where the parabola did not move λ off it.
    cost = (
        costs[best] if division == lambdas[best] else _epipolar_cost(pairs, centre, scale, division)
    )
    warped = [division_undistort(x, centre, scale, division) for x in tracks]
    focal = search_focal(warped, start, rng, threshold_px, workers=workers, image_size=image_size)
    unwarped = float(costs[np.flatnonzero(lambdas == 0.0)[0]])
    return LensSearchResult(
        division=division,
        centre=centre,
        scale=scale,
        focal=focal,
        lambdas=lambdas,
        costs=costs,
        ratio=unwarped / max(cost, 1e-12),
    )


def _epipolar_job(job: tuple) -> float:
    return _epipolar_cost(*job)


def _epipolar_cost(
    pairs: list[tuple[np.ndarray, np.ndarray]], centre: np.ndarray, scale: float, division: float
) -> float:
    """Σ over the view pairs (tracks (n, 2), (n, 2) pixels) of ``min(d², TRUNCATION_PX²)``,
    d the Sampson distance of the warped tracks from their robust fundamental matrix
    (OpenCV USAC), in raw pixels; a pair without one costs the truncation per track."""
    total = 0.0
    for x1, x2 in pairs:
        (offset1, denominator1), (offset2, denominator2) = (
            _division(x, centre, scale, division) for x in (x1, x2)
        )
        u1 = centre + offset1 / denominator1[:, None]
        u2 = centre + offset2 / denominator2[:, None]
        try:
            F, _ = cv2.findFundamentalMat(
                np.ascontiguousarray(u1),
                np.ascontiguousarray(u2),
                cv2.USAC_DEFAULT,
                PAIR_THRESHOLD_PX,
                0.999,
                PAIR_ITERATIONS,
            )
        except cv2.error:  # USAC finds no model on degenerate samples
            F = None
        if F is None or F.shape != (3, 3):
            total += TRUNCATION_PX**2 * len(x1)
            continue
        # The warp magnifies the image by 1 / (1 + λ r²) around each point.
        magnification = 0.5 * (1.0 / denominator1 + 1.0 / denominator2)
        distance2 = sampson_squared(F, u1, u2) / magnification**2
        total += float(np.minimum(distance2, TRUNCATION_PX**2).sum())
    return total


def sampson_squared(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Squared Sampson distances (n,) of matches x1 <-> x2 (n, 2) from ``x2ᵀ F x1 = 0``."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1)
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    numerator = np.sum(h2 * Fx1, axis=1) ** 2
    denominator = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return numerator / np.maximum(denominator, 1e-300)


def _parabola_minimum(x: np.ndarray, y: np.ndarray) -> float:
    """The vertex of the parabola through three points (x sorted), clipped to their
    span; the best point where there are fewer or the curve is not convex."""
    best = float(x[int(np.argmin(y))])
    if len(x) != 3:
        return best
    (x0, x1, x2), (y0, y1, y2) = x, y
    denominator = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / denominator
    b = (x2**2 * (y0 - y1) + x1**2 * (y2 - y0) + x0**2 * (y1 - y2)) / denominator
    if a <= 0:
        return best
    return round(float(np.clip(-b / (2 * a), x0, x2)), 4)


def polynomial_start(
    search: LensSearchResult,
    intrinsics: np.ndarray,
    num_parameters: int,
    max_radius: float,
) -> np.ndarray:
    """The radial polynomial closest to the warp: COLMAP's ``k1[, k2]`` with
    ``x_d = x_u (1 + k1 ρ + k2 ρ²)``, ``ρ = |x_u|²`` in coordinates normalised by the
    focal length of ``intrinsics`` (pixels), least squares over distorted radii up to
    ``max_radius`` pixels; ``num_parameters`` (1 or 2) of them."""
    focal = float(np.sqrt(intrinsics[0] * intrinsics[1]))
    distorted = np.linspace(max_radius / FIT_SAMPLES, max_radius, FIT_SAMPLES)
    undistorted = distorted / (1.0 + search.division * (distorted / search.scale) ** 2)
    rho = (undistorted / focal) ** 2
    design = np.stack([rho**power for power in range(1, num_parameters + 1)], axis=1)
    return np.linalg.lstsq(design, distorted / undistorted - 1.0, rcond=None)[0]
