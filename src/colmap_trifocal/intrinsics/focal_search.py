"""A starting focal length from calibrated three-view hypotheses (no prior needed).

Why. Tensors are estimated in coordinates normalised by a starting K, and on
near-planar triplets the hypothesis that wins MSAC is the calibrated one (the
5-point essential matrix and PnP, :func:`.tensor_estimation.calibrated_hypothesis`),
which needs a roughly right K. Measured on fountain-P11 from COLMAP's default
camera (f = 1.2 · max(width, height), 33 % too long there): that hypothesis
fails, the linear 7-point ones win, and the bundle adjustment ends in
plane-dominated local minima on half the triplets (3126 instead of 3986 inliers
on the best one), so only 10 of 30 tensors were MSAC inliers and the tensor
stage took 4× longer.

How. The fit of the calibrated hypothesis is sharply best at the true focal
length. For each candidate ``f = factor · f0`` on a log-spaced grid (0.5–2×, 13
steps of 12 %), with square pixels and the starting principal point, the cost
of a triplet is the mean truncated squared transfer error of its calibrated
hypothesis (pixels², on a random subset of its tracks); costs are summed over
the first selected triplets and the grid minimum is refined by a parabola in
log f. Measured on both Strecha scenes from the default camera: focal length
within 1–4 % of the truth (3 seeds), enough for the tensor stage to behave as from a
±5 % prior. Candidates below the grid's 12 % spacing are not resolved here;
the constraint solver does that.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..common.parallel import map_jobs
from ..geometry.tensor_estimation import calibrated_hypothesis, transfer_errors
from ..geometry.trifocal import intrinsics_matrix

#: Candidate focal lengths relative to the start (12 % apart).
SEARCH_FACTORS = np.geomspace(0.5, 2.0, 13)


@dataclass
class FocalSearchResult:
    """Outcome of :func:`search_focal`."""

    focal: float  # pixels, used for fx and fy
    factors: np.ndarray  # (m,) candidates relative to the starting focal length
    costs: np.ndarray  # (m,) summed cost per candidate (pixels²)


def hypothesis_costs(
    tracks_px: np.ndarray,
    focals: np.ndarray,
    principal_point: np.ndarray,
    threshold_px: float,
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
        cameras = calibrated_hypothesis(x, threshold_px / focal)
        if cameras is not None:
            errors = transfer_errors(x, *cameras, np.array([focal, focal]))
            costs[index] = np.minimum(errors, threshold2).mean()
    return costs


def _costs_job(job: tuple) -> np.ndarray:
    return hypothesis_costs(*job)


def search_focal(
    tracks: list[np.ndarray],
    start: np.ndarray,
    rng: np.random.Generator,
    threshold_px: float = 4.0,
    max_tracks: int = 300,
    workers: int | None = None,
    progress: bool = False,
) -> FocalSearchResult:
    """Search the focal length that best explains the triplets' tracks.

    Args:
        tracks: per triplet, undistorted pixel tracks (3, n, 2).
        start: starting (fx, fy, cx, cy) in pixels; the grid is centred on
            sqrt(fx · fy) and the principal point kept.
        rng: draws the track subsets (reproducible for a seeded generator).
        threshold_px: inlier threshold of the hypotheses, pixels.
        max_tracks: tracks per triplet used (a random subset).
        workers: processes (None: one per core).
        progress: show a progress bar.
    """
    focal0 = float(np.sqrt(start[0] * start[1]))
    focals = focal0 * SEARCH_FACTORS
    jobs = []
    for x in tracks:
        n = x.shape[1]
        subset = np.sort(rng.choice(n, size=min(n, max_tracks), replace=False))
        jobs.append((x[:, subset], focals, np.asarray(start[2:4], float), threshold_px))
    costs = np.sum(map_jobs(_costs_job, jobs, workers, "focal search", progress), axis=0)
    return FocalSearchResult(
        focal=focal0 * _parabola_minimum(SEARCH_FACTORS, costs),
        factors=SEARCH_FACTORS.copy(),
        costs=costs,
    )


def _parabola_minimum(factors: np.ndarray, costs: np.ndarray) -> float:
    """Minimum of the parabola in log(factor) through the best grid point and its neighbours."""
    best = int(np.argmin(costs))
    if best == 0 or best == len(costs) - 1:
        return float(factors[best])
    before, centre, after = costs[best - 1 : best + 2]
    curvature = before - 2 * centre + after
    offset = 0.5 * (before - after) / curvature if curvature > 0 else 0.0
    step = np.log(factors[best + 1] / factors[best])
    return float(factors[best] * np.exp(np.clip(offset, -0.5, 0.5) * step))
