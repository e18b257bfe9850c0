"""The lens search: a radial warp and a focal length where tensors disagree.

Why. Strong barrel distortion (a 100° lens, an action or drone camera: a fifth to a
third of the radius in the image corners) bends the tracks so far from any pinhole
camera that the projective tensors disagree with each other, and the lens stage
(:mod:`intrinsics.lens.distortion`), which starts from agreeing tensors, never runs: the run
can only hold the start.

How. Two one-parameter warps of the pixels that need no focal length, both with
``r = |x − c| / s`` (``c``: the start's principal point, ``s``: its distance to the
farthest image corner, half the diagonal for a centred one, so ``r ≤ 1`` in the image):

* ``division``: Fitzgibbon's model (CVPR 2001), ``x_u = c + (x_d − c) / (1 + λ r_d²)``,
  undone in closed form for every ``λ > −1``; it holds wide lenses whose polynomial
  needs several terms (a 100° lens);
* ``polynomial``: the radial polynomial COLMAP's models hold,
  ``x_d = c + (x_u − c)(1 + κ r_u²)``, so that COLMAP's ``k1 = κ f² / s²``; undone by
  Newton's method, up to the radius where a barrel polynomial folds
  (``r_u = 1 / √(−3κ)``). A one-parameter division warp leaves pixels of a strong
  polynomial lens in the outer image, which planar scenes' tensors do not survive
  (docs/lenses.md).

Fitzgibbon's observation is that only the right warp lets straight epipolar geometry
explain the matches, whatever the focal length: for each parameter of
:data:`LAMBDAS` and :data:`KAPPAS` every view pair of the first triplets gets a
robust fundamental matrix (OpenCV's USAC) on the warped tracks, and the warp costs the
truncated Sampson errors summed over the pairs (each error scaled back to the raw
pixels by the warp's magnification there). The family with the lower grid minimum is
kept, and a parabola through its minimum and neighbours gives the parameter. The warp
is taken when the unwarped tracks cost :data:`CLEAR_RATIO` times more; only then does
the focal search (:func:`intrinsics.start.focal_search.search_focal`) run on the
tracks warped with it.

The warp only lets the tensors and the solve see nearly pinhole tracks: the camera's
own model (``SIMPLE_RADIAL`` k, ``RADIAL`` k1 k2, ``OPENCV`` k1 k2 p1 p2) is adjusted
afterwards from the raw tracks (:mod:`intrinsics.lens.distortion`), started from the warp's
least-squares polynomial at the estimated focal length (:func:`polynomial_start`).
Pixels in COLMAP's convention (the centre of the top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ...common.parabola import parabola_step
from ...common.parallel import map_jobs
from ...common.sampling import evenly_spaced
from ..start.focal_search import FocalSearchResult, search_focal

#: Division parameters searched: pincushion (+0.2) to a strong barrel (−0.8: a
#: corner's radius 1 / (1 − 0.8) = 5× shorter than its undistorted one; a 100° lens
#: with k1 = −0.25, k2 = 0.05 is about −0.6 over its tracks).
LAMBDAS = tuple(np.round(np.arange(-0.8, 0.21, 0.1), 2))
#: Polynomial parameters searched (κ = k1 s² / f²), barrel only (a pincushion lens is
#: as near a division one): none to a barrel that folds at 0.77 s (−0.25: k1 = −0.4 at
#: a 65° lens, whose s ≈ 0.8 f).
KAPPAS = tuple(np.round(np.arange(-0.25, 0.01, 0.05), 2))
#: The two warp families (see the module).
DIVISION, POLYNOMIAL = "division", "polynomial"
#: The unwarped tracks must cost this many times more than the warped ones for the
#: warp to be taken. Undistorted real scenes whose first tensors disagreed (a ring, a
#: drive) measured 1.01–1.11; real images through a mild lens, 1.2–1.25 for k1 +0.03
#: and −0.02 at 3072×2048 (whose corners move 25 and 16 px), 2–2.5 for −0.04 and −0.06
#: (docs/lenses.md). A warp taken is still only tried: its tensors must agree and the
#: lens stage must confirm the distortion from the raw tracks.
CLEAR_RATIO = 1.2
#: Tracks per view pair (evenly spaced), RANSAC iterations, inlier threshold (pixels)
#: of the fundamental matrices, and the Sampson distance (pixels) errors are
#: truncated at.
PAIR_TRACKS = 200
PAIR_ITERATIONS = 200
PAIR_THRESHOLD_PX = 1.0
TRUNCATION_PX = 2.0
#: Distorted radii the polynomial is fitted at (evenly spaced out to the farthest track).
FIT_SAMPLES = 64
#: The epipolar cost's basin is a few tens of pixels of corner displacement wide, whatever
#: the image size, while the grids' steps are fixed in units of the image: they move the
#: farthest corner by 22 px (κ) and 45 px (λ) at a 752×480 drone frame, but by 92 and
#: 185 px at 3072×2048, where a lens between two grid points misses both basins: a
#: phone-like lens (k1 −0.06: κ −0.027, the corners 50 px in) lay between the grid
#: point 0 and its neighbours, which cost as much as no warp, and the parabola through
#: the three missed it (docs/lenses.md). Where a family's step moves the corner by more
#: than ``COARSE_STEP_PX``, it is halved around the family's best while it still moves
#: it by more than ``FINE_STEP_PX`` (:func:`_finer_minima`). Halving every grid (EuRoC's
#: too) took EuRoC's lens, which one term does not hold, 0.1–0.4 % further.
COARSE_STEP_PX = 50.0
#: ... and the corner displacement (pixels) a step is halved down to.
FINE_STEP_PX = 16.0


@dataclass
class LensSearchResult:
    """Outcome of :func:`search_lens`.

    Attributes:
        family: the warp's family, ``DIVISION`` (λ) or ``POLYNOMIAL`` (κ).
        parameter: the best warp's λ or κ (0: none).
        centre: (2,) the warp's centre, pixels.
        scale: s, the distance from ``centre`` to the farthest image corner, pixels.
        focal: the focal search on the tracks warped with ``parameter``; None where
            the warp is not :attr:`clear` (nothing would use it).
        grid: (m,) every parameter of ``family`` evaluated; ``costs`` (m,) its
            epipolar cost.
        ratio: the cost of the unwarped tracks over the cost at ``parameter``.
        alternative: the other family's best (family, parameter) where it also explains
            the tracks clearly better than none, else None.
    """

    family: str
    parameter: float
    centre: np.ndarray
    scale: float
    focal: FocalSearchResult | None
    grid: np.ndarray
    costs: np.ndarray
    ratio: float
    alternative: tuple[str, float] | None = None

    @property
    def clear(self) -> bool:
        """Whether the warp explains the tracks clearly better than none (whether its
        focal length is decisive or not: the warped tensors decide that)."""
        return self.parameter != 0.0 and self.ratio >= CLEAR_RATIO

    def candidates(self) -> list[tuple[str, float]]:
        """Warps (family, parameter) to try, in order: the best, the other family's
        best (the families differ in shape: a lens with a second radial term is
        nearer a division one, a strong one-term lens a polynomial, and the epipolar
        cost of few view pairs can rank them wrongly), then one grid step either side
        of the best, the side whose tracks cost less first (the cost is flat near
        its minimum), leaving out no warp at all."""
        step = float(self.grid[1] - self.grid[0])
        near = [
            round(self.parameter + side * step, 4)
            for side in (-1.0, 1.0)
            if self.grid[0] <= self.parameter + side * step <= self.grid[-1]
        ]
        # A zero warp is the raw tracks, on which most tensors already disagreed.
        near = [d for d in near if d != 0.0]
        near.sort(key=lambda d: float(np.interp(d, self.grid, self.costs)))
        other = [] if self.alternative is None else [self.alternative]
        return [(self.family, self.parameter), *other, *((self.family, d) for d in near)]

    def undistort(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 2) in pixels, warped (:func:`radial_undistort`)."""
        return radial_undistort(points, self.centre, self.scale, self.family, self.parameter)

    def describe(self) -> str:
        """The warp in words, e.g. ``"division λ = -0.25"``."""
        symbol = "λ" if self.family == DIVISION else "κ"
        return f"{self.family} {symbol} = {self.parameter:.2f}"


