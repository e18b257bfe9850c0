"""One camera shared by several triplets' calibrated bundle adjustments (pycolmap).

The engine of the polish (:mod:`.bundle`) and of the lens stage
(:mod:`..lens.distortion`): each triplet enters with its calibrated cameras at a
camera K and its tracks triangulated (:mod:`.calibrated_tracks`), as its own three
images and points of one ``pycolmap.Reconstruction`` with one camera. A triplet's
poses and points can be adjusted alone at the shared camera (its likelihood ratio
λ against its projective fit), or several triplets together with the camera free;
their Schur complements on the camera give its information (:mod:`.information`).
Pixels in COLMAP's convention (the centre of the top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Any

import numpy as np
import pycolmap

from ...common.bundle_adjustment import bundle_adjustment_options
from ...common.log import keep_colmap_quiet
from ...common.parallel import MIN_FORKED_JOBS, map_jobs
from ...database.cameras import CameraInfo
from ...geometry.tensor_estimation import TripletTensor
from .calibrated_tracks import (
    MAX_TRACKS,
    Observed,
    calibrated_cameras,
    observed_triplet,
    triangulate,
)
from .camera_setup import NOTHING, Refined
from .information import reduced_information

#: The one camera of the shared reconstruction.
CAMERA_ID = 1
#: Ceres' relative function tolerance of every shared-camera adjustment: it stops once an
#: iteration lowers the cost by a millionth. The cost is about σ² per residual degree of
#: freedom (10³–10⁵ of them), so what is left is a few hundredths of σ² at most, far
#: below what moves an estimate by a fraction of its std. Tighter, a crawl goes on: the
#: lens stage's one-term fit of a lens with k2 (EuRoC) took 56 iterations to 10⁻¹², f
#: within 0.03 std of its end after 20; the facades' adjustments one more iteration
#: each (docs/accuracy.md, twenty-fourth session).
FUNCTION_TOLERANCE = 1e-6
GRADIENT_TOLERANCE = 1e-14


MAX_ITERATIONS = 200
#: Ceres' initial trust region radius (its default is 1e4): the solves here start next
#: to their optimum (each triplet's calibrated fit, then the camera freed), where the
#: Gauss–Newton step is right and Levenberg–Marquardt's damped first steps only delay
#: it (docs/accuracy.md, twentieth session).
INITIAL_TRUST_REGION_RADIUS = 1e8


@dataclass
class AdjustedTriplet:
    """One triplet inside the shared reconstruction."""

    index: int  # position among the tensors
    image_ids: tuple[int, int, int]  # the triplet's images in the reconstruction
    point_ids: np.ndarray  # (n,) its 3D points
    pixels: np.ndarray  # (3, n, 2) its tracks, pixels
    projective_cost: float  # C_proj, px²
    sigma2: float  # σ², px²
    #: Every point, as triangulated when the triplet was added (or as last checked,
    #: :meth:`SharedCamera.still_in_front`), in front of its three cameras (where not,
    #: no adjustment of the triplet alone is run: :meth:`SharedCamera.adjust_each`).
    in_front: bool = True


class SharedCamera:
    """A pycolmap reconstruction: one camera, each triplet its own three images and points."""

    def __init__(
        self,
        intrinsics: np.ndarray,
        camera_model: str,
        width: int,
        height: int,
        distortion: np.ndarray | None = None,
    ):
        """A camera of ``camera_model`` (any of :data:`..database.cameras.SUPPORTED_MODELS`)
        at (fx, fy, cx, cy), pixels, its distortion parameters ``distortion`` (COLMAP's
        order; default 0)."""
        self.reconstruction = pycolmap.Reconstruction()
        camera = CameraInfo.of_model(
            CAMERA_ID, camera_model, width, height, intrinsics, distortion
        ).to_pycolmap()
        self.reconstruction.add_camera_with_trivial_rig(camera)
        self.triplets: list[AdjustedTriplet] = []

    @property
    def reconstruction(self) -> pycolmap.Reconstruction:
        """The triplets' images and points and the camera. Assigning another (a copy
        adjusted on the side) forgets the poses and points read from this one."""
        return self._reconstruction

    @reconstruction.setter
    def reconstruction(self, value: pycolmap.Reconstruction) -> None:
        self._reconstruction = value
        # Each triplet's poses and points as last read (by its images), until an
        # adjuster is set up over it: pycolmap reads a point at a time, and λ, the cost
        # and the information read every triplet again between solves.
        self._read: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}

    @property
    def camera(self) -> pycolmap.Camera:
        """The shared camera, as adjusted."""
        return self.reconstruction.cameras[CAMERA_ID]

    def cost(self, which: list[int]) -> float:
        """Summed squared reprojection error (px²) of the triplets ``which``."""
        return float(sum(self._squared_errors(self.triplets[p]).sum() for p in which))

    def intrinsics(self) -> np.ndarray:
        camera = self.reconstruction.cameras[CAMERA_ID]
        return np.array(
            [
                camera.focal_length_x,
                camera.focal_length_y,
                camera.principal_point_x,
                camera.principal_point_y,
            ]
        )

    def add(
        self, observed: Observed, cameras: np.ndarray, keypoints: np.ndarray | None = None
    ) -> None:
        """Add a triplet's tracks with its calibrated cameras (3, 3, 4): its points
        triangulated from its (undistorted) tracks, observed at ``keypoints`` (3, n, 2)
        pixels where the camera's distortion is to explain them (default: the tracks)."""
        intrinsics = self.intrinsics()
        normalised = (observed.pixels - intrinsics[2:]) / intrinsics[:2]
        points = triangulate(cameras, normalised)
        pixels = observed.pixels if keypoints is None else keypoints
        first = 3 * len(self.triplets) + 1
        image_ids = (first, first + 1, first + 2)
        for view, image_id in enumerate(image_ids):
            image = pycolmap.Image(
                name=f"{image_id}.png",
                keypoints=np.ascontiguousarray(pixels[view], dtype=np.float64),
                camera_id=CAMERA_ID,
                image_id=image_id,
            )
            pose = pycolmap.Rigid3d(
                pycolmap.Rotation3d(cameras[view][:, :3]), cameras[view][:, 3].copy()
            )
            self.reconstruction.add_image_with_trivial_frame(image, pose)
        # pycolmap adds one point per call; a track's elements added by image id and
        # keypoint index cost half as much as a track built from TrackElement objects.
        point_ids = []
        for k, point in enumerate(points):
            track = pycolmap.Track()
            for image_id in image_ids:
                track.add_element(image_id, k)
            point_ids.append(self.reconstruction.add_point3D(point, track))
        self.triplets.append(
            AdjustedTriplet(
                observed.index,
                image_ids,
                np.array(point_ids),
                pixels,
                observed.projective_cost,
                observed.sigma2,
                in_front=_in_front(cameras, points),
            )
        )

    def adjuster(
        self,
        which: list[int],
        refined: Refined,
        *,
        fix_scale: bool = False,
        function_tolerance: float = FUNCTION_TOLERANCE,
        max_iterations: int = MAX_ITERATIONS,
    ) -> pycolmap.CeresBundleAdjuster:
        """pycolmap's bundle adjuster of the triplets ``which`` (positions in
        ``self.triplets``): poses and points, the camera's parameters as asked.

        Each triplet's first pose is held; its scale is a gauge direction that Ceres'
        damping handles, or, with ``fix_scale`` (for a covariance, which needs a problem
        without gauge freedom), that its first point holds.
        """
        config = pycolmap.BundleAdjustmentConfig()
        for position in which:
            triplet = self.triplets[position]
            # The adjuster normalises the rotations as it sets the problem up (a change
            # in the last digit), and its solve moves poses and points: read them again.
            self._read.pop(triplet.image_ids, None)
            for image_id in triplet.image_ids:
                config.add_image(image_id)
            first = self.reconstruction.images[triplet.image_ids[0]]
            config.set_constant_rig_from_world_pose(first.frame_id)
            if fix_scale:
                config.add_constant_point(int(triplet.point_ids[0]))
        if not (refined.focal or refined.principal_point or refined.distortion):
            config.set_constant_cam_intrinsics(CAMERA_ID)
        options = bundle_adjustment_options(
            refine_focal_length=refined.focal,
            refine_principal_point=refined.principal_point,
            refine_extra_params=refined.distortion,
            function_tolerance=function_tolerance,
            gradient_tolerance=GRADIENT_TOLERANCE,
            max_iterations=max_iterations,
            threads=1,
        )
        options.ceres.solver_options.initial_trust_region_radius = INITIAL_TRUST_REGION_RADIUS
        return pycolmap.create_default_ceres_bundle_adjuster(options, config, self.reconstruction)

    def adjust(self, which: list[int], refined: Refined) -> bool:
        """Bundle-adjust the triplets ``which`` in place (:meth:`adjuster`); False when
        Ceres finds no usable solution."""
        return bool(self.solve(which, refined).is_solution_usable())

    def solve(
        self,
        which: list[int],
        refined: Refined,
        *,
        function_tolerance: float = FUNCTION_TOLERANCE,
        max_iterations: int = MAX_ITERATIONS,
    ) -> pycolmap.BundleAdjustmentSummary:
        """:meth:`adjust` with Ceres' relative ``function_tolerance`` and
        ``max_iterations`` given; pycolmap's summary of the solve."""
        with keep_colmap_quiet():
            adjuster = self.adjuster(
                which,
                refined,
                function_tolerance=function_tolerance,
                max_iterations=max_iterations,
            )
            return adjuster.solve()

    def adjust_each(self, which: list[int]) -> bool:
        """Adjust the poses and points of each triplet of ``which`` at the camera as it
        is, one problem per triplet (they share nothing while the camera is held, and
        one triplet far from the camera would keep a joint problem iterating for all);
        False when Ceres finds no usable solution for any of them.

        A triplet added with a point behind one of its cameras, or found so after an
        adjustment (:attr:`AdjustedTriplet.in_front`), is left as it is: its λ stays inf
        (:meth:`ratios`). Adjusted from there, Ceres crawls for up to hundreds of
        iterations into fits with points behind its cameras, and on the real scenes
        no such triplet ever agreed (docs/accuracy.md, twenty-third session)."""
        fitted = [p for p in which if self.triplets[p].in_front]
        usable = [self.adjust([position], NOTHING) for position in fitted]
        return not fitted or any(usable)

    def still_in_front(self, which: list[int]) -> list[int]:
        """The triplets of ``which`` whose points all lie in front of their cameras as
        adjusted; the others are marked as not (:attr:`AdjustedTriplet.in_front`: they
        are not adjusted alone again, and their λ is inf)."""
        kept = []
        for position in which:
            triplet = self.triplets[position]
            poses, points = self.poses_and_points(triplet)
            triplet.in_front = _in_front(poses, points)
            if triplet.in_front:
                kept.append(position)
        return kept

    def poses_and_points(self, triplet: AdjustedTriplet) -> tuple[np.ndarray, np.ndarray]:
        """A triplet's cameras (3, 3, 4) ``[R | t]`` and points (n, 3), as adjusted
        (read-only arrays)."""
        read = self._read.get(triplet.image_ids)
        if read is not None:
            return read
        images, stored = self.reconstruction.images, self.reconstruction.points3D
        poses = np.stack(
            [np.asarray(images[i].cam_from_world().matrix()) for i in triplet.image_ids]
        )
        # pycolmap forms the map's wrapper at each attribute access: taken once, the
        # reads of 500 points cost two thirds.
        points = np.array([stored[int(p)].xyz for p in triplet.point_ids])
        poses.setflags(write=False)
        points.setflags(write=False)
        self._read[triplet.image_ids] = poses, points
        return poses, points

    def information(self, which: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per triplet of ``which``: its information (m, 4, 4) and gradient (m, 4) on
        (fx, fy, cx, cy) and its squared error (m,), px² (:mod:`intrinsics.polish.information`)."""
        intrinsics = self.intrinsics()
        parts = [
            reduced_information(
                intrinsics, *self.poses_and_points(self.triplets[p]), self.triplets[p].pixels
            )
            for p in which
        ]
        return (
            np.stack([h for h, _, _ in parts]),
            np.stack([g for _, g, _ in parts]),
            np.array([c for _, _, c in parts]),
        )

    def _squared_errors(self, triplet: AdjustedTriplet) -> np.ndarray:
        """(3, n) squared reprojection errors (px²) of a triplet through the shared
        camera (its distortion included); inf behind a camera."""
        poses, points = self.poses_and_points(triplet)
        camera = self.camera
        errors = np.empty((3, len(points)))
        for view, pose in enumerate(poses):
            local = points @ pose[:, :3].T + pose[:, 3]
            in_front = local[:, 2] > 0
            safe = np.where(in_front[:, None], local, [0.0, 0.0, 1.0])
            pixels = np.asarray(
                camera.img_from_cam(np.ascontiguousarray(safe), check_cheirality=False)
            )
            squared = np.sum((pixels - triplet.pixels[view]) ** 2, axis=1)
            errors[view] = np.where(in_front & np.isfinite(squared), squared, np.inf)
        return errors

    def ratios(self) -> np.ndarray:
        """λ of every triplet at the current cameras (inf where a point is behind a camera)."""
        return np.array(
            [
                (float(self._squared_errors(triplet).sum()) - triplet.projective_cost)
                / triplet.sigma2
                for triplet in self.triplets
            ]
        )


def _in_front(cameras: np.ndarray, points: np.ndarray) -> bool:
    """Whether every point (n, 3) lies in front of every camera ``[R | t]`` (3, 3, 4)."""
    return bool(np.all(points @ cameras[:, 2, :3].T + cameras[:, 2, 3] > 0))


@dataclass(frozen=True)
class RawObservations:
    """Where the triplets are observed through the shared camera's distortion: per
    triplet its keypoints (3, n, 2) as observed, pixels, and the distortion (COLMAP's
    order) the camera starts at."""

    keypoints: list[np.ndarray]
    distortion: np.ndarray


def cameras_at(
    observed: list[Observed],
    start: np.ndarray,
    intrinsics: np.ndarray,
    workers: int | None = None,
    known: dict[tuple[int, int, int], np.ndarray] | None = None,
) -> list[np.ndarray | None]:
    """Each triplet's calibrated cameras (3, 3, 4) at K (:func:`calibrated_cameras`; None
    where they cannot be formed), over ``workers`` threads, or forked processes from
    ``MIN_FORKED_JOBS`` triplets (None: one per core).
    ``known``: cameras already formed at K from the same tracks, by the tensor's images."""
    known = known or {}
    missing = [triplet for triplet in observed if triplet.tensor.image_ids not in known]
    jobs = [(triplet, start, intrinsics) for triplet in missing]
    formed = map_jobs(_cameras_job, jobs, workers, processes=len(jobs) >= MIN_FORKED_JOBS)
    known = known | {t.tensor.image_ids: c for t, c in zip(missing, formed, strict=True)}
    return [known[triplet.tensor.image_ids] for triplet in observed]


