"""Synthetic multi-view scenes for testing and benchmarking TrifocalCalib.

The set-up follows the synthetic experiments of the TrifocalCalib paper:

* 3D points uniformly distributed in a cube centred at the origin (default side 2,
  world units);
* ``num_cameras`` cameras whose centres are uniformly distributed on a sphere of
  radius ~6 around the origin (the radius is jittered by ±``radius_jitter``); each
  looks *roughly* at the origin: its optical axis is the direction to the origin
  tilted by a random angle up to ``cone_deg`` degrees, and it has a uniformly random
  roll. Optical axes therefore do not meet in one point (a critical configuration
  for focal-length self-calibration) and the cameras are in general position;
* one shared pinhole camera ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (pixels),
  COLMAP pixel convention: the centre of the top-left pixel is at (0.5, 0.5), so the
  image covers ``[0, width] x [0, height]``;
* only points in front of every camera and projecting inside every image are kept
  (the generator draws points until ``num_points`` of them qualify);
* observations are the exact projections plus i.i.d. uniform pixel noise in
  ``[-noise_px, +noise_px]`` on each coordinate (std ``noise_px / sqrt(3)``);
* a fraction ``outlier_ratio`` of the tracks are outliers: their observation in one
  random view is replaced by a uniformly random pixel of the image.

Poses are world-to-camera: ``x_cam = R X + t``, ``x_px ~ K x_cam``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ..geometry.tensor_estimation import TensorEstimationOptions, TripletTensor
from ..geometry.trifocal import intrinsics_matrix, normalize_tensor, tensor_from_cameras
from ..geometry.triplet_fit import estimate_triplet_tensor

#: Intrinsics (fx, fy, cx, cy) of the Strecha fountain-P11 camera, pixels (3072 x 2048).
DEFAULT_INTRINSICS = np.array([2759.48, 2764.16, 1520.69, 1006.81])
DEFAULT_WIDTH = 3072
DEFAULT_HEIGHT = 2048


@dataclass
class SyntheticScene:
    """Ground truth and noisy pixel observations of a synthetic scene."""

    K: np.ndarray  # (3, 3) shared intrinsics, pixels
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy, pixels
    rotations: np.ndarray  # (m, 3, 3) world-to-camera rotations
    translations: np.ndarray  # (m, 3): x_cam = R X + t
    points: np.ndarray  # (n, 3) world points
    observations: np.ndarray  # (m, n, 2) noisy pixel observations (COLMAP convention)
    outliers: np.ndarray  # (n,) bool, tracks with one corrupted observation
    outlier_views: np.ndarray  # (n,) int, the corrupted view of each track, −1 if none
    width: int  # image width, pixels
    height: int  # image height, pixels
    #: (m, n) bool: point n projects inside image m, in front of it; None: all of them.
    visible: np.ndarray | None = None

    @property
    def num_cameras(self) -> int:
        return len(self.rotations)

    @property
    def num_points(self) -> int:
        return len(self.points)

    @property
    def centers(self) -> np.ndarray:
        """Camera centres (m, 3) in world coordinates, ``C = −Rᵀ t``."""
        return -np.einsum("mji,mj->mi", self.rotations, self.translations)

    def outliers_in(self, views: tuple[int, ...] | list[int]) -> np.ndarray:
        """(n,) bool: tracks whose corrupted observation is in one of ``views``.

        These are the outliers of the sub-problem made of those views; an outlier track
        of the scene is a clean track for views that do not include its corrupted one.
        """
        return np.isin(self.outlier_views, np.asarray(views))

    def camera_matrices(self, K: np.ndarray | None = None) -> np.ndarray:
        """Projection matrices ``K [R | t]`` (m, 3, 4); ``K`` defaults to the true one.

        Pass ``K = np.eye(3)`` for the normalised cameras, or ``K0⁻¹ K`` for cameras in
        coordinates normalised by a prior ``K0``.
        """
        K = self.K if K is None else K
        Rt = np.concatenate([self.rotations, self.translations[:, :, None]], axis=2)
        return K @ Rt

    def project(self, points: np.ndarray | None = None) -> np.ndarray:
        """Exact pixel projections (m, n, 2) of world points (n, 3) (default: the scene's)."""
        points = self.points if points is None else points
        return _project(self.K, self.rotations, self.translations, points)[0]

    def true_tensor(self, views: tuple[int, int, int], K0: np.ndarray | None = None) -> np.ndarray:
        """The exact tensor (3, 3, 3), unit Frobenius norm, of cameras ``views``.

        Coordinates are normalised by ``K0`` (``x̂ = K0⁻¹ x``; default: the true K, which
        gives the calibrated tensor): cameras ``M [R_j | t_j]`` with ``M = K0⁻¹ K``,
        mapped by the projective change of frame that brings the first one to ``[I | 0]``.
        This is the tensor :func:`estimate_triplet_tensor` estimates from the tracks
        ``observations[list(views)]`` with prior ``K0`` (up to sign).
        """
        K0 = self.K if K0 is None else K0
        P = self.camera_matrices(np.linalg.solve(K0, self.K))[list(views)]
        H = np.linalg.inv(np.vstack([P[0], [0.0, 0.0, 0.0, 1.0]]))
        P = P @ H
        return normalize_tensor(tensor_from_cameras(P[1], P[2]))


def _as_generator(seed: int | np.random.Generator | None) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def _project(
    K: np.ndarray, rotations: np.ndarray, translations: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel projections (m, n, 2) and depths (m, n) of points (n, 3)."""
    cam = np.einsum("mij,nj->mni", rotations, points) + translations[:, None, :]
    depth = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = (cam @ K.T)[..., :2] / depth[..., None]
    return pixels, depth


def random_rotations(rng: np.random.Generator, count: int) -> np.ndarray:
    """Uniformly distributed rotations (count, 3, 3) (QR of Gaussian matrices)."""
    q, r = np.linalg.qr(rng.standard_normal((count, 3, 3)))
    q = q * np.sign(np.einsum("nii->ni", r))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1.0
    return q


def look_at_rotations(directions: np.ndarray, rolls: np.ndarray) -> np.ndarray:
    """World-to-camera rotations (m, 3, 3) of cameras with the given optical axes.

    Args:
        directions: optical axes (m, 3) in world coordinates (camera +z), any length.
        rolls: rotation about the optical axis (m,), radians.
    """
    z = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    # Any vector not parallel to z gives a first x axis; roll then rotates it about z.
    helper = np.where(np.abs(z[:, [2]]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    c, s = np.cos(rolls)[:, None], np.sin(rolls)[:, None]
    x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z], axis=1)  # rows: camera axes in world coordinates


def _tilt(directions: np.ndarray, max_angle: float, rng: np.random.Generator) -> np.ndarray:
    """Unit vectors uniformly distributed in the cone of half-angle ``max_angle`` (rad)."""
    m = len(directions)
    cos_angle = rng.uniform(np.cos(max_angle), 1.0, size=m)  # uniform on the spherical cap
    sin_angle = np.sqrt(1.0 - cos_angle**2)
    azimuth = rng.uniform(0.0, 2.0 * np.pi, size=m)
    helper = np.where(np.abs(directions[:, [2]]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(helper, directions)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(directions, u)
    return cos_angle[:, None] * directions + sin_angle[:, None] * (
        np.cos(azimuth)[:, None] * u + np.sin(azimuth)[:, None] * v
    )


def _camera_directions(
    count: int, min_angle: float, rng: np.random.Generator, max_tries: int
) -> np.ndarray:
    """Unit vectors (count, 3) uniform on the sphere, pairwise at least ``min_angle`` apart."""
    for _ in range(max_tries):
        directions = rng.standard_normal((count, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        cosines = directions @ directions.T
        np.fill_diagonal(cosines, -1.0)
        if np.all(cosines <= np.cos(min_angle)):
            return directions
    raise ValueError(f"could not place {count} cameras {np.rad2deg(min_angle):.1f} degrees apart")


def _check_scene_arguments(
    num_points: int, num_cameras: int, noise_px: float, outlier_ratio: float
) -> None:
    """ValueError on a scene :func:`make_scene` cannot make."""
    if num_points < 1 or num_cameras < 1:
        raise ValueError("num_points and num_cameras must be positive")
    if noise_px < 0 or not 0.0 <= outlier_ratio <= 1.0:
        raise ValueError("noise_px must be >= 0 and outlier_ratio in [0, 1]")


@dataclass(frozen=True)
class _Views:
    """The cameras of a scene: K (3, 3), world-to-camera R (m, 3, 3) and t (m, 3), and
    the image size (pixels)."""

    K: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    width: int
    height: int


def make_scene(  # noqa: PLR0913 (a scene generator: every knob a keyword with a default)
    num_points: int = 500,
    num_cameras: int = 3,
    noise_px: float = 0.0,
    outlier_ratio: float = 0.0,
    seed: int | np.random.Generator | None = 0,
    intrinsics: np.ndarray | None = None,
    width: int = DEFAULT_WIDTH,
    height: int = DEFAULT_HEIGHT,
    cube_side: float = 2.0,
    radius: float = 6.0,
    radius_jitter: float = 0.5,
    cone_deg: float = 5.0,
    min_separation_deg: float = 10.0,
    max_tries: int = 100,
) -> SyntheticScene:
    """Random scene of ``num_points`` points seen by all ``num_cameras`` cameras.

    Args:
        num_points: number of tracks (points visible in every view).
        num_cameras: number of cameras (m ≥ 1).
        noise_px: half-width of the uniform pixel noise on each coordinate, pixels.
        outlier_ratio: fraction of tracks (rounded) with one observation replaced by a
            uniformly random pixel of the image.
        seed: int seed or a numpy Generator (used as is, so it advances).
        intrinsics: (fx, fy, cx, cy) in pixels; default :data:`DEFAULT_INTRINSICS`.
        width, height: image size, pixels.
        cube_side: side of the cube of points (centred at the origin), world units.
        radius, radius_jitter, cone_deg, min_separation_deg: the cameras' placement
            (:func:`place_cameras_around_origin`).
        max_tries: draws of camera centres, and batches of candidate points, at most.

    Raises:
        ValueError: on invalid arguments, when no camera placement satisfies
            ``min_separation_deg`` or when too few points are visible in all views
            (e.g. a very narrow field of view or a large ``cone_deg``).
    """
    _check_scene_arguments(num_points, num_cameras, noise_px, outlier_ratio)
    rng = _as_generator(seed)
    params = np.asarray(DEFAULT_INTRINSICS if intrinsics is None else intrinsics, dtype=float)
    rotations, translations = place_cameras_around_origin(
        num_cameras, rng, radius, radius_jitter, cone_deg, min_separation_deg, max_tries
    )
    views = _Views(intrinsics_matrix(params), rotations, translations, width, height)
    points = _points_visible_in_all_views(views, num_points, cube_side, rng, max_tries)
    observations, outlier_views = _observe(views, points, noise_px, outlier_ratio, rng)
    return SyntheticScene(
        K=views.K,
        intrinsics=params.copy(),
        rotations=views.rotations,
        translations=views.translations,
        points=points,
        observations=observations,
        outliers=outlier_views >= 0,
        outlier_views=outlier_views,
        width=width,
        height=height,
    )


def place_cameras_around_origin(
    num_cameras: int,
    rng: np.random.Generator,
    radius: float = 6.0,
    radius_jitter: float = 0.5,
    cone_deg: float = 5.0,
    min_separation_deg: float = 10.0,
    max_tries: int = 100,
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R (m,3,3), t (m,3)) of cameras on a sphere, looking near the origin.

    Args:
        num_cameras: cameras (m).
        rng: the random generator (advanced).
        radius: mean distance of the camera centres from the origin, world units.
        radius_jitter: the distance is uniform in ``radius ± radius_jitter``.
        cone_deg: maximal angle between an optical axis and the direction to the
            origin, degrees.
        min_separation_deg: minimal angle between two camera centres seen from the
            origin, degrees (centres are redrawn until it holds), so that no two
            cameras nearly coincide.
        max_tries: draws of camera centres at most.
    """
    directions = _camera_directions(num_cameras, np.deg2rad(min_separation_deg), rng, max_tries)
    centers = (
        directions
        * rng.uniform(radius - radius_jitter, radius + radius_jitter, num_cameras)[:, None]
    )
    axes = _tilt(-directions, np.deg2rad(cone_deg), rng)
    rotations = look_at_rotations(axes, rng.uniform(0.0, 2.0 * np.pi, num_cameras))
    translations = -np.einsum("mij,mj->mi", rotations, centers)
    return rotations, translations


def _points_visible_in_all_views(
    views: _Views,
    num_points: int,
    cube_side: float,
    rng: np.random.Generator,
    max_tries: int,
) -> np.ndarray:
    """``num_points`` uniform points of the centred cube inside every image (n, 3)."""
    kept: list[np.ndarray] = []
    count = 0
    for _ in range(max_tries):
        candidates = rng.uniform(-cube_side / 2, cube_side / 2, size=(2 * num_points, 3))
        pixels, depth = _project(views.K, views.rotations, views.translations, candidates)
        inside = (
            (depth > 0)
            & (pixels[..., 0] >= 0)
            & (pixels[..., 0] <= views.width)
            & (pixels[..., 1] >= 0)
            & (pixels[..., 1] <= views.height)
        )
        visible = candidates[np.all(inside, axis=0)]
        kept.append(visible)
        count += len(visible)
        if count >= num_points:
            return np.concatenate(kept)[:num_points]
    raise ValueError(
        f"only {count} of {num_points} points are visible in all {len(views.rotations)} views"
    )


def _observe(
    cameras: _Views,
    points: np.ndarray,
    noise_px: float,
    outlier_ratio: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy pixels (m, n, 2) and, per track, the view replaced by an outlier (−1: none)."""
    num_cameras, num_points = len(cameras.rotations), len(points)
    width, height = cameras.width, cameras.height
    exact, _ = _project(cameras.K, cameras.rotations, cameras.translations, points)
    observations = exact + rng.uniform(-noise_px, noise_px, size=exact.shape)
    outlier_views = np.full(num_points, -1)
    num_outliers = int(round(outlier_ratio * num_points))
    if num_outliers > 0:
        corrupted = rng.choice(num_points, size=num_outliers, replace=False)
        views = rng.integers(0, num_cameras, size=num_outliers)
        observations[views, corrupted] = rng.uniform(
            [0.0, 0.0], [float(width), float(height)], size=(num_outliers, 2)
        )
        outlier_views[corrupted] = views
    return observations, outlier_views


def perturbed_prior(
    intrinsics: np.ndarray,
    fraction: float = 0.05,
    rng: int | np.random.Generator | None = None,
) -> np.ndarray:
    """A prior (4,): each of (fx, fy, cx, cy) times ``1 + U(−fraction, +fraction)``."""
    rng = _as_generator(rng)
    intrinsics = np.asarray(intrinsics, dtype=float)
    return intrinsics * (1.0 + rng.uniform(-fraction, fraction, size=intrinsics.shape))


def triplet_tensors(
    scene: SyntheticScene,
    prior: np.ndarray,
    rng: int | np.random.Generator | None = None,
    options: TensorEstimationOptions | None = None,
    triplets: list[tuple[int, int, int]] | None = None,
) -> list[TripletTensor]:
    """Tensors estimated by :func:`estimate_triplet_tensor` for every camera triplet.

    Args:
        scene: the scene; all its tracks are passed (outliers included).
        prior: prior intrinsics (fx0, fy0, cx0, cy0), pixels.
        rng: seed or Generator for the estimation.
        options: estimation settings.
        triplets: camera index triplets; default all ``itertools.combinations``.

    Returns:
        The tensors that could be estimated; image ids are camera indices.
    """
    rng = _as_generator(rng)
    K0 = intrinsics_matrix(np.asarray(prior, dtype=float))
    if triplets is None:
        triplets = list(itertools.combinations(range(scene.num_cameras), 3))
    tensors = []
    for views in triplets:
        tensor = estimate_triplet_tensor(
            (int(views[0]), int(views[1]), int(views[2])),
            scene.observations[list(views)],
            K0,
            rng,
            options,
        )
        if tensor is not None:
            tensors.append(tensor)
    return tensors