def radial_undistort(
    points: np.ndarray, centre: np.ndarray, scale: float, family: str, parameter: float
) -> np.ndarray:
    """Distorted pixels (..., 2) to undistorted ones under a warp of ``family``: the
    division model's ``c + (x − c) / (1 + λ r²)``, ``r = |x − c| / s``, or the
    polynomial's inverse (s = ``scale``)."""
    offset, magnification = _warp(points, centre, scale, family, parameter)
    return np.asarray(centre + offset * magnification[..., None])


#: Newton steps of the polynomial's inverse (quadratic convergence from r_u = r_d).
_NEWTON_STEPS = 12


def _warp(
    points: np.ndarray, centre: np.ndarray, scale: float, family: str, parameter: float
) -> tuple[np.ndarray, np.ndarray]:
    """The points' offsets from the centre (..., 2) and the warp's magnification
    ``|x_u − c| / |x_d − c|`` at each (...,)."""
    if family == DIVISION:
        offset, denominator = _division(points, centre, scale, parameter)
        return offset, 1.0 / denominator
    offset = np.asarray(points, float) - centre
    distorted = np.linalg.norm(offset, axis=-1) / scale
    undistorted = _polynomial_inverse(distorted, parameter)
    with np.errstate(divide="ignore", invalid="ignore"):
        magnification = np.where(distorted > 0, undistorted / distorted, 1.0)
    return offset, magnification


