"""Three-view tracks from pairwise matches, and the spread of the selected triplets."""

from __future__ import annotations

from collections import Counter
from itertools import combinations

import numpy as np

from colmap_trifocal.geometry.tracks import (
    MatchGraph,
    Triplet,
    candidate_triplets,
    select_triplets,
    spread_triplets,
)


def complete_graph(num_images: int, num_tracks: int) -> MatchGraph:
    """Every keypoint k of every image matched to keypoint k of every other image."""
    identity = np.stack([np.arange(num_tracks)] * 2, axis=1)
    matches = {pair: identity for pair in combinations(range(1, num_images + 1), 2)}
    return MatchGraph(matches, dict.fromkeys(range(1, num_images + 1), num_tracks))


def test_tracks_need_a_consistent_three_cycle() -> None:
    matches = {
        (1, 2): np.array([[0, 0], [1, 1], [2, 2]]),
        (1, 3): np.array([[0, 0], [1, 1], [2, 2]]),
        (2, 3): np.array([[0, 0], [1, 2], [2, 1]]),  # keypoints 1 and 2 swapped
    }
    graph = MatchGraph(matches, {1: 3, 2: 3, 3: 3})
    np.testing.assert_array_equal(graph.track_indices(1, 2, 3), [[0, 0, 0]])
    assert len(graph.track_indices(1, 2, 4)) == 0  # no matches with image 4


def test_chained_tracks_need_two_pairs_and_no_contradiction() -> None:
    matches = {
        (1, 2): np.array([[0, 0], [1, 1], [2, 2], [3, 3], [5, 5]]),
        (1, 3): np.array([[0, 0], [1, 1], [4, 4], [5, 6]]),
        (2, 3): np.array([[0, 0], [2, 2], [4, 4], [5, 5]]),
    }
    graph = MatchGraph(matches, dict.fromkeys((1, 2, 3), 7))
    chained = graph.chained_track_indices(1, 2, 3)
    # 0: every pair links it (a 3-cycle); 1: (1, 2) and (1, 3); 2: (1, 2) and (2, 3);
    # 4: (1, 3) and (2, 3); 3: one pair only; 5: (2, 3) links 5 to keypoint 5, (1, 3) to 6.
    np.testing.assert_array_equal(chained, [[0, 0, 0], [1, 1, 1], [2, 2, 2], [4, 4, 4]])
    cycles = graph.track_indices(1, 2, 3)
    assert {tuple(row) for row in cycles} <= {tuple(row) for row in chained}
    np.testing.assert_array_equal(cycles, [[0, 0, 0]])


def test_chained_tracks_bring_in_triplets_the_three_cycles_miss() -> None:
    """Each pair's matches keep a different two thirds of 60 shared points: no track
    closes the 3-cycle, every one of the 60 is chained."""
    points = np.arange(60)
    keep = {(1, 2): points % 3 != 0, (1, 3): points % 3 != 1, (2, 3): points % 3 != 2}
    matches = {pair: np.stack([points[k], points[k]], axis=1) for pair, k in keep.items()}
    graph = MatchGraph(matches, dict.fromkeys((1, 2, 3), 60))
    assert select_triplets(graph, [1, 2, 3], 30, 20) == []
    (triplet,) = select_triplets(graph, [1, 2, 3], 30, 20, chained=True)
    np.testing.assert_array_equal(triplet.keypoint_indices, np.stack([points] * 3, axis=1))


def test_the_chained_bound_counts_what_two_pairs_can_link() -> None:
    """A chained track takes a match of at least two pairs: with 100, 5 and 5 matches at
    most 10 (half the sum, 55, would let a 30-track threshold evaluate it)."""

    def pairs(counts: dict[tuple[int, int], int]) -> MatchGraph:
        matches = {pair: np.stack([np.arange(n)] * 2, axis=1) for pair, n in counts.items()}
        return MatchGraph(matches, dict.fromkeys((1, 2, 3), 100))

    graph = pairs({(1, 2): 100, (1, 3): 5, (2, 3): 5})
    (_, [bound]) = candidate_triplets(graph, [1, 2, 3], None, chained=True)
    assert bound == 10 >= len(graph.chained_track_indices(1, 2, 3))
    graph = pairs({(1, 2): 40, (1, 3): 40, (2, 3): 40})
    (_, [bound]) = candidate_triplets(graph, [1, 2, 3], None, chained=True)
    assert bound == 60 >= len(graph.chained_track_indices(1, 2, 3)) == 40
    assert candidate_triplets(graph, [1, 2, 3], None)[1].tolist() == [40]


def test_all_triplets_when_under_the_limit() -> None:
    triplets = select_triplets(complete_graph(5, 50), list(range(1, 6)), 40, None)
    assert len(triplets) == 10
    assert all(len(t.keypoint_indices) == 50 for t in triplets)
    assert select_triplets(complete_graph(5, 30), list(range(1, 6)), 40, None) == []


def test_equal_triplets_are_spread_over_the_images() -> None:
    """With equal track counts, ranking alone would take (1,2,3), (1,2,4), ... (all with 1)."""
    triplets = select_triplets(complete_graph(8, 60), list(range(1, 9)), 40, 20)
    assert len(triplets) == 20
    uses = Counter(i for t in triplets for i in t.image_ids)
    assert set(uses) == set(range(1, 9))
    assert max(uses.values()) - min(uses.values()) <= 2
    # Every image can be dropped and triplets remain (what the jackknife needs).
    assert all(any(i not in t.image_ids for t in triplets) for i in range(1, 9))
    assert len({t.image_ids for t in triplets}) == 20


def test_spread_prefers_more_tracks_and_starts_with_the_best() -> None:
    def triplet(ids: tuple[int, int, int], tracks: int) -> Triplet:
        return Triplet(ids, np.zeros((tracks, 3), dtype=np.int64))

    candidates = [
        triplet((1, 2, 3), 1000),
        triplet((1, 2, 4), 900),
        triplet((4, 5, 6), 400),
        triplet((1, 5, 6), 100),
    ]
    chosen = spread_triplets(candidates, 3)
    # (1, 2, 4) reuses two images: 900 / 3 = 300 < 400 of the disjoint (4, 5, 6).
    assert [t.image_ids for t in chosen] == [(1, 2, 3), (4, 5, 6), (1, 2, 4)]
    assert spread_triplets(candidates, 10) == spread_triplets(candidates, 4)
