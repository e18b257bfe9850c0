"""The lens-search route: a method's run again on tracks the lens search warped.

Where most tensors disagree at the first start on a camera whose stored model has
radial distortion but holds none (COLMAP's default ``SIMPLE_RADIAL``), the lens search
(:mod:`.lens_search`) looks for a radial warp (division or polynomial). When it finds
one clearly better than none, the keypoints and tracks are warped with it, the tensors
estimated and solved again from the warp's focal length (one start per warp, in the
order of :meth:`.LensSearchResult.candidates`, until at least ``MIN_AGREEING`` tensors
agree; the starts count in the camera's budget), and the lens stage adjusts the stored
model's own distortion from the raw tracks, started from the warp's nearest
polynomial. Where the warp is not clear, its tensors do not agree, or the adjustment
does not confirm the distortion, the unwarped run goes on; where the raw tracks were
clearly bent, without other focal starts (they cannot make bent tracks agree), and
the diagnosis names the distortion. Pixels in COLMAP's convention (the centre of the
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
from .method_run import Finished, MethodRun, consensus
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


@dataclass
class LensRoute:
    """What the lens-search route gave: the run on its warped tracks (None where not
    used), the refinement starts it spent, and the search (None where it did not run)."""

    warped: Warped | None
    spent: int
    search: LensSearchResult | None

    @property
    def bent(self) -> bool:
        """The search found the raw tracks clearly bent (a warp costs them much less,
        :attr:`.LensSearchResult.clear`)."""
        return self.search is not None and self.search.clear

    def finding(self) -> str | None:
        """The diagnosis where the tracks are bent and no warp was used, else None."""
        if self.search is None or not self.bent or self.warped is not None:
            return None
        return (
            f"unmodelled radial distortion (a {self.search.describe()} warp cuts the raw "
            f"tracks' epipolar error {self.search.ratio:.1f}×, but the tensors agree on "
            "none of the warps: the lens is not a one-parameter lens, or the scene has "
            "too little depth relief for what that leaves)"
        )


def through_lens_search(run: MethodRun) -> LensRoute:
    """The run on the lens search's warped tracks; its ``warped`` None where the search
    finds no clear warp, the tensors agree on none of its warps
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
        "camera %d: lens search: %s, %.1f px (the unwarped tracks cost %.1fx; %s)",
        camera.camera_id,
        found.describe(),
        found.focal.focal,
        found.ratio,
        "used" if found.clear else "not clear: not used",
    )
    if not found.clear:
        return LensRoute(None, 0, found)
    spent = 0
    for family, parameter in found.candidates():
        if not run.estimator.can_afford(spent + len(tracks.triplets)):
            return LensRoute(None, spent, found)
        warp = replace(found, family=family, parameter=parameter)
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
        # unwarped run as it would have gone on. Where they agree, no second starts
        # and no restart: the lens stage adjusts K from the raw tracks, so the warped
        # tensors only choose its triplets and its start.
        best = warped_run.attempt(
            first_start(data.prior, warp.focal), restart=False, complete=False
        )
        if not consensus(best.fallback):
            best = warped_run.restarted(best)
        spent += warped_run.estimator.starts_used
        if consensus(best.fallback):
            break
        logger.info(
            "camera %d: %d of %d tensors agree on the tracks warped with %s",
            camera.camera_id,
            best.agreeing,
            len(best.tensors.tensors),
            warp.describe(),
        )
    else:
        return LensRoute(None, spent, found)
    raw = tracks.by_images()
    finished = warped_run.finish(
        best, lambda intrinsics: LensStart(raw, distortion_start(camera, warp, raw, intrinsics))
    )
    if finished.lens is None or not finished.lens.present:
        logger.info(
            "camera %d: the lens adjustment did not confirm the warp: not used", camera.camera_id
        )
        return LensRoute(None, spent, found)
    return LensRoute(Warped(warped_run.data, warped, warp.focal, finished), spent, found)


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