def _polynomial_inverse(distorted: np.ndarray, kappa: float) -> np.ndarray:
    """r_u with ``r_u (1 + κ r_u²) = r_d`` (radii in units of s), by Newton's method
    from r_u = r_d; a barrel polynomial (κ < 0) is inverted up to its fold
    ``1 / √(−3κ)``, beyond which radii stay at the fold (no undistorted point maps
    there: such tracks only cost the truncation)."""
    if kappa == 0.0:
        return distorted.copy()
    fold = 1.0 / np.sqrt(-3.0 * kappa) if kappa < 0 else np.inf
    target = np.minimum(distorted, fold * (1.0 + kappa * fold**2))
    undistorted = np.minimum(target, fold)
    for _ in range(_NEWTON_STEPS):
        value = undistorted * (1.0 + kappa * undistorted**2) - target
        slope = np.maximum(1.0 + 3.0 * kappa * undistorted**2, 1e-6)
        undistorted = np.clip(undistorted - value / slope, 0.0, fold)
    return np.asarray(undistorted)


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
    centre: np.ndarray | None = None,
) -> LensSearchResult:
    """The radial warp and focal length that best explain the triplets' tracks.

    Args:
        tracks: per triplet, its tracks (3, n, 2), pixels as observed (distorted).
        start: (fx, fy, cx, cy) the search starts from, pixels.
        rng: draws the focal search's track subsets.
        threshold_px: the focal search's inlier threshold, pixels.
        image_size: (width, height), pixels.
        workers: threads of the epipolar costs, processes of the focal search (None: one
            per core).
        centre: (2,) the warps' centre, pixels (None: the start's principal point).
    """
    centre = np.asarray(start[2:4] if centre is None else centre, float)
    corners = np.array([[0.0, 0.0], [image_size[0], 0.0], [0.0, image_size[1]], image_size])
    scale = float(np.max(np.linalg.norm(corners - centre, axis=1)))
    pairs = [
        (x[a][chosen], x[b][chosen])
        for x in tracks
        for chosen in [evenly_spaced(x.shape[1], PAIR_TRACKS)]
        for a, b in ((0, 1), (0, 2), (1, 2))
    ]
    grids = {DIVISION: np.array(LAMBDAS), POLYNOMIAL: np.array(KAPPAS)}
    costs, unwarped = _grid_costs(pairs, centre, scale, grids, workers)
    refined = _refined_minima(pairs, centre, scale, grids, costs, workers)
    coarse = {
        family: grid
        for family, grid in grids.items()
        if (grid[1] - grid[0]) * scale > COARSE_STEP_PX
    }
    if coarse:
        finer = _finer_minima(pairs, centre, scale, coarse, costs, workers)
        for family in coarse:
            refined[family] = min(refined[family], finer[family], key=lambda found: found[1])
    family, other = sorted(refined, key=lambda name: refined[name][1])
    (parameter, cost), grid = refined[family], grids[family]
    alternative = None
    if refined[other][0] != 0.0 and unwarped >= CLEAR_RATIO * refined[other][1]:
        alternative = (other, refined[other][0])
    found = LensSearchResult(
        family=family,
        parameter=parameter,
        centre=centre,
        scale=scale,
        focal=None,
        grid=grid,
        costs=costs[family],
        ratio=unwarped / max(cost, 1e-12),
        alternative=alternative,
    )
    if found.clear:
        warped = [found.undistort(x) for x in tracks]
        found.focal = search_focal(
            warped, start, rng, threshold_px, workers=workers, image_size=image_size
        )
    return found


