"""The TrifocalCalib paper's synthetic experiment: one run of every method on one scene.

Set-up (paper, section "Experiments - Synthetic Data"): ``num_points`` 3D points
uniformly in a cube centred at the origin, three cameras in general position
facing the origin (:func:`colmap_trifocal.synthetic.scenes.make_scene`), one shared
camera, exact projections plus uniform pixel noise in ``[-n, +n]`` on each
coordinate (n = 0.1, 0.5, 1.0 px in the paper) and a prior whose every parameter
is the truth times ``1 + U(-5 %, +5 %)``. Each run draws one scene and one prior
and calibrates them with

* ``msac-opt``, ``direct`` (and ``msac``): TrifocalCalib through
  :func:`intrinsics.api.calibrate_contents_methods` (the trifocal
  variants of a run share their focal search and tensors);
* ``fundamental``: the Mendonça–Cipolla baseline on F re-fitted from the matches;
* ``ba-floor``: a bundle adjustment of intrinsics, poses and points started from
  the ground truth with the noisy observations (outlier tracks excluded), the
  accuracy a calibration from these observations can hope for.

Conventions
-----------
* Pixels, COLMAP pixel convention: the centre of the top-left pixel is at
  ``(0.5, 0.5)``, so an image spans ``[0, width] x [0, height]``; the synthetic
  observations and the database keypoints use it unchanged.
* Intrinsics are ``(fx, fy, cx, cy)`` in pixels, ``K = [[fx, 0, cx], [0, fy, cy],
  [0, 0, 1]]`` (a COLMAP PINHOLE camera with params ``(fx, fy, cx, cy)``).
* Poses are world-to-camera, ``x_cam = R X + t``.
* Errors are the paper's mean relative error of (fx, fy, cx, cy), in percent
  (:func:`colmap_trifocal.evaluation.records.mean_relative_error_percent`).

Determinism: the scene, the prior and the calibration seed all derive from
``np.random.SeedSequence(seed)``. The noise is drawn last and scales with
``noise_px``, so one seed gives the same points, cameras and prior (and the same
noise pattern, scaled) at every noise level: the noise levels are paired.
"""

from __future__ import annotations

import time

import numpy as np
import pycolmap

from ..common.bundle_adjustment import bundle_adjustment_options
from ..common.errors import CalibrationError
from ..common.log import keep_colmap_quiet
from ..database.snapshot import DatabaseContents
from ..intrinsics.api import METHODS, CalibrationOptions, calibrate_contents_methods
from ..intrinsics.results import PARAMETER_NAMES
from ..reconstruction.mapping import camera_intrinsics
from ..synthetic.database import CAMERA_ID, scene_contents
from ..synthetic.scenes import SyntheticScene, make_scene, perturbed_prior
from .records import RunRecord

EXPERIMENT = "synthetic"
BA_FLOOR = "ba-floor"
#: Methods of the experiment: TrifocalCalib variants, the F baseline and the floor.
SYNTHETIC_METHODS = ("msac-opt", "direct", "fundamental", BA_FLOOR)
#: Noise half-widths of the paper, pixels.
NOISE_LEVELS = (0.1, 0.5, 1.0)
NUM_CAMERAS = 3
_TRIFOCAL_METHODS = tuple(m for m in METHODS if m != "fundamental")
#: Ceres tolerances of the floor's bundle adjustment (tighter than COLMAP's
#: defaults: the floor should be the converged optimum, not an early stop).
_BA_GRADIENT_TOLERANCE = 1e-10
_BA_FUNCTION_TOLERANCE = 1e-12


def perturbation_label(fraction: float) -> str:
    """The record's perturbation range in percent, e.g. ``0.05 -> "0-5"``."""
    return f"0-{fraction * 100.0:g}"


def min_ba_tracks(num_views: int) -> int:
    """Fewest complete tracks for which the floor's bundle adjustment is determined.

    ``2 m n`` residuals against ``4 + 6 m - 7 + 3 n`` unknowns (intrinsics, poses,
    points, minus the 7-dof similarity gauge) for ``n`` tracks seen in ``m`` views.
    """
    return int(np.ceil((6 * num_views - 3) / (2 * num_views - 3)))


