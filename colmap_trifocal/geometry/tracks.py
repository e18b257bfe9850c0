"""Three-view tracks from verified pairwise matches, and triplet selection.

A track of the triplet (i, j, k) is a keypoint of image i matched to a keypoint
of j and one of k, where the verified matches of (j, k) also link those two
keypoints: the 3-cycle check removes most mismatches before any tensor is fit.
"Tracks" are pixel coordinates (3, n, 2) (:func:`triplet_points`); the keypoint
indices (n, 3) they come from are a triplet's ``keypoint_indices``
(:meth:`MatchGraph.track_indices`). On a sparse capture, where few tracks close the
3-cycle, a triplet's chained tracks (:meth:`MatchGraph.chained_track_indices`: two of
the three pairs link them, the third does not contradict them) can be used instead.

Selection, bounded for large databases (:func:`select_triplets`):

1. candidates: triangles of the view graph within each image's
   ``NEIGHBOURS_PER_IMAGE`` best-matched neighbours (linear in the number of
   images; every triangle when there are at most that many images), ranked by
   an upper bound on their track count, the smallest of their three pairs'
   match counts;
2. exact tracks for the ``CANDIDATES_PER_TRIPLET · max_triplets`` best-ranked
   candidates and the best of every image; then further candidates, in order
   of their bound, while fewer than that many reach ``min_tracks``;
3. greedy spread over the view graph (:func:`spread_triplets`), weighing each
   candidate by its tracks times their parallax off the dominant plane of its
   widest pair (:func:`parallax_score`), when the keypoints are given.

Sequences (video, driving; :func:`is_sequence`): adjacent frames share most
tracks but barely rotate, and a triplet of them says little about K. There the
candidates are all triangles among each frame's (up to 50) matched neighbours, and they are
ranked and spread by :func:`information_score`, ``sqrt(num_tracks) · motion``, with
``motion`` the smallest of the three pairs' median keypoint displacements
(:func:`pair_motions`): triplets over wider frame gaps and across turns win, as
long as they keep enough tracks.

Memory: keypoint lookup tables (int32, one per ordered pair) are built only for
the pairs of evaluated candidates, and only those candidates' tracks are kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import chain, combinations

import numpy as np
from scipy.stats import spearmanr

from ..common.parallel import MIN_FORKED_JOBS, map_jobs
from .parallax import _parallax_job, parallax_score, triplet_points

Pair = tuple[int, int]

#: Best-matched neighbours of an image among which its candidate triplets are formed.
NEIGHBOURS_PER_IMAGE = 10
#: Exact tracks are computed for this many times ``max_triplets`` best candidates
#: (by their bound) per batch, plus every image's best candidate.
CANDIDATES_PER_TRIPLET = 3
#: Best-matched neighbours of a frame among which sequence triplets are formed (every
#: triangle of a frame's matched neighbours when it has at most this many; bounds the
#: candidates of long exhaustively matched videos to ~1200 per frame).
SEQUENCE_NEIGHBOURS = 50
#: A view graph is a sequence (:func:`is_sequence`) with at least this many images ...
SEQUENCE_MIN_IMAGES = 12
#: ... when 90 % of its matched pairs are at most this share of the images apart.
SEQUENCE_MAX_GAP = 1.0 / 3.0
#: ... or when the match counts of its pairs fall with their distance in id order
#: (Spearman rank correlation at most this).
SEQUENCE_CORRELATION = -0.4


@dataclass(frozen=True)
class Triplet:
    """Three images and the keypoint indices of their tracks, (n, 3) int."""

    image_ids: tuple[int, int, int]
    keypoint_indices: np.ndarray


class MatchGraph:
    """Verified matches of image pairs, with keypoint lookup tables built on demand."""

    def __init__(self, matches: dict[Pair, np.ndarray], num_keypoints: dict[int, int]):
        """Args:
        matches: (id1, id2) with id1 < id2 -> (m, 2) keypoint indices (id1, id2).
        num_keypoints: image id -> number of keypoints.
        """
        self.num_keypoints = num_keypoints
        self._matches = {pair: m for pair, m in matches.items() if len(m)}
        self._tables: dict[Pair, np.ndarray] = {}

    def match_count(self, a: int, b: int) -> int:
        """Verified matches between images a and b (0 if none)."""
        m = self._matches.get((min(a, b), max(a, b)))
        return 0 if m is None else len(m)

    def neighbours(self) -> dict[int, set[int]]:
        """Image id -> ids it has verified matches with."""
        graph: dict[int, set[int]] = {}
        for a, b in self._matches:
            graph.setdefault(a, set()).add(b)
            graph.setdefault(b, set()).add(a)
        return graph

    def _lookup(self, a: int, b: int) -> np.ndarray | None:
        """Keypoint of b matched to each keypoint of a (−1: none), int32; cached."""
        table = self._tables.get((a, b))
        if table is None:
            m = self._matches.get((min(a, b), max(a, b)))
            if m is None:
                return None
            source, target = (m[:, 0], m[:, 1]) if a < b else (m[:, 1], m[:, 0])
            table = np.full(self.num_keypoints[a], -1, dtype=np.int32)
            table[source] = target
            self._tables[(a, b)] = table
        return table

    def track_indices(self, i: int, j: int, k: int) -> np.ndarray:
        """Keypoint indices (n, 3) of the 3-cycle-consistent tracks of (i, j, k)."""
        ij, ik, jk = self._lookup(i, j), self._lookup(i, k), self._lookup(j, k)
        if ij is None or ik is None or jk is None:
            return np.empty((0, 3), dtype=np.int64)
        seeds = np.flatnonzero((ij >= 0) & (ik >= 0))
        in_j, in_k = ij[seeds], ik[seeds]
        consistent = jk[in_j] == in_k
        return np.column_stack([seeds[consistent], in_j[consistent], in_k[consistent]]).astype(
            np.int64
        )

    def chained_track_indices(self, i: int, j: int, k: int) -> np.ndarray:
        """Keypoint indices (n, 3) of the chained tracks of (i, j, k), sorted by row.

        A chained track is linked by the verified matches of two of the three pairs, and
        the third pair's matches do not contradict it (they link neither of its other two
        keypoints elsewhere). Every 3-cycle-consistent track is one. On a sparse capture
        the pairs of a triplet share few matches (each pair's ratio test keeps a
        different subset of the same points): on 30 of NeRF lego's renders 7 triplets
        have 30 or more 3-cycle-consistent tracks and 18 have as many chained ones.
        A keypoint claimed by two chained tracks (possible only where two pairs' matches
        disagree) is dropped with both.
        """
        columns = {i: 0, j: 1, k: 2}
        rows = []
        for centre, a, b in ((i, j, k), (j, i, k), (k, i, j)):
            to_a, to_b = self._lookup(centre, a), self._lookup(centre, b)
            if to_a is None or to_b is None:
                continue
            seeds = np.flatnonzero((to_a >= 0) & (to_b >= 0))
            in_a, in_b = to_a[seeds], to_b[seeds]
            a_to_b, b_to_a = self._lookup(a, b), self._lookup(b, a)
            if a_to_b is not None and b_to_a is not None:
                linked_b, linked_a = a_to_b[in_a], b_to_a[in_b]
                kept = ((linked_b < 0) | (linked_b == in_b)) & ((linked_a < 0) | (linked_a == in_a))
                seeds, in_a, in_b = seeds[kept], in_a[kept], in_b[kept]
            track = np.empty((len(seeds), 3), dtype=np.int64)
            for image, keypoints in ((centre, seeds), (a, in_a), (b, in_b)):
                track[:, columns[image]] = keypoints
            rows.append(track)
        if not rows:
            return np.empty((0, 3), dtype=np.int64)
        tracks = np.unique(np.concatenate(rows), axis=0)
        for view in range(3):
            _, where, count = np.unique(tracks[:, view], return_inverse=True, return_counts=True)
            tracks = tracks[count[where] == 1]
        return tracks


def is_sequence(graph: MatchGraph, image_ids: list[int], min_matches: int = 15) -> bool:
    """Whether the images form a sequence: matches fall off with the distance in image order.

    With at least :data:`SEQUENCE_MIN_IMAGES` images, over the pairs with
    ``min_matches`` verified matches: True when 90 % of them are at most
    ``SEQUENCE_MAX_GAP`` of the images apart in id order (sequential matching), or
    when their match counts fall with that distance (rank correlation at most
    :data:`SEQUENCE_CORRELATION`: exhaustive matching of a video or a drive, where far
    frames still share distant points). Image ids follow the file names, as COLMAP's
    feature extraction assigns them.
    """
    if len(image_ids) < SEQUENCE_MIN_IMAGES:
        return False
    rank = {image: index for index, image in enumerate(sorted(image_ids))}
    neighbours = graph.neighbours()
    pairs = [
        (abs(rank[a] - rank[b]), graph.match_count(a, b))
        for a in rank
        for b in neighbours.get(a, ())
        if b in rank and a < b and graph.match_count(a, b) >= min_matches
    ]
    if len(pairs) < 3:
        return False
    gaps, counts = np.array(pairs, dtype=float).T
    if np.percentile(gaps, 90) <= SEQUENCE_MAX_GAP * len(image_ids):
        return True
    if np.ptp(gaps) == 0 or np.ptp(counts) == 0:  # no order to correlate
        return False
    # Spearman's rank correlation with tied gaps (1, 2, 3, ... frames) at their mean rank.
    correlation = spearmanr(gaps, counts).statistic
    return bool(correlation <= SEQUENCE_CORRELATION)


def pair_motions(
    matches: dict[Pair, np.ndarray], keypoints: dict[int, np.ndarray]
) -> dict[Pair, float]:
    """Median displacement (pixels) of the verified matches of each pair.

    A proxy for how much the view turned or moved sideways between the two images:
    zero for copies of one image, growing with rotation and with parallax.
    """
    motions = {}
    for (a, b), m in matches.items():
        if len(m):
            flow = keypoints[b][m[:, 1], :2] - keypoints[a][m[:, 0], :2]
            motions[(a, b)] = float(np.median(np.linalg.norm(flow, axis=1)))
    return motions


def information_score(
    triple: tuple[int, int, int], num_tracks: int, motions: dict[Pair, float]
) -> float:
    """``sqrt(num_tracks) · min(motion of the three pairs)`` (pixels): many tracks,
    and all views apart."""
    i, j, k = triple
    motion = min(motions.get(p, 0.0) for p in ((i, j), (i, k), (j, k)))
    return float(np.sqrt(num_tracks) * motion)


def select_sequence_triplets(
    graph: MatchGraph,
    image_ids: list[int],
    motions: dict[Pair, float],
    min_tracks: int = 40,
    max_triplets: int = 100,
) -> list[Triplet]:
    """Up to ``max_triplets`` triplets of a sequence, chosen by :func:`information_score`.

    Every triangle among each image's ``SEQUENCE_NEIGHBOURS`` best-matched neighbours
    is a candidate; they are
    ranked by the score of their track bound, exact tracks are computed for the
    ``CANDIDATES_PER_TRIPLET · max_triplets`` best and every image's best, and the
    spread (:func:`spread_triplets`) uses the score of the exact track counts.
    """
    ids, bounds = candidate_triplets(graph, image_ids, SEQUENCE_NEIGHBOURS)
    keep = bounds >= min_tracks
    ids, bounds = [t for t, k in zip(ids, keep, strict=True) if k], bounds[keep]
    scores = np.array([information_score(t, b, motions) for t, b in zip(ids, bounds, strict=True)])
    order = np.argsort(-scores, kind="stable")
    best_of_image: dict[int, int] = {}
    for index in order:
        for image in ids[index]:
            best_of_image.setdefault(image, int(index))
    batch = CANDIDATES_PER_TRIPLET * max_triplets
    chosen = sorted(set(order[:batch].tolist()) | set(best_of_image.values()))
    evaluated = []
    for index in chosen:
        indices = graph.track_indices(*ids[index])
        if len(indices) >= min_tracks:
            evaluated.append(Triplet(ids[index], indices))
    weights = np.array(
        [information_score(t.image_ids, len(t.keypoint_indices), motions) for t in evaluated]
    )
    ranked = np.argsort(-weights, kind="stable")
    return spread_triplets([evaluated[i] for i in ranked], max_triplets, list(weights[ranked]))


def candidate_triplets(
    graph: MatchGraph,
    image_ids: list[int],
    neighbours_per_image: int | None,
    *,
    chained: bool = False,
) -> tuple[list[tuple[int, int, int]], np.ndarray]:
    """Triangles of the view graph among ``image_ids`` and their track bounds.

    With ``neighbours_per_image`` only triangles within some image's that many
    best-matched neighbours (None: all triangles). Returns the sorted id triples
    and the bound, best bound first: the smallest of the three pair match counts, or
    for ``chained`` tracks (:meth:`MatchGraph.chained_track_indices`, each of which
    takes one match of at least two pairs, so one of the two smaller pairs') the
    smaller of half their sum and the sum of the two smallest.
    """
    allowed = set(image_ids)
    adjacent = {i: n & allowed for i, n in graph.neighbours().items() if i in allowed}
    if neighbours_per_image is None:
        close = adjacent
    else:
        close = {
            i: set(sorted(n, key=lambda j: (-graph.match_count(i, j), j))[:neighbours_per_image])
            for i, n in adjacent.items()
        }
    triangles = set()
    for i, near in close.items():
        for j, k in combinations(sorted(near), 2):
            if k in adjacent.get(j, ()):
                triangles.add(tuple(sorted((i, j, k))))
    ordered = sorted(triangles)
    counts = np.array(
        [
            (graph.match_count(i, j), graph.match_count(i, k), graph.match_count(j, k))
            for i, j, k in ordered
        ],
        dtype=np.int64,
    ).reshape(-1, 3)
    if chained:
        ordered_counts = np.sort(counts, axis=1)
        bounds = np.minimum(counts.sum(axis=1) // 2, ordered_counts[:, :2].sum(axis=1))
    else:
        bounds = counts.min(axis=1)
    order = np.argsort(-bounds, kind="stable")
    return [ordered[o] for o in order], bounds[order]


def select_triplets(  # noqa: PLR0913 (the view graph, the bounds, and how tracks are formed and weighed)
    graph: MatchGraph,
    image_ids: list[int],
    min_tracks: int = 40,
    max_triplets: int | None = 100,
    keypoints: dict[int, np.ndarray] | None = None,
    workers: int | None = None,
    seed: int = 0,
    *,
    chained: bool = False,
) -> list[Triplet]:
    """Up to ``max_triplets`` triplets with at least ``min_tracks`` tracks, spread over the images.

    See the module docstring for the steps. ``max_triplets=None`` evaluates every
    triangle of the view graph and returns all that qualify, most tracks first.
    ``chained``: the triplets' tracks are their chained ones
    (:meth:`MatchGraph.chained_track_indices`), not only the 3-cycle-consistent ones.
    With ``keypoints`` (image id -> (m, ≥2) pixels) the spread weighs candidates by
    :func:`parallax_score` instead of their track count (computed over ``workers``
    threads, or forked processes from ``MIN_FORKED_JOBS`` candidates, None: one per
    core; ``seed`` draws the RANSAC samples of the parallax).
    """
    track_indices = graph.chained_track_indices if chained else graph.track_indices
    if max_triplets is None:
        ids, _ = candidate_triplets(graph, image_ids, None, chained=chained)
        triplets = [Triplet(t, track_indices(*t)) for t in ids]
        triplets = [t for t in triplets if len(t.keypoint_indices) >= min_tracks]
        return sorted(triplets, key=lambda t: -len(t.keypoint_indices))
    ids, bounds = candidate_triplets(graph, image_ids, NEIGHBOURS_PER_IMAGE, chained=chained)
    ids = [t for t, bound in zip(ids, bounds, strict=True) if bound >= min_tracks]
    batch = CANDIDATES_PER_TRIPLET * max_triplets
    # The best-bounded candidates and every image's best one (view-graph coverage)
    # first; further candidates, by bound, only while too few qualify.
    best_of_image: dict[int, int] = {}
    for index, triple in enumerate(ids):
        for image in triple:
            best_of_image.setdefault(image, index)
    priority = sorted(set(range(min(batch, len(ids)))) | set(best_of_image.values()))
    taken = set(priority)
    rest = (index for index in range(len(ids)) if index not in taken)
    evaluated: list[Triplet] = []
    for position, index in enumerate(chain(priority, rest)):
        if position >= len(priority) and len(evaluated) >= batch:
            break
        indices = track_indices(*ids[index])
        if len(indices) >= min_tracks:
            evaluated.append(Triplet(ids[index], indices))
    evaluated.sort(key=lambda t: -len(t.keypoint_indices))
    if len(evaluated) <= max_triplets:
        return evaluated
    if keypoints is not None:
        jobs = [(triplet_points(t, keypoints), seed) for t in evaluated]
        parallax = map_jobs(_parallax_job, jobs, workers, processes=len(jobs) >= MIN_FORKED_JOBS)
        weights = np.array(
            [
                parallax_score(len(t.keypoint_indices), p)
                for t, p in zip(evaluated, parallax, strict=True)
            ]
        )
        ranked = np.argsort(-weights, kind="stable")
        return spread_triplets([evaluated[i] for i in ranked], max_triplets, list(weights[ranked]))
    return spread_triplets(evaluated, max_triplets)


def spread_triplets(
    candidates: list[Triplet], count: int, weights: list[float] | None = None
) -> list[Triplet]:
    """Greedily pick ``count`` triplets, each maximising ``num_tracks / (1 + uses)``.

    ``weights`` (one per candidate) replace the track counts when given.

    ``uses`` is how often the triplet's three images already appear among the
    picked ones. Ranking by tracks alone piles the triplets onto a few images (with
    equal track counts, the first candidates all share one image), so their errors
    share those images' keypoints and an image jackknife cannot drop any of them;
    the discount spreads them over the view graph while still preferring
    well-matched triplets. The first pick is the triplet with most tracks. Ties go
    to the earlier candidate.
    """
    images = sorted({i for t in candidates for i in t.image_ids})
    column = {image: index for index, image in enumerate(images)}
    members = np.array([[column[i] for i in t.image_ids] for t in candidates])
    merit = np.array(
        [len(t.keypoint_indices) for t in candidates] if weights is None else weights, dtype=float
    )
    uses = np.zeros(len(images))
    available = np.ones(len(candidates), dtype=bool)
    chosen = []
    for _ in range(min(count, len(candidates))):
        score = np.where(available, merit / (1.0 + uses[members].sum(axis=1)), -np.inf)
        best = int(np.argmax(score))
        chosen.append(candidates[best])
        available[best] = False
        uses[members[best]] += 1
    return chosen
