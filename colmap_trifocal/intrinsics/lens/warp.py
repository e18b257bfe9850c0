"""The lens search's warp applied to a camera's input, and what the route tells.

Where most tensors disagree at the first start on a camera that holds no distortion
(COLMAP's default ``SIMPLE_RADIAL`` with k = 0, or a pinhole camera), the lens search
(:mod:`.search`) looks for a radial warp (division or polynomial). This module says
when the search applies (:func:`lens_search_applies`), runs it with the camera's seed
(:func:`find_warp`), warps the keypoints and tracks with a warp (:func:`warped_input`),
and words the diagnosis where the raw tracks are bent but no warp made the tensors agree
(:func:`bent_tracks_finding`). The pipeline (:mod:`..pipeline`) runs the warped
attempts; the lens stage starts from the warp's nearest polynomial
(:class:`.distortion.LensStart`). Pixels in COLMAP's convention (the centre of the
top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

import numpy as np

from ...common.log import logger
from ...database.cameras import CameraInfo
from ..inputs.camera_input import CameraInput
from ..inputs.triplet_selection import CameraTracks
from ..options import CalibrationOptions
from .distortion import RADIAL_PARAMETERS, distortion_model
from .search import LensSearchResult, search_lens


def lens_search_applies(camera: CameraInfo, method: str, options: CalibrationOptions) -> bool:
    """Whether the lens search may run: the polished variant, a focal search, and a
    stored camera that holds no distortion and whose lens stage fits radial terms (its
    own model, or ``SIMPLE_RADIAL`` / ``OPENCV`` behind a pinhole camera, which stays
    pinhole: K through the lens, no distortion written)."""
    return (
        method == "msac-opt"
        and options.triplet_bundle
        and options.focal_search
        and distortion_model(camera) in RADIAL_PARAMETERS
    )


def find_warp(
    data: CameraInput,
    tracks: CameraTracks,
    options: CalibrationOptions,
    centre: np.ndarray | None = None,
) -> LensSearchResult:
    """The lens search over the first ``options.search_triplets`` triplets, seeded by the
    camera's seed sequence (the key after the triplets' and the focal search's), its
    warps centred on ``centre`` (pixels; None: the start's principal point)."""
    camera = data.camera
    rng = np.random.default_rng(
        np.random.SeedSequence(options.seed, spawn_key=(len(tracks.triplets) + 1,))
    )
    found = search_lens(
        tracks.tracks[: options.search_triplets],
        data.prior,
        rng,
        options.tensor.inlier_threshold_px,
        (camera.width, camera.height),
        options.workers,
        centre,
    )
    logger.info(
        "camera %d: lens search%s: %s%s (the unwarped tracks cost %.1fx; %s)",
        camera.camera_id,
        "" if centre is None else " about the image centre",
        found.describe(),
        "" if found.focal is None else f", {found.focal.focal:.1f} px",
        found.ratio,
        "used" if found.clear else "not clear: not used",
    )
    return found


def warped_input(
    data: CameraInput, tracks: CameraTracks, warp: LensSearchResult
) -> tuple[CameraInput, CameraTracks]:
    """The camera's keypoints and tracks undistorted by ``warp`` (pixels)."""
    keypoints = {image: warp.undistort(k) for image, k in data.keypoints.items()}
    warped = CameraTracks(
        tracks.triplets, [warp.undistort(x) for x in tracks.tracks], tracks.sequence
    )
    return CameraInput(data.camera, data.prior, keypoints, data.matches), warped


def bent_tracks_finding(search: LensSearchResult) -> str:
    """The diagnosis where the raw tracks are bent and no warp was used."""
    return (
        f"unmodelled radial distortion (a {search.describe()} warp cuts the raw "
        f"tracks' epipolar error {search.ratio:.1f}×, but the tensors agree on "
        "none of the warps: the lens is not a one-parameter lens, or the scene has "
        "too little depth relief for what that leaves)"
    )
