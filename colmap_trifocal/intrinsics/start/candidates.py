"""Where the tensors of one camera are estimated from: the start candidates.

A start K normalises the tensors' coordinates (θ = 0 there). The first start is the
prior with the focal search's focal length when the tracks favour it. When the
estimate lands far from its start, the tensors are estimated once more from the
estimate (a restart). When fewer than half the tensors agree with the estimate,
the focal search's other candidates are tried (other starts). Every start carries
the values undetermined parameters are held at, with their std.

Intrinsics are (fx, fy, cx, cy) in pixels; std relative to the focal length (θ units).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..options import RESTART_THRESHOLD, CalibrationOptions
from ..solve.fallback import FallbackSolution
from ..solve.observability import FALLBACK_FACTOR, default_held_std
from ..solve.theta import focal_scale, fold_focal_sign, theta_to_intrinsics, with_focal
from .focal_search import FocalSearchResult

#: Other starts :func:`other_starts` offers at most (besides the first).
MAX_OTHER_STARTS = 3


@dataclass
class StartCandidate:
    """A start K and the values undetermined parameters are held at from it.

    Attributes:
        start: (fx0, fy0, cx0, cy0), pixels.
        held: (fx, fy, cx, cy) undetermined parameters keep, pixels.
        held_std: (4,) how well ``held`` is known, relative to the focal length.
        held_source: where the held focal length comes from (``prior``, ``focal-search``).
    """

    start: np.ndarray
    held: np.ndarray
    held_std: np.ndarray
    held_source: str


def held_values(
    prior: np.ndarray, search: FocalSearchResult | None
) -> tuple[np.ndarray, np.ndarray, str]:
    """What undetermined parameters are held at: the best estimate the run has.

    The focal search's focal length when the tracks favour it over the prior
    (:attr:`.FocalSearchResult.improves_on_start`; the prior's aspect ratio kept),
    else the prior's, known no better than its disagreement with the search's focal
    length. The principal point is always the prior's.

    Returns:
        (fx, fy, cx, cy) in pixels, their std relative to the focal length (θ
        units; a prior's assumed :func:`intrinsics.solve.observability.default_held_std`), and the
        source of the focal length (``"focal-search"`` or ``"prior"``).
    """
    held = np.asarray(prior, float).copy()
    std = default_held_std()
    if search is None:
        return held, std, "prior"
    if not search.improves_on_start:
        # The search's focal length is not taken, but where it lies far from the
        # prior's, the prior is known no better than that disagreement.
        disagreement = abs(search.focal / np.sqrt(held[0] * held[1]) - 1.0)
        std[:2] = np.maximum(std[:2], disagreement)
        return held, std, "prior"
    held[:2] = with_focal(held, search.focal)[:2]
    std[:2] = search.relative_std
    return held, std, "focal-search"


def first_start(prior: np.ndarray, search: FocalSearchResult | None) -> StartCandidate:
    """The prior, with the focal search's focal length where the tracks favour it."""
    start = np.asarray(prior, float).copy()
    if search is not None and search.favours_focal:
        start[:2] = search.focal
    held, held_std, held_source = held_values(prior, search)
    return StartCandidate(start, held, held_std, held_source)


def other_starts(
    search: FocalSearchResult | None,
    first: StartCandidate,
    start: np.ndarray,
    method: str,
    options: CalibrationOptions,
) -> list[StartCandidate]:
    """Other starts when the tracks reject the first: the focal search's candidates.

    The focal search's focal length, then the other local minima of its coarse cost
    curve (lowest cost first: the weak perspective of a narrow lens can put the
    global minimum 3x off), each more than ``RESTART_THRESHOLD`` from the focal
    lengths tried before (``start``, where the first tensors ended, first), at most
    ``MAX_OTHER_STARTS``; the aspect ratio and principal point of ``start``. Each
    holds ``first``'s held values: an other start is only where the tensors are
    estimated from, and what the tensors leave undetermined stays at the best
    evidence (never at a focal length whose cost the search did not single out).

    None where the search's curve is decisive and the first start was its focal length:
    the evidence favours no other, and tensors that disagree there disagree for another
    reason (a lens the model does not hold, a facade's planes).
    """
    if search is None or not options.restart or method == "direct":
        return []
    first_focal = float(np.sqrt(first.start[0] * first.start[1]))
    if search.decisive and abs(search.focal / first_focal - 1.0) <= RESTART_THRESHOLD:
        return []
    tried = [float(np.sqrt(start[0] * start[1]))]
    candidates = []
    for focal in [search.focal, *search.local_minima()]:
        if all(abs(focal / f - 1.0) > RESTART_THRESHOLD for f in tried):
            tried.append(focal)
            other = with_focal(start, focal)
            candidates.append(StartCandidate(other, first.held, first.held_std, first.held_source))
    return candidates[:MAX_OTHER_STARTS]


def restart_point(fallback: FallbackSolution, start: np.ndarray) -> np.ndarray:
    """Where to re-estimate the tensors from: the unconstrained estimate, where trusted.

    Parameters whose unconstrained std exceeds ``FALLBACK_FACTOR`` tolerances keep
    their start value; an untrusted focal length follows the trusted one with the
    start's aspect ratio (planar motion leaves fy wandering tens of percent away).
    """
    unconstrained = fallback.unconstrained
    estimate = fold_focal_sign(theta_to_intrinsics(unconstrained.theta, start))
    trusted = unconstrained.relative_std < FALLBACK_FACTOR * fallback.tolerances
    point = np.where(trusted, estimate, start)
    if trusted[0] and not trusted[1]:
        point[1] = point[0] * start[1] / start[0]
    elif trusted[1] and not trusted[0]:
        point[0] = point[1] * start[0] / start[1]
    return point


def moved_far(estimate: np.ndarray, start: np.ndarray) -> bool:
    """Whether any parameter moved more than ``RESTART_THRESHOLD`` of the focal length."""
    return bool(np.max(np.abs(estimate - start) / focal_scale(start)) > RESTART_THRESHOLD)
