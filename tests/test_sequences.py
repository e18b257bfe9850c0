"""Sequences (issue 13, item 3): triplets over wide frame gaps and across turns."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_trifocal import CalibrationOptions, calibrate_contents
from colmap_trifocal.geometry.tracks import (
    MatchGraph,
    is_sequence,
    pair_motions,
    select_sequence_triplets,
    select_triplets,
)
from colmap_trifocal.synthetic.database import scene_contents
from colmap_trifocal.synthetic.driving import driving_sequence
from colmap_trifocal.synthetic.facade import facade_scene
from colmap_trifocal.synthetic.motions import general_motion


@pytest.fixture(scope="module")
def turning_drive():
    """30 frames 1 m apart, KITTI camera, a 90° right turn midway."""
    scene = driving_sequence(num_images=30, turn_deg=90.0, num_points=3000, seed=1)
    return scene, scene_contents(scene)


def graph_of(contents) -> tuple[MatchGraph, list[int]]:
    graph = MatchGraph(contents.matches, {i: len(k) for i, k in contents.keypoints.items()})
    return graph, sorted(contents.keypoints)


def rotation_angle_deg(scene, views: tuple[int, ...]) -> float:
    """Largest rotation between two of the views (database ids, 1-based), degrees."""
    R = scene.rotations[[v - 1 for v in views]]
    angles = [
        np.degrees(np.arccos(np.clip((np.trace(R[a] @ R[b].T) - 1.0) / 2.0, -1.0, 1.0)))
        for a in range(len(R))
        for b in range(a + 1, len(R))
    ]
    return float(max(angles))


def test_sequences_are_detected_from_the_view_graph(turning_drive) -> None:
    _, contents = turning_drive
    assert is_sequence(*graph_of(contents))
    straight = scene_contents(driving_sequence(num_images=30, num_points=5000, seed=2))
    assert is_sequence(*graph_of(straight))
    for unordered in (
        scene_contents(general_motion(num_images=16)),
        scene_contents(facade_scene()),
    ):
        assert not is_sequence(*graph_of(unordered))


def test_sequence_triplets_span_wider_gaps_and_the_turn(turning_drive) -> None:
    scene, contents = turning_drive
    graph, ids = graph_of(contents)
    by_tracks = select_triplets(graph, ids, 40, 20)
    by_information = select_sequence_triplets(
        graph, ids, pair_motions(contents.matches, contents.keypoints), 40, 20
    )
    assert len(by_information) == 20
    assert all(len(t.keypoint_indices) >= 40 for t in by_information)
    gap_tracks = np.median([max(t.image_ids) - min(t.image_ids) for t in by_tracks])
    gap_information = np.median([max(t.image_ids) - min(t.image_ids) for t in by_information])
    assert gap_information >= 2 * gap_tracks, (gap_tracks, gap_information)
    turn_tracks = np.median([rotation_angle_deg(scene, t.image_ids) for t in by_tracks])
    turn_information = np.median([rotation_angle_deg(scene, t.image_ids) for t in by_information])
    assert turn_information >= 2 * turn_tracks, (turn_tracks, turn_information)


def test_sequence_selection_improves_the_calibration(turning_drive) -> None:
    """Same drive and prior: the wide triplets give a smaller error and a smaller std.

    20 triplets, the default, seeds 0–2 (the general selection's parallax ranking
    draws its RANSAC samples from the seed, and one seed decides little: seed 0 alone
    gives the general selection 0.03 % against the sequence's 0.04 %). Measured over
    seeds 0–4: fx error 0.068 % (sequence) against 0.103 % (general), fx std 0.89
    against 1.08 px.
    """
    scene, contents = turning_drive
    truth = scene.intrinsics
    prior = tuple(truth * (1.0 + 0.05 * np.array([1.0, -1.0, 1.0, -1.0])))
    errors: dict[bool, list[float]] = {False: [], True: []}
    stds: dict[bool, list[float]] = {False: [], True: []}
    for seed in range(3):
        for sequence in (False, True):
            options = CalibrationOptions(prior=prior, seed=seed, workers=1, sequence=sequence)
            (result,) = calibrate_contents(contents, options)
            if sequence:
                # Yaw only: fy is tied to fx (planar motion), and the report says so.
                assert not result.observable["fy"] and result.observable["fx"]
            errors[sequence].append(abs(result.fx / truth[0] - 1.0))
            stds[sequence].append(result.std["fx"])
    assert np.mean(errors[True]) < np.mean(errors[False]), errors
    assert max(errors[True]) < 0.005
    assert np.mean(stds[True]) < np.mean(stds[False]), stds
