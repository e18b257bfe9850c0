"""A starting focal length from calibrated three-view hypotheses (no prior needed).

Why. Tensors are estimated in coordinates normalised by a starting K, and on
near-planar triplets the hypothesis that wins MSAC is the calibrated one (the
5-point essential matrix and PnP, :func:`.tensor_estimation.calibrated_hypothesis`),
which needs a roughly right K. From a focal length far off (COLMAP's default
camera, f = 1.2 · max(width, height), can be a third too long) that hypothesis
fails, the linear 7-point ones win, and the bundle adjustment ends in
plane-dominated local minima: fewer inlier tracks, few tensors that agree, and a
slower tensor stage (docs/accuracy.md, "Why these constants").

How. The fit of the calibrated hypothesis is sharply best at the true focal
length. With square pixels and the starting principal point, the cost of a
triplet at a candidate focal length is the mean truncated squared transfer
error of its calibrated hypothesis (pixels², on a random subset of its tracks),
summed over the first selected triplets. Coarse to fine: a grid over fields of
view of 5°–150° (21 candidates 25 % apart, half the tracks; a 10° telephoto is
4.8× COLMAP's default guess, a 100° lens 0.35×), then 9 candidates over one
coarse step either side of its minimum, refined by a parabola in log f. The
result is within a few percent of the truth, enough for the tensor stage to
behave as from a ±5 % prior.

Evidence, not a guess. The result replaces the start only when the tracks
clearly favour it (:attr:`FocalSearchResult.improves_on_start`); it carries a
std (the standard error of the triplets' own minima, at least 2 %) and whether
its cost curve is decisive. On straight forward motion the curve is flat (every
focal length explains the tracks), and the start is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...common.parabola import parabola_step
from ...common.parallel import map_jobs
from ...geometry.tensor_estimation import transfer_errors
from ...geometry.trifocal import intrinsics_matrix
from ...geometry.triplet_fit import calibrated_hypothesis

#: Fields of view searched, degrees across the longer image side: from a long
#: telephoto (5°, f = 11.4 · max(w, h)) to a fisheye-like wide angle (150°,
#: f = 0.13 · max(w, h)). COLMAP's default guess is 45°.
MIN_FOV_DEG = 5.0
MAX_FOV_DEG = 150.0
#: Ratio between neighbouring focal lengths of the coarse grid (21 candidates over 5°–150°).
COARSE_RATIO = 1.25
#: Candidates of the fine grid, spanning one coarse step either side of the coarse
#: minimum (a ratio of 1.057 between neighbours).
FINE_STEPS = 9
#: RANSAC iterations (PnP, essential matrix) on the coarse grid: far from the focal
#: length few tracks fit and RANSAC runs to its limit; near it, it stops after a few
#: samples anyway.
COARSE_ITERATIONS = (30, 30)
#: ... and on the fine grid and at the start.
FINE_ITERATIONS = (100, 1000)
#: Without an image size: candidates relative to the start, 0.5–2× its focal length.
SEARCH_FACTORS = np.geomspace(0.5, 2.0, 13)
#: The cost curve is decisive when its minimum is interior and the cost one coarse
#: step either side is at least this many times the minimum: far above on general
#: motion, about 1 on straight forward motion, whose calibrated hypotheses fit
#: almost equally well at any focal length.
DECISIVE_CONTRAST = 1.5
#: Floor of the focal search's relative std: the calibrated hypotheses use the
#: start's principal point and square pixels, which biases the minimum by a few
#: percent.
MIN_RELATIVE_STD = 0.02
#: The search's focal length replaces the start's when the start costs at least
#: this many times more and the curve is decisive
#: (:attr:`FocalSearchResult.improves_on_start`). On straight forward motion the
#: cost curve is flat, so a prior is kept there; a start far off costs several
#: times more.
ADOPT_RATIO = 1.2
#: ... and without a decisive curve, when the start costs this many times more.
CLEAR_RATIO = 1.5


@dataclass
class FocalSearchResult:
    """Outcome of :func:`search_focal`.

    Attributes:
        focal: the best focal length, pixels (used for fx and fy).
        factors: (m,) every candidate evaluated, relative to the starting focal length.
        costs: (m,) summed cost per candidate (pixels²).
        relative_std: std of ``focal`` relative to it: the spread of the triplets'
            own minima (their standard error), at least ``MIN_RELATIVE_STD``.
        decisive: whether the cost curve singles out ``focal`` (interior minimum,
            contrast at least ``DECISIVE_CONTRAST``); when not, the images do not
            determine the focal length this way (e.g. straight forward motion).
        contrast: cost one coarse step either side of the minimum over the minimum.
        start_ratio: cost at the starting focal length over the cost at ``focal``
            (1: the start explains the tracks as well as the search's result).
    """

    focal: float
    factors: np.ndarray
    costs: np.ndarray
    relative_std: float = float("inf")
    decisive: bool = False
    contrast: float = 1.0
    start_ratio: float = 1.0
    #: (k,) the coarse grid's focal lengths (pixels) and their summed costs (empty
    #: without an image size): what :meth:`local_minima` reads.
    coarse_focals: np.ndarray = field(default_factory=lambda: np.zeros(0))
    coarse_costs: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def local_minima(self) -> list[float]:
        """Focal lengths (pixels) at the interior local minima of the coarse cost
        curve, lowest cost first: where else the tracks could be explained when the
        curve is not decisive (a narrow lens seen in weak perspective)."""
        costs = self.coarse_costs
        if len(costs) < 3:
            return []
        inner = np.flatnonzero((costs[1:-1] < costs[:-2]) & (costs[1:-1] <= costs[2:])) + 1
        return [float(self.coarse_focals[i]) for i in inner[np.argsort(costs[inner])]]

    @property
    def favours_focal(self) -> bool:
        """Whether the tensors are better estimated from ``focal`` than from the start.

        The start costs ``CLEAR_RATIO`` times more, or ``ADOPT_RATIO`` times more and
        the curve is decisive. Only a linearisation point: what the tensors then agree
        on decides the estimate (:attr:`improves_on_start` decides what is reported).
        """
        return self.start_ratio >= CLEAR_RATIO or self.improves_on_start

    @property
    def improves_on_start(self) -> bool:
        """Whether ``focal`` replaces the start where the tensors leave the focal length
        undetermined: the curve is decisive and the start costs ``ADOPT_RATIO`` times
        more. An indecisive curve never replaces the start (a lens whose distortion is
        not modelled, straight forward motion: the cost prefers a focal length the
        images do not single out)."""
        return self.decisive and self.start_ratio >= ADOPT_RATIO


def hypothesis_costs(
    tracks_px: np.ndarray,
    focals: np.ndarray,
    principal_point: np.ndarray,
    threshold_px: float,
    pnp_iterations: int = 100,
    essential_iterations: int = 1000,
) -> np.ndarray:
    """Cost (m,) of each candidate focal length (m,) for one triplet's tracks (3, n, 2).

    The cost is ``mean(min(e², threshold²))`` over the tracks, e the transfer error
    (pixels, views 2 and 3) of the calibrated hypothesis built with that focal
    length; a candidate without a hypothesis costs ``threshold²``.
    """
    n = tracks_px.shape[1]
    homogeneous = np.concatenate([tracks_px, np.ones((3, n, 1))], axis=2)
    threshold2 = threshold_px**2
    costs = np.full(len(focals), threshold2)
    for index, focal in enumerate(focals):
        K = intrinsics_matrix(np.array([focal, focal, *principal_point]))
        x = (homogeneous @ np.linalg.inv(K).T)[..., :2]
        cameras = calibrated_hypothesis(
            x, threshold_px / focal, pnp_iterations, essential_iterations
        )
        if cameras is not None:
            errors = transfer_errors(x, *cameras, np.array([focal, focal]))
            costs[index] = np.minimum(errors, threshold2).mean()
    return costs


def _costs_job(job: tuple[Any, ...]) -> np.ndarray:
    return hypothesis_costs(*job)


def focal_range(width: int, height: int) -> tuple[float, float]:
    """Smallest and largest focal length searched (pixels): ``MAX_FOV_DEG`` and ``MIN_FOV_DEG``."""
    half_side = 0.5 * max(width, height)
    return (
        half_side / np.tan(np.deg2rad(MAX_FOV_DEG) / 2.0),
        half_side / np.tan(np.deg2rad(MIN_FOV_DEG) / 2.0),
    )


#: Tracks per triplet the fine grid uses (a random subset; the coarse grid half).
MAX_TRACKS = 150


@dataclass(frozen=True)
class _Grid:
    """What every cost evaluation of one search shares: each triplet's track subset
    (3, n, 2) in pixels, the start's principal point, the hypotheses' inlier threshold
    (pixels), and the processes and progress bar of the work."""

    subsets: list[np.ndarray]
    principal_point: np.ndarray
    threshold_px: float
    workers: int | None
    progress: bool

    def costs(
        self, focals: np.ndarray, count: int, iterations: tuple[int, int] = (100, 1000)
    ) -> np.ndarray:
        """(triplets, focals) cost of each candidate focal length on ``count`` tracks.

        One job per triplet, in forked processes (:func:`..common.parallel.map_jobs`):
        OpenCV's RANSACs release the GIL, but the pose recovery, triangulation and
        transfer errors around them are numpy that holds it, and two threads ran the
        search on 1.3–1.6 cores (docs/accuracy.md, thirty-third session)."""
        jobs = [
            (x[:, :count], focals, self.principal_point, self.threshold_px, *iterations)
            for x in self.subsets
        ]
        costs = map_jobs(
            _costs_job,
            jobs,
            self.workers,
            "focal search",
            progress=self.progress,
            processes=True,
        )
        return np.array(costs)


def search_focal(
    tracks: list[np.ndarray],
    start: np.ndarray,
    rng: np.random.Generator,
    threshold_px: float = 4.0,
    workers: int | None = None,
    *,
    progress: bool = False,
    image_size: tuple[int, int] | None = None,
) -> FocalSearchResult:
    """Search the focal length that best explains the triplets' tracks, coarse to fine.

    With ``image_size`` the coarse grid covers fields of view of ``MIN_FOV_DEG`` to
    ``MAX_FOV_DEG`` (ratio ``COARSE_RATIO`` between candidates, half the tracks);
    then a fine grid of ``FINE_STEPS`` candidates spans one coarse step either side
    of the coarse minimum, and its minimum is refined by a parabola in log f.
    Without ``image_size``, one grid of ``SEARCH_FACTORS`` around the start.

    Args:
        tracks: per triplet, undistorted pixel tracks (3, n, 2).
        start: starting (fx, fy, cx, cy) in pixels; the principal point is kept and
            the result is reported relative to sqrt(fx · fy).
        rng: draws the track subsets (``MAX_TRACKS`` per triplet; reproducible for a
            seeded generator).
        threshold_px: inlier threshold of the hypotheses, pixels.
        workers: processes (None: one per core).
        progress: show a progress bar.
        image_size: (width, height) in pixels.
    """
    focal0 = float(np.sqrt(start[0] * start[1]))
    subsets = []
    for x in tracks:
        n = x.shape[1]
        subsets.append(x[:, rng.choice(n, size=min(n, MAX_TRACKS), replace=False)])
    grid = _Grid(subsets, np.asarray(start[2:4], float), threshold_px, workers, progress)
    if image_size is None:
        return _around_start(grid, focal0)
    return _coarse_to_fine(grid, focal0, image_size)


def _around_start(grid: _Grid, focal0: float) -> FocalSearchResult:
    """The search on one grid of ``SEARCH_FACTORS`` around the start's focal length."""
    focals = focal0 * SEARCH_FACTORS
    per_triplet = grid.costs(focals, MAX_TRACKS)
    result = _result(focals, per_triplet, focal0, focals, per_triplet.sum(axis=0))
    costs = per_triplet.sum(axis=0)
    result.start_ratio = float(np.interp(0.0, np.log(SEARCH_FACTORS), costs)) / max(
        float(costs.min()), 1e-12
    )
    return result


def _coarse_to_fine(grid: _Grid, focal0: float, image_size: tuple[int, int]) -> FocalSearchResult:
    """The coarse grid over the fields of view, then the fine grid around its minimum."""
    low, high = focal_range(*image_size)
    coarse = np.geomspace(low, high, int(np.ceil(np.log(high / low) / np.log(COARSE_RATIO))) + 1)
    coarse_costs = grid.costs(coarse, max(MAX_TRACKS // 2, 1), COARSE_ITERATIONS).sum(axis=0)
    best = int(np.argmin(coarse_costs))
    ratio = coarse[1] / coarse[0]
    fine = coarse[best] * ratio ** np.linspace(-1.0, 1.0, FINE_STEPS)
    # The start is costed with the fine grid, in the same call: each focal length's
    # cost is its own (OpenCV's RANSACs seed each call), and a call forks its workers.
    with_start = grid.costs(np.append(fine, focal0), MAX_TRACKS, FINE_ITERATIONS)
    per_triplet, start_cost = with_start[:, :-1], float(with_start[:, -1].sum())
    all_focals = np.concatenate([coarse, fine, [focal0]])
    all_costs = np.concatenate([coarse_costs, per_triplet.sum(axis=0), [start_cost]])
    order = np.argsort(all_focals)
    result = _result(fine, per_triplet, focal0, all_focals[order], all_costs[order])
    result.start_ratio = start_cost / max(float(per_triplet.sum(axis=0).min()), 1e-12)
    result.coarse_focals, result.coarse_costs = coarse, coarse_costs
    if best in (0, len(coarse) - 1):  # the minimum lies at the end of the searched range
        result.decisive = False
    return result


def _result(
    focals: np.ndarray,
    per_triplet: np.ndarray,
    focal0: float,
    all_focals: np.ndarray,
    all_costs: np.ndarray,
) -> FocalSearchResult:
    """The refined minimum of one grid (m,) of per-triplet costs (t, m), its std and contrast."""
    costs = per_triplet.sum(axis=0)
    factors = focals / focals[0]
    focal = float(focals[0] * _parabola_minimum(factors, costs))
    best = int(np.argmin(costs))
    interior = 0 < best < len(costs) - 1
    # Each triplet's own minimum; their spread over sqrt(t) is the standard error.
    minima = np.log([focals[0] * _parabola_minimum(factors, c) for c in per_triplet])
    spread = float(np.std(minima, ddof=1) / np.sqrt(len(minima))) if len(minima) > 1 else 0.0
    relative_std = float(np.hypot(spread, MIN_RELATIVE_STD))
    contrast = min(costs[0], costs[-1]) / max(float(costs[best]), 1e-12)
    return FocalSearchResult(
        focal=focal,
        factors=all_focals / focal0,
        costs=all_costs,
        relative_std=relative_std,
        decisive=bool(interior and contrast >= DECISIVE_CONTRAST),
        contrast=float(contrast),
    )


def _parabola_minimum(factors: np.ndarray, costs: np.ndarray) -> float:
    """Minimum of the parabola in log(factor) through the best grid point and its neighbours."""
    best = int(np.argmin(costs))
    if best == 0 or best == len(costs) - 1:
        return float(factors[best])
    offset = parabola_step(*costs[best - 1 : best + 2])
    step = np.log(factors[best + 1] / factors[best])
    return float(factors[best] * np.exp(np.clip(offset, -0.5, 0.5) * step))
