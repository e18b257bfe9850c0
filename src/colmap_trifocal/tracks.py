"""Three-view tracks from verified pairwise matches, and triplet selection.

A track of the triplet (i, j, k) is a keypoint of image i matched to a keypoint
of j and one of k, where the verified matches of (j, k) also link those two
keypoints: the 3-cycle check removes most mismatches before any tensor is fit.
Triplets are ranked by their number of tracks.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

Pair = tuple[int, int]


@dataclass(frozen=True)
class Triplet:
    """Three images and the keypoint indices of their tracks, (n, 3) int."""

    image_ids: tuple[int, int, int]
    keypoint_indices: np.ndarray


class MatchGraph:
    """Verified matches as keypoint lookup tables, one per ordered image pair."""

    def __init__(self, matches: dict[Pair, np.ndarray], num_keypoints: dict[int, int]):
        """Args:
        matches: (id1, id2) with id1 < id2 -> (m, 2) keypoint indices (id1, id2).
        num_keypoints: image id -> number of keypoints.
        """
        self.num_keypoints = num_keypoints
        self._lookup: dict[Pair, np.ndarray] = {}
        for (a, b), m in matches.items():
            if len(m) == 0:
                continue
            self._lookup[(a, b)] = self._table(m[:, 0], m[:, 1], num_keypoints[a])
            self._lookup[(b, a)] = self._table(m[:, 1], m[:, 0], num_keypoints[b])

    @staticmethod
    def _table(source: np.ndarray, target: np.ndarray, size: int) -> np.ndarray:
        table = np.full(size, -1, dtype=np.int64)
        table[source] = target
        return table

    def neighbours(self) -> dict[int, set[int]]:
        """Image id -> ids it has verified matches with."""
        graph: dict[int, set[int]] = {}
        for a, b in self._lookup:
            graph.setdefault(a, set()).add(b)
        return graph

    def tracks(self, i: int, j: int, k: int) -> np.ndarray:
        """Keypoint indices (n, 3) of the 3-cycle-consistent tracks of (i, j, k)."""
        ij, ik, jk = self._lookup.get((i, j)), self._lookup.get((i, k)), self._lookup.get((j, k))
        if ij is None or ik is None or jk is None:
            return np.empty((0, 3), dtype=np.int64)
        seeds = np.flatnonzero((ij >= 0) & (ik >= 0))
        in_j, in_k = ij[seeds], ik[seeds]
        consistent = jk[in_j] == in_k
        return np.column_stack([seeds[consistent], in_j[consistent], in_k[consistent]])


def select_triplets(
    graph: MatchGraph,
    image_ids: list[int],
    min_tracks: int = 40,
    max_triplets: int | None = 100,
) -> list[Triplet]:
    """Triplets of ``image_ids`` with at least ``min_tracks`` tracks, spread over the images.

    Only triplets whose three pairs all have verified matches are considered. At
    most ``max_triplets`` are returned (None: all, most tracks first), chosen by
    :func:`spread_triplets`.
    """
    neighbours = graph.neighbours()
    allowed = set(image_ids)
    triplets = []
    for i, j in combinations(sorted(allowed), 2):
        if j not in neighbours.get(i, ()):
            continue
        for k in sorted(neighbours[i] & neighbours.get(j, set()) & allowed):
            if k <= j:
                continue
            indices = graph.tracks(i, j, k)
            if len(indices) >= min_tracks:
                triplets.append(Triplet((i, j, k), indices))
    triplets.sort(key=lambda t: -len(t.keypoint_indices))
    if max_triplets is None or len(triplets) <= max_triplets:
        return triplets
    return spread_triplets(triplets, max_triplets)


def spread_triplets(candidates: list[Triplet], count: int) -> list[Triplet]:
    """Greedily pick ``count`` triplets, each maximising ``tracks / (1 + uses)``.

    ``uses`` is how often the triplet's three images already appear among the
    picked ones. Ranking by tracks alone piles the triplets onto a few images
    (measured: when all triplets of an 8-image sequence have equal track counts,
    the top 20 all contain image 1), so their errors share those images' keypoints
    and an image jackknife cannot drop any of them; the discount spreads them over
    the view graph while still preferring well-matched triplets. The first pick is
    the triplet with most tracks. Ties go to the earlier candidate.
    """
    images = sorted({i for t in candidates for i in t.image_ids})
    column = {image: index for index, image in enumerate(images)}
    members = np.array([[column[i] for i in t.image_ids] for t in candidates])
    tracks = np.array([len(t.keypoint_indices) for t in candidates], dtype=float)
    uses = np.zeros(len(images))
    available = np.ones(len(candidates), dtype=bool)
    chosen = []
    for _ in range(min(count, len(candidates))):
        score = np.where(available, tracks / (1.0 + uses[members].sum(axis=1)), -np.inf)
        best = int(np.argmax(score))
        chosen.append(candidates[best])
        available[best] = False
        uses[members[best]] += 1
    return chosen