def ground_truth_reconstruction(
    scene: SyntheticScene, intrinsics: np.ndarray | None = None
) -> pycolmap.Reconstruction:
    """A pycolmap reconstruction of the scene: true poses and points, noisy observations.

    Args:
        scene: the scene; its outlier tracks are left out.
        intrinsics: (fx, fy, cx, cy) of the PINHOLE camera; default the truth.

    Image ``v + 1`` holds view ``v``; its keypoint ``k`` observes the ``k``-th inlier
    track, which is 3D point ``k + 1``.
    """
    params = scene.intrinsics if intrinsics is None else np.asarray(intrinsics, float)
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(
        pycolmap.Camera(
            camera_id=CAMERA_ID,
            model="PINHOLE",
            width=scene.width,
            height=scene.height,
            params=params.tolist(),
        )
    )
    inliers = np.flatnonzero(~scene.outliers)
    image_ids = range(1, scene.num_cameras + 1)
    for image_id, R, t, xy in zip(
        image_ids, scene.rotations, scene.translations, scene.observations[:, inliers], strict=True
    ):
        image = pycolmap.Image(
            name=f"{image_id:04d}.png",
            keypoints=np.ascontiguousarray(xy, dtype=np.float64),
            camera_id=CAMERA_ID,
            image_id=image_id,
        )
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), np.asarray(t, float))
        reconstruction.add_image_with_trivial_frame(image, pose)
    for k, point in enumerate(scene.points[inliers]):
        track = pycolmap.Track([pycolmap.TrackElement(i, k) for i in image_ids])
        reconstruction.add_point3D(point, track)
    return reconstruction


def _floor_options() -> pycolmap.BundleAdjustmentOptions:
    """Refine focal lengths and principal point (no distortion), one thread, tight."""
    return bundle_adjustment_options(
        function_tolerance=_BA_FUNCTION_TOLERANCE,
        gradient_tolerance=_BA_GRADIENT_TOLERANCE,
        threads=1,  # the runs are parallelised outside
    )


def ba_floor(scene: SyntheticScene, start: np.ndarray | None = None) -> np.ndarray:
    """(fx, fy, cx, cy) refined by bundle adjustment from the ground truth, pixels.

    Intrinsics, poses and points are refined together on the noisy observations of
    the inlier tracks (``scene.outliers`` excluded); COLMAP fixes the gauge (the
    first pose and the scale). With exact observations it returns the truth.

    Args:
        scene: the scene.
        start: starting intrinsics; default the truth (poses and points always are).

    Raises:
        CalibrationError: too few inlier tracks, or a non-finite result.
    """
    num_tracks = int(np.count_nonzero(~scene.outliers))
    needed = min_ba_tracks(scene.num_cameras)
    if num_tracks < needed:
        raise CalibrationError(
            f"bundle adjustment needs at least {needed} inlier tracks, got {num_tracks}"
        )
    reconstruction = ground_truth_reconstruction(scene, start)
    with keep_colmap_quiet():
        pycolmap.bundle_adjustment(reconstruction, _floor_options())
    estimate = camera_intrinsics(reconstruction.cameras[CAMERA_ID])
    if not np.all(np.isfinite(estimate)):
        raise CalibrationError("bundle adjustment gave non-finite intrinsics")
    return estimate


def case_seeds(seed: int) -> tuple[np.random.Generator, np.random.Generator, int]:
    """Generators of the scene and the prior, and the calibration seed, of a run seed."""
    scene_seq, prior_seq, calibration_seq = np.random.SeedSequence(seed).spawn(3)
    calibration_seed = int(calibration_seq.generate_state(1, dtype=np.uint32)[0])
    return np.random.default_rng(scene_seq), np.random.default_rng(prior_seq), calibration_seed


def _reason(exc: CalibrationError) -> str:
    """The one-line reason of a failure."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _std_list(std: dict[str, float | None]) -> list[float | None]:
    """A calibration's standard deviations in (fx, fy, cx, cy) order."""
    values = [std.get(name) for name in PARAMETER_NAMES]
    return [None if value is None else float(value) for value in values]


def _pipeline_records(
    contents: DatabaseContents,
    methods: tuple[str, ...],
    options: CalibrationOptions,
    truth: np.ndarray,
    prior: np.ndarray,
    common: dict,
    extra: dict,
) -> list[RunRecord]:
    """Records of pipeline methods run together (all fail together on CalibrationError).

    ``seconds`` is the pipeline's own per-method time (perf_counter; for trifocal
    variants: the shared focal search and tensors plus that variant's solve); for a
    failure, the time until it.
    """
    clock = time.perf_counter()
    try:
        results = calibrate_contents_methods(contents, options, methods)
    except CalibrationError as exc:
        seconds = time.perf_counter() - clock
        return [
            RunRecord.finished(
                None,
                truth,
                prior,
                method=m,
                seconds=seconds,
                message=_reason(exc),
                extra=dict(extra),
                **common,
            )
            for m in methods
        ]
    records = []
    for method in methods:
        (result,) = results[method]
        method_extra = dict(extra)
        if method == "fundamental":
            # False when the optimiser stopped without converging.
            method_extra["converged"] = all(result.observable.values())
        else:
            method_extra["num_inlier_triplets"] = result.num_inlier_triplets
        records.append(
            RunRecord.finished(
                result.intrinsics,
                truth,
                prior,
                method=method,
                std=_std_list(result.std),
                seconds=result.seconds,
                extra=method_extra,
                **common,
            )
        )
    return records