def _grid_costs(
    pairs: list[tuple[np.ndarray, np.ndarray]],
    centre: np.ndarray,
    scale: float,
    grids: dict[str, np.ndarray],
    workers: int | None,
) -> tuple[dict[str, np.ndarray], float]:
    """Each family's epipolar cost on its grid, and the unwarped tracks' cost: λ = 0 and
    κ = 0 are the same (no) warp, evaluated once with the division grid."""
    kappas = [float(value) for value in grids[POLYNOMIAL] if value != 0.0]
    jobs = [(pairs, centre, scale, DIVISION, float(value)) for value in grids[DIVISION]]
    jobs += [(pairs, centre, scale, POLYNOMIAL, value) for value in kappas]
    evaluated = map_jobs(_epipolar_job, jobs, workers)
    costs = {DIVISION: np.array(evaluated[: len(grids[DIVISION])])}
    unwarped = float(costs[DIVISION][np.flatnonzero(grids[DIVISION] == 0.0)[0]])
    by_kappa = dict(zip(kappas, evaluated[len(grids[DIVISION]) :], strict=True))
    costs[POLYNOMIAL] = np.array(
        [by_kappa.get(float(value), unwarped) for value in grids[POLYNOMIAL]]
    )
    return costs, unwarped


def _refined_minima(
    pairs: list[tuple[np.ndarray, np.ndarray]],
    centre: np.ndarray,
    scale: float,
    grids: dict[str, np.ndarray],
    costs: dict[str, np.ndarray],
    workers: int | None,
) -> dict[str, tuple[float, float]]:
    """Each family's best parameter (the parabola through its grid minimum and
    neighbours) and its epipolar cost: the grid's own where the parabola stays on the
    grid, else evaluated (the families' together, over ``workers`` threads)."""
    evaluated: dict[str, dict[float, float]] = {}
    minima = {}
    for family, grid in grids.items():
        best = int(np.argmin(costs[family]))
        parameter = float(grid[best])
        if 0 < best < len(grid) - 1:
            parameter = _parabola_minimum(
                grid[best - 1 : best + 2], costs[family][best - 1 : best + 2]
            )
        minima[family] = parameter
        evaluated[family] = {float(grid[best]): float(costs[family][best])}
    wanted = [(family, value) for family, value in minima.items() if value not in evaluated[family]]
    _evaluate(pairs, centre, scale, wanted, evaluated, workers)
    return {family: (value, evaluated[family][value]) for family, value in minima.items()}


def _finer_minima(
    pairs: list[tuple[np.ndarray, np.ndarray]],
    centre: np.ndarray,
    scale: float,
    grids: dict[str, np.ndarray],
    costs: dict[str, np.ndarray],
    workers: int | None,
) -> dict[str, tuple[float, float]]:
    """Each family of ``grids``' best parameter and its epipolar cost, by halving its grid
    step around its grid minimum (within the grid) while a step moves the farthest image
    corner (``scale`` pixels from the centre) by more than ``FINE_STEP_PX``; the last
    three points' parabola gives the parameter. The families' points of a level are
    evaluated together, over ``workers`` threads (None: one per core)."""
    evaluated = {
        family: dict(zip(map(float, grid), map(float, costs[family]), strict=True))
        for family, grid in grids.items()
    }
    best = {family: min(evaluated[family], key=evaluated[family].__getitem__) for family in grids}
    half = {family: float(grid[1] - grid[0]) / 2 for family, grid in grids.items()}
    while True:
        levels = [family for family in grids if half[family] * scale > FINE_STEP_PX]
        if not levels:
            break
        wanted = [
            (family, round(best[family] + side * half[family], 6))
            for family in levels
            for side in (-1.0, 1.0)
        ]
        wanted = [
            (family, value)
            for family, value in wanted
            if grids[family][0] <= value <= grids[family][-1] and value not in evaluated[family]
        ]
        _evaluate(pairs, centre, scale, wanted, evaluated, workers)
        for family in levels:
            best[family] = min(evaluated[family], key=evaluated[family].__getitem__)
            half[family] /= 2
    minima = {}
    for family in grids:
        centre_value, step = best[family], 2 * half[family]
        around = [round(centre_value + side * step, 6) for side in (-1.0, 0.0, 1.0)]
        minima[family] = centre_value
        if all(value in evaluated[family] for value in around):
            minima[family] = _parabola_minimum(
                np.array(around), np.array([evaluated[family][value] for value in around])
            )
    wanted = [(family, value) for family, value in minima.items() if value not in evaluated[family]]
    _evaluate(pairs, centre, scale, wanted, evaluated, workers)
    return {family: (value, evaluated[family][value]) for family, value in minima.items()}