def observed_at(
    tensors: list[TripletTensor],
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    intrinsics: np.ndarray,
    max_tracks: int = MAX_TRACKS,
    workers: int | None = None,
) -> tuple[list[Observed], list[np.ndarray | None]]:
    """:func:`.calibrated_tracks.observed_tracks` and their :func:`cameras_at` ``intrinsics``
    (pixels), each triplet's both in one job: one call to the workers instead of two
    (one fork fewer where they are forked processes, from ``MIN_FORKED_JOBS`` tensors;
    and no wait between the two for the slowest triplet). The same values as the two
    calls."""
    jobs = [
        (index, tensor, tracks, start, max_tracks, intrinsics)
        for index, tensor in enumerate(tensors)
    ]
    results = map_jobs(_observed_at_job, jobs, workers, processes=len(jobs) >= MIN_FORKED_JOBS)
    kept = [result for result in results if result is not None]
    return [observed for observed, _ in kept], [cameras for _, cameras in kept]


def _observed_at_job(job: tuple[Any, ...]) -> tuple[Observed, np.ndarray | None] | None:
    index, tensor, tracks, start, max_tracks, intrinsics = job
    observed = observed_triplet(index, tensor, tracks, start, max_tracks)
    if observed is None:
        return None
    return observed, _cameras_job((observed, start, intrinsics))


