"""The lens-search route: a method's run again on tracks the lens search warped.

Where most tensors disagree at the first start on a camera whose stored model has
radial distortion but holds none (COLMAP's default ``SIMPLE_RADIAL``), the lens search
(:mod:`.lens_search`) looks for a division-model warp. When it finds one clearly
better than none, the keypoints and tracks are warped with it, the tensors estimated
and solved again from the warp's focal length (one start per warp: the warp, then one
grid step either side), and the lens stage adjusts the stored model's own distortion
from the raw tracks, started from the warp's nearest polynomial. Where the warp is not
clear, its tensors do not agree, or the adjustment does not confirm the distortion, the
unwarped run goes on as it would have. Pixels in COLMAP's convention (the centre of the
top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..common.log import logger
from ..database.cameras import CameraInfo
from .camera_input import CameraInput
from .focal_search import FocalSearchResult
from .lens_distortion import LensStart, distortion_model
from .lens_search import LensSearchResult, polynomial_start, search_lens
from .method_run import Finished, MethodRun
from .start_candidates import first_start
from .tensor_set import TensorEstimator
from .triplet_selection import CameraTracks

#: Radial terms (k1[, k2]) of the stored models the lens search can start, COLMAP's
#: order (they come first among the model's distortion parameters).
RADIAL_PARAMETERS = {"SIMPLE_RADIAL": 1, "RADIAL": 2, "OPENCV": 2}


@dataclass
class Warped:
    """A run on the lens search's warped tracks: its input and tracks (warped), the
    warp's focal search, and what it finished with (the lens stage having adjusted the
    stored model's distortion from the raw tracks)."""

    data: CameraInput
    tracks: CameraTracks
    search: FocalSearchResult
    finished: Finished


def lens_search_applies(run: MethodRun) -> bool:
    """Whether the lens search may run: the polished variant, a focal search, and a
    stored model with radial distortion that holds none yet (a pinhole stays pinhole)."""
    camera, options = run.data.camera, run.options
    return (
        run.method == "msac-opt"
        and options.triplet_bundle
        and options.focal_search
        and distortion_model(camera) == camera.model
        and camera.model in RADIAL_PARAMETERS
    )


def through_lens_search(run: MethodRun) -> tuple[Warped | None, int]:
    """The run on the lens search's warped tracks, and the refinement starts it spent;
    None where the search finds no clear warp, the tensors agree on none of its warps
    (:meth:`.LensSearchResult.candidates`), or the lens stage does not confirm the
    distortion."""
    data, tracks, options = run.data, run.tracks, run.options
    camera = data.camera
    rng = np.random.default_rng(
        np.random.SeedSequence(options.seed, spawn_key=(len(tracks.triplets) + 1,))
    )
    with run.clock("lens_search"):
        found = search_lens(
            tracks.tracks[: options.search_triplets],
            data.prior,
            rng,
            options.tensor.inlier_threshold_px,
            (camera.width, camera.height),
            options.workers,
        )
    logger.info(
        "camera %d: lens search: division %.2f, %.1f px (the unwarped tracks cost %.1fx; %s)",
        camera.camera_id,
        found.division,
        found.focal.focal,
        found.ratio,
        "used" if found.clear else "not clear: not used",
    )
    if not found.clear:
        return None, 0
    spent = 0
    for division in found.candidates():
        warp = replace(found, division=division)
        keypoints = {image: warp.undistort(k) for image, k in data.keypoints.items()}
        warped = CameraTracks(
            tracks.triplets, [warp.undistort(x) for x in tracks.tracks], tracks.sequence
        )
        warped_run = replace(
            run,
            data=CameraInput(camera, data.prior, keypoints, data.matches),
            tracks=warped,
            estimator=TensorEstimator(warped, camera.camera_id, options, run.estimator.seeds),
        )
        # One start per warp: where its tensors do not agree, the next warp, then the
        # unwarped run as it would have gone on.
        best = warped_run.attempt(first_start(data.prior, warp.focal))
        spent += warped_run.estimator.starts_used
        if not warped_run.nothing_agrees(best):
            break
        logger.info(
            "camera %d: %d of %d tensors agree on the tracks warped with division %.2f",
            camera.camera_id,
            best.agreeing,
            len(best.tensors.tensors),
            division,
        )
    else:
        return None, spent
    raw = tracks.by_images()
    finished = warped_run.finish(
        best, lambda intrinsics: LensStart(raw, distortion_start(camera, warp, raw, intrinsics))
    )
    if finished.lens is None or not finished.lens.present:
        logger.info(
            "camera %d: the lens adjustment did not confirm the warp: not used", camera.camera_id
        )
        return None, spent
    return Warped(warped_run.data, warped, warp.focal, finished), spent


def distortion_start(
    camera: CameraInfo,
    warp: LensSearchResult,
    raw: dict[tuple[int, int, int], np.ndarray],
    intrinsics: np.ndarray,
) -> np.ndarray:
    """The stored model's distortion (COLMAP's order) nearest the warp at ``intrinsics``
    (pixels): its radial terms fitted out to the farthest raw track, the rest 0."""
    farthest = max(float(np.max(np.linalg.norm(x - warp.centre, axis=-1))) for x in raw.values())
    radial = polynomial_start(warp, intrinsics, RADIAL_PARAMETERS[camera.model], farthest)
    start = np.zeros(len(camera.distortion))
    start[: len(radial)] = radial
    return start