def _evaluate(
    pairs: list[tuple[np.ndarray, np.ndarray]],
    centre: np.ndarray,
    scale: float,
    wanted: list[tuple[str, float]],
    evaluated: dict[str, dict[float, float]],
    workers: int | None,
) -> None:
    """The epipolar cost of each (family, parameter) of ``wanted`` into ``evaluated``
    (by family, then parameter), over ``workers`` threads (None: one per core)."""
    jobs = [(pairs, centre, scale, family, value) for family, value in wanted]
    for (family, value), cost in zip(wanted, map_jobs(_epipolar_job, jobs, workers), strict=True):
        evaluated[family][value] = cost


def _epipolar_job(job: tuple[Any, ...]) -> float:
    return _epipolar_cost(*job)


def _epipolar_cost(
    pairs: list[tuple[np.ndarray, np.ndarray]],
    centre: np.ndarray,
    scale: float,
    family: str,
    parameter: float,
) -> float:
    """Σ over the view pairs (tracks (n, 2), (n, 2) pixels) of ``min(d², TRUNCATION_PX²)``,
    d the Sampson distance of the tracks warped by ``family`` with ``parameter`` from
    their robust fundamental matrix (OpenCV's ``USAC_FAST``: LO-RANSAC with a shorter
    local optimisation, as exact here as ``USAC_DEFAULT`` at half its cost), in raw
    pixels; a pair without one costs the truncation per track."""
    total = 0.0
    for x1, x2 in pairs:
        (offset1, magnification1), (offset2, magnification2) = (
            _warp(x, centre, scale, family, parameter) for x in (x1, x2)
        )
        u1 = centre + offset1 * magnification1[:, None]
        u2 = centre + offset2 * magnification2[:, None]
        try:
            F, _ = cv2.findFundamentalMat(
                np.ascontiguousarray(u1),
                np.ascontiguousarray(u2),
                cv2.USAC_FAST,
                PAIR_THRESHOLD_PX,
                0.999,
                PAIR_ITERATIONS,
            )
        except cv2.error:  # USAC finds no model on degenerate samples
            F = None
        if F is None or F.shape != (3, 3):
            total += TRUNCATION_PX**2 * len(x1)
            continue
        # The warp magnifies the image around each point (division: 1 / (1 + λ r²)).
        magnification = 0.5 * (magnification1 + magnification2)
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
    return np.asarray(numerator / np.maximum(denominator, 1e-300))


def _parabola_minimum(x: np.ndarray, y: np.ndarray) -> float:
    """The minimum of the parabola through three evenly spaced points (x sorted),
    clipped to their span and rounded to 4 decimals; the middle point where the curve
    is not convex."""
    step = parabola_step(float(y[0]), float(y[1]), float(y[2]))
    return round(float(np.clip(x[1] + step * (x[2] - x[1]), x[0], x[2])), 4)


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
    offsets = np.stack([distorted, np.zeros_like(distorted)], axis=1)
    _, magnification = _warp(offsets, np.zeros(2), search.scale, search.family, search.parameter)
    undistorted = distorted * magnification
    rho = (undistorted / focal) ** 2
    design = np.stack([rho**power for power in range(1, num_parameters + 1)], axis=1)
    return np.asarray(np.linalg.lstsq(design, distorted / undistorted - 1.0, rcond=None)[0])