def _floor_record(
    scene: SyntheticScene, truth: np.ndarray, prior: np.ndarray, common: dict, extra: dict
) -> RunRecord:
    """The ``ba-floor`` record (no standard deviations)."""
    clock = time.perf_counter()
    try:
        estimate, message = ba_floor(scene), ""
    except CalibrationError as exc:
        estimate, message = None, _reason(exc)
    return RunRecord.finished(
        estimate,
        truth,
        prior,
        method=BA_FLOOR,
        seconds=time.perf_counter() - clock,
        message=message,
        extra=dict(extra),
        **common,
    )


def _checked_methods(methods: tuple[str, ...]) -> tuple[str, ...]:
    """``methods`` without repeats, in their order; CalibrationError on an unknown one."""
    known = (*_TRIFOCAL_METHODS, "fundamental", BA_FLOOR)
    methods = tuple(dict.fromkeys(methods))  # drop repeats, keep the order
    unknown = [m for m in methods if m not in known]
    if unknown:
        raise CalibrationError(f"unknown method {unknown[0]!r} (choose from {known})")
    return methods


def run_synthetic_case(
    noise_px: float,
    run: int,
    seed: int,
    methods: tuple[str, ...] = SYNTHETIC_METHODS,
    num_points: int = 500,
    prior_fraction: float = 0.05,
    outlier_ratio: float = 0.0,
) -> list[RunRecord]:
    """One run of the synthetic experiment: one scene, one prior, every method on them.

    Args:
        noise_px: half-width of the uniform keypoint noise, pixels.
        run: run index (recorded only).
        seed: determines the scene, the prior and the calibration (see module docs).
        methods: any of ``msac-opt``, ``msac``, ``direct``, ``fundamental``, ``ba-floor``.
        num_points: tracks (points seen by all three cameras).
        prior_fraction: each prior parameter is the truth times ``1 + U(-f, +f)``.
        outlier_ratio: fraction of tracks with one observation replaced by a random
            pixel (passed to every method; the floor leaves them out).

    Returns:
        One record per method, in the order of ``methods``. A method that raises
        :class:`CalibrationError` gives a record with ``estimate`` None and the
        message; any other exception propagates.

    Raises:
        CalibrationError: an unknown method.
    """
    methods = _checked_methods(methods)
    scene_rng, prior_rng, calibration_seed = case_seeds(seed)
    scene = make_scene(num_points, NUM_CAMERAS, noise_px, outlier_ratio, seed=scene_rng)
    truth = scene.intrinsics
    prior = perturbed_prior(truth, prior_fraction, prior_rng)
    common = dict(
        experiment=EXPERIMENT,
        scene=f"cube-{num_points}",
        run=run,
        seed=seed,
        num_images=NUM_CAMERAS,
        perturbation=perturbation_label(prior_fraction),
        noise_px=float(noise_px),
    )
    extra = {"outlier_ratio": float(outlier_ratio)}
    contents = scene_contents(scene)
    fx, fy, cx, cy = (float(v) for v in prior)
    options = CalibrationOptions(prior=(fx, fy, cx, cy), seed=calibration_seed, workers=1)
    by_method: dict[str, RunRecord] = {}
    trifocal = tuple(m for m in methods if m in _TRIFOCAL_METHODS)
    if trifocal:
        for record in _pipeline_records(contents, trifocal, options, truth, prior, common, extra):
            by_method[record.method] = record
    if "fundamental" in methods:
        (by_method["fundamental"],) = _pipeline_records(
            contents, ("fundamental",), options, truth, prior, common, extra
        )
    if BA_FLOOR in methods:
        by_method[BA_FLOOR] = _floor_record(scene, truth, prior, common, extra)
    return [by_method[m] for m in methods]


def run_synthetic_task(task: tuple) -> list[RunRecord]:
    """:func:`run_synthetic_case` on one task tuple ``(noise_px, run, seed, methods,
    num_points, prior_fraction, outlier_ratio)``: the unit of work sent to the workers."""
    noise, run, seed, methods, points, fraction, outliers = task
    return run_synthetic_case(noise, run, seed, methods, points, fraction, outliers)
