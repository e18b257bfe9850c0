"""The tracks stage: which image triplets one camera is calibrated from, and their tracks.

A sequence that moves forward (video, driving) takes triplets over wide frame gaps
and across turns (:func:`..geometry.tracks.select_sequence_triplets`); anything else
the general selection spread over the view graph (:func:`..geometry.tracks.select_triplets`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...common.errors import CalibrationError
from ...common.log import logger
from ...geometry.motion import moves_forward
from ...geometry.tracks import (
    MatchGraph,
    Triplet,
    is_sequence,
    pair_motions,
    select_sequence_triplets,
    select_triplets,
)
from ..options import TrackOptions, WorkOptions
from .camera_input import CameraInput


@dataclass
class CameraTracks:
    """The selected triplets of one camera.

    Attributes:
        triplets: the triplets (image ids, keypoint indices of their tracks).
        tracks: per triplet, its tracks (3, n, 2) in undistorted pixels (views 1, 2, 3).
        sequence: whether they were chosen as a sequence's.
    """

    triplets: list[Triplet]
    tracks: list[np.ndarray]
    sequence: bool

    def by_images(self) -> dict[tuple[int, int, int], np.ndarray]:
        """Triplet image ids -> its tracks (3, n, 2), pixels."""
        return {triplet.image_ids: x for triplet, x in zip(self.triplets, self.tracks, strict=True)}


def select_camera_triplets(
    data: CameraInput, image_ids: list[int], options: TrackOptions, work: WorkOptions
) -> CameraTracks:
    """Triplets with at least ``options.min_tracks`` tracks, at most ``options.max_triplets``.

    Raises:
        CalibrationError: no triplet has enough tracks.
    """
    camera = data.camera
    graph = MatchGraph(data.matches, {i: len(k) for i, k in data.keypoints.items()})
    sequence = options.sequence
    if sequence is None:
        sequence = is_sequence(graph, image_ids) and moves_forward(
            data.keypoints, data.matches, data.prior, workers=work.workers
        )
    if sequence:
        logger.info("camera %d: a sequence: triplets over wide gaps and turns", camera.camera_id)
        motions = pair_motions(data.matches, data.keypoints)
        triplets = select_sequence_triplets(
            graph, image_ids, motions, options.min_tracks, options.max_triplets or 100
        )
    else:
        triplets = select_triplets(
            graph,
            image_ids,
            options.min_tracks,
            options.max_triplets,
            keypoints=data.keypoints,
            workers=work.workers,
            seed=work.seed,
        )
    if not triplets:
        raise CalibrationError(
            f"camera {camera.camera_id}: no image triplet with at least {options.min_tracks} "
            "three-view tracks"
        )
    tracks = [
        np.stack(
            [
                data.keypoints[i][triplet.keypoint_indices[:, v]]
                for v, i in enumerate(triplet.image_ids)
            ]
        )
        for triplet in triplets
    ]
    return CameraTracks(triplets, tracks, bool(sequence))