def shared_camera(
    observed: list[Observed],
    cameras: list[np.ndarray | None],
    intrinsics: np.ndarray,
    camera_model: str,
    size: tuple[int, int],
    raw: RawObservations | None = None,
) -> SharedCamera | None:
    """Every triplet whose calibrated cameras at K (``cameras``, :func:`cameras_at`)
    could be formed, in one reconstruction. With ``raw`` the triplets are observed at
    its keypoints through a camera whose distortion starts at its distortion
    (:meth:`SharedCamera.add`)."""
    shared = SharedCamera(intrinsics, camera_model, *size, None if raw is None else raw.distortion)
    seen = raw.keypoints if raw is not None else [None] * len(observed)
    for triplet, formed, at in zip(observed, cameras, seen, strict=True):
        if formed is not None and np.all(np.isfinite(formed)):
            shared.add(triplet, formed, at)
    return shared if shared.triplets else None


def _cameras_job(job: tuple[Any, ...]) -> np.ndarray | None:
    triplet, start, intrinsics = job
    normalised = (triplet.pixels - intrinsics[2:]) / intrinsics[:2]
    return calibrated_cameras(triplet.tensor, normalised, start, intrinsics)


#: Rounds of "choose the agreeing triplets at K, adjust them together".
ROUNDS = 2


