"""The tracks stage: which image triplets one camera is calibrated from, and their tracks.

A sequence that moves forward (video, driving) takes triplets over wide frame gaps
and across turns (:func:`..geometry.tracks.select_sequence_triplets`); anything else
the general selection spread over the view graph (:func:`..geometry.tracks.select_triplets`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...common.errors import NoEstimate
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
from ..options import DEFAULT_MIN_TRACKS, SPARSE_MIN_TRACKS, TrackOptions, WorkOptions
from .camera_input import CameraInput

#: A sparse capture's triplets (``SPARSE_MIN_TRACKS``) that use fewer than this share of
#: the camera's matched images are replaced by those of chained tracks where these use
#: more. On 30 of NeRF lego's renders 7 triplets use 16 of the 30 images (the chained
#: ones: 20 triplets over 23 images); on the temple ring's 16 views 9 use 15 (the
#: chained ones, 18 over 16, doubled the cost, 0.6 → 1.2 s, and took the error from
#: COLMAP's guess from 0.97 to 1.48 %), on its first 9 views 3 use 7.
CHAINED_COVERAGE = 2.0 / 3.0


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


def _spread_triplets(
    graph: MatchGraph,
    data: CameraInput,
    image_ids: list[int],
    options: TrackOptions,
    work: WorkOptions,
) -> tuple[int, list[Triplet]]:
    """The tracks a triplet needed and the triplets spread over the view graph.

    With ``DEFAULT_MIN_TRACKS`` 3-cycle-consistent tracks; on a sparse capture (fewer
    than ``max_triplets`` triplets have that many; ``min_tracks`` not given) with
    ``SPARSE_MIN_TRACKS``, which brings in more of the images, where that gives more
    triplets. Where the triplets are still fewer than ``max_triplets`` and use less
    than ``CHAINED_COVERAGE`` of the matched images, those with ``SPARSE_MIN_TRACKS``
    chained tracks (:meth:`..geometry.tracks.MatchGraph.chained_track_indices`: two of
    the three pairs link them) replace them where they use more of the images.
    """

    def select(needed: int, *, chained: bool = False) -> list[Triplet]:
        return select_triplets(
            graph,
            image_ids,
            needed,
            options.max_triplets,
            keypoints=data.keypoints,
            workers=work.workers,
            seed=work.seed,
            chained=chained,
        )

    if options.min_tracks is not None:
        return options.min_tracks, select(options.min_tracks)
    triplets = select(DEFAULT_MIN_TRACKS)
    if options.max_triplets is None or len(triplets) >= options.max_triplets:
        return DEFAULT_MIN_TRACKS, triplets
    needed, what = DEFAULT_MIN_TRACKS, "tracks"
    more = select(SPARSE_MIN_TRACKS)
    if len(more) > len(triplets):
        needed, triplets = SPARSE_MIN_TRACKS, more
    matched = set(graph.neighbours()) & set(image_ids)
    used = _images(triplets)
    if len(triplets) < options.max_triplets and len(used) < CHAINED_COVERAGE * len(matched):
        chained = select(SPARSE_MIN_TRACKS, chained=True)
        if len(_images(chained)) > len(used):
            needed, triplets, what = SPARSE_MIN_TRACKS, chained, "chained tracks"
    if not triplets:
        return SPARSE_MIN_TRACKS, triplets
    if needed == SPARSE_MIN_TRACKS:
        logger.info(
            "camera %d: a sparse capture: %d triplets with at least %d %s, over %d of %d images",
            data.camera.camera_id,
            len(triplets),
            SPARSE_MIN_TRACKS,
            what,
            len(_images(triplets)),
            len(matched),
        )
    return needed, triplets


def _images(triplets: list[Triplet]) -> set[int]:
    """The images of ``triplets``."""
    return {image for triplet in triplets for image in triplet.image_ids}


def select_camera_triplets(
    data: CameraInput, image_ids: list[int], options: TrackOptions, work: WorkOptions
) -> CameraTracks:
    """Triplets with enough tracks (``options.min_tracks``), at most ``options.max_triplets``.

    Raises:
        NoEstimate: no triplet has enough tracks.
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
        needed = options.min_tracks or DEFAULT_MIN_TRACKS
        triplets = select_sequence_triplets(
            graph, image_ids, motions, needed, options.max_triplets or 100
        )
    else:
        needed, triplets = _spread_triplets(graph, data, image_ids, options, work)
    if not triplets:
        raise NoEstimate(
            f"camera {camera.camera_id}: no image triplet with at least {needed} three-view tracks"
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