@dataclass
class Agreement:
    """The triplets that agree with the shared camera, adjusted together with it.

    Attributes:
        agreeing: their positions in ``shared.triplets``.
        ratios: λ of every triplet at the start of the final round.
        fallback: the agreeing set is the fallback's (too few triplets agreed).
    """

    agreeing: list[int]
    ratios: np.ndarray
    fallback: bool = False


def agree_and_adjust(
    shared: SharedCamera,
    limit: float,
    refined: Refined,
    minimum: int = 1,
    fallback: Callable[[], list[int]] | None = None,
    adjusted: Collection[int] = (),
) -> Agreement | None:
    """The rounds of the polish and the lens stage, ``ROUNDS`` at most.

    Each round: the triplets not adjusted with the current K get their poses and points
    adjusted at it (the first round: all but ``adjusted``, those already adjusted
    together with the camera as it is, refined as ``refined``), which gives every
    triplet's λ at K; those with ``λ < limit`` are then adjusted together with the
    camera refined as ``refined``. A triplet adjusted with K free is already at its
    optimum for that K, and when the agreeing set is the one K was last adjusted with
    (in the first round: ``adjusted``), neither changes: the rounds stop there.
    Where fewer than ``minimum`` agree in the first round, ``fallback`` (if given)
    chooses them instead, and the rounds end after their adjustment. None where Ceres
    fails or fewer than ``minimum`` triplets remain.
    """
    everything = range(len(shared.triplets))
    agreement = Agreement([], np.array([]))
    settled = sorted(adjusted)  # the triplets K was last adjusted with
    for _ in range(ROUNDS):
        stale = [p for p in everything if p not in settled]
        if stale and not shared.adjust_each(stale):
            return None
        ratios = shared.ratios()
        chosen = [p for p, ratio in enumerate(ratios) if ratio < limit]
        used = agreement.fallback
        if len(chosen) < minimum and fallback is not None and not agreement.agreeing:
            used, chosen = True, fallback()
        if len(chosen) < minimum:
            return None
        if chosen == settled:
            return Agreement(chosen, ratios, used)
        agreement = Agreement(chosen, ratios, used)
        settled = chosen
        if not shared.adjust(chosen, refined):
            return None
        if used:
            break
    return agreement
