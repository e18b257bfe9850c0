"""Synthetic scenes seen through narrow (telephoto) and wide lenses.

COLMAP's default camera guesses ``f = 1.2 · max(width, height)``, a 45° horizontal
field of view. A telephoto lens (10°: f = 5.7 · max(w, h)) or a wide lens (100°:
f = 0.42 · max(w, h)) is far outside ±2× of that guess, so these scenes check
that a calibration finds such lenses from the default camera.

Both scenes are rings of cameras around an object (general rotations: every
intrinsic is determined in principle), one shared pinhole camera with square
pixels and the principal point 2–3 % off the image centre. Conventions as in
:mod:`.synthetic.scenes` (pixels, COLMAP's centre of the top-left pixel at
(0.5, 0.5), world-to-camera poses).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .facade import facade_scene
from .motions import scene_from_poses
from .scenes import SyntheticScene, _as_generator, look_at_rotations, make_scene

#: Image size of the lens scenes, pixels (VGA, as a small handheld or turntable set).
LENS_WIDTH = 640
LENS_HEIGHT = 480


def focal_for_field_of_view(fov_deg: float, width: int, height: int) -> float:
    """Focal length (pixels) whose field of view across the longer image side is ``fov_deg``."""
    return 0.5 * max(width, height) / np.tan(np.deg2rad(fov_deg) / 2.0)


def lens_intrinsics(fov_deg: float, width: int = LENS_WIDTH, height: int = LENS_HEIGHT):
    """(fx, fy, cx, cy) in pixels: the lens' focal length, the principal point off centre."""
    focal = focal_for_field_of_view(fov_deg, width, height)
    return np.array([focal, focal, 0.52 * width, 0.47 * height])


def lens_scene(
    fov_deg: float,
    num_images: int = 8,
    noise_px: float = 0.5,
    seed: int | np.random.Generator | None = 0,
    num_points: int = 1500,
) -> SyntheticScene:
    """Cameras in general position around a 2 m cube, framing it through a ``fov_deg`` lens.

    The distance is chosen so that the cube fills about 70 % of the image
    (narrow lenses look from far away, so the perspective is weak: a 10° lens sees
    depth differences of only 1.5 % of the distance); the optical axes are tilted
    by up to 10 % of the field of view and every point is seen in every view.
    """
    half = np.deg2rad(fov_deg) / 2.0
    radius = 1.0 + 1.0 / (0.7 * np.tan(half))
    scene = make_scene(
        num_points,
        num_images,
        noise_px,
        0.0,
        seed,
        intrinsics=lens_intrinsics(fov_deg),
        width=LENS_WIDTH,
        height=LENS_HEIGHT,
        radius=radius,
        radius_jitter=0.05 * radius,
        cone_deg=0.1 * fov_deg / 2.0,
    )
    scene.visible = np.ones((num_images, num_points), dtype=bool)
    return scene


def narrow_lens(
    num_images: int = 8, noise_px: float = 0.5, seed: int | np.random.Generator | None = 0
) -> SyntheticScene:
    """A 10° telephoto (f = 3658 px at 640 × 480, 4.8× COLMAP's default guess)."""
    return lens_scene(10.0, num_images, noise_px, seed)


def wide_lens(
    num_images: int = 8, noise_px: float = 0.5, seed: int | np.random.Generator | None = 0
) -> SyntheticScene:
    """A 100° wide-angle pinhole (f = 269 px at 640 × 480, 0.35× COLMAP's default guess)."""
    return lens_scene(100.0, num_images, noise_px, seed)


def turntable(
    num_images: int = 16,
    noise_px: float = 0.5,
    seed: int | np.random.Generator | None = 0,
    fov_deg: float = 11.0,
    elevation_deg: float = 20.0,
    num_points: int = 600,
) -> SyntheticScene:
    """A small object on a turntable shot through a narrow lens (11° by default).

    ``num_images`` views evenly around a full turn, all from ``elevation_deg`` above
    the table (the camera looks down at the object), 3 m away; the object is a
    0.24 m cube of points, of which each view sees the half facing it. All rotations
    are about the turntable's axis (planar motion, the axis tilted by the
    elevation in the camera), and the object's depth is 8 % of the distance (weak
    perspective): the focal length is only weakly determined by any method.
    """
    rng = _as_generator(seed)
    angles = np.linspace(0.0, 2.0 * np.pi, num_images, endpoint=False)
    distance, elevation = 3.0, np.deg2rad(elevation_deg)
    centers = distance * np.stack(
        [
            np.cos(elevation) * np.sin(angles),
            -np.sin(elevation) * np.ones(num_images),  # world y points down: above
            -np.cos(elevation) * np.cos(angles),
        ],
        axis=1,
    )
    points = rng.uniform(-0.12, 0.12, size=(num_points, 3))
    aims = -centers + rng.normal(0.0, 0.005, size=(num_images, 3))
    rotations = look_at_rotations(aims, rng.normal(0.0, np.deg2rad(0.3), num_images))
    scene = scene_from_poses(
        rotations,
        centers,
        points,
        noise_px,
        rng,
        intrinsics=lens_intrinsics(fov_deg),
        width=LENS_WIDTH,
        height=LENS_HEIGHT,
    )
    facing = (centers @ scene.points.T) > 0  # the half of the object facing the camera
    scene.visible = scene.visible & facing
    scene.observations[~scene.visible] = 0.0
    return scene


#: The drone survey's camera: a 65° VGA lens, the principal point off centre, pixels.
DRONE_INTRINSICS = np.array([500.0, 500.0, 330.0, 236.0])


def drone_survey(
    seed: int | np.random.Generator | None = 0, relief: float = 0.05, num_images: int = 10
) -> SyntheticScene:
    """A drone's VGA camera (65°, :data:`DRONE_INTRINSICS`) passing over ground with
    little relief (``relief``: depth variation relative to the distance): the facade
    walk of :func:`.facade.facade_scene` seen from 640 × 480 pixels, so that most view
    pairs are close to a homography and every triplet's tensor is weakly conditioned."""
    return facade_scene(
        relief=relief,
        num_images=num_images,
        seed=seed,
        num_points=1500,
        intrinsics=DRONE_INTRINSICS,
        width=LENS_WIDTH,
        height=LENS_HEIGHT,
    )


def with_radial_distortion(scene: SyntheticScene, k1: float, k2: float = 0.0) -> SyntheticScene:
    """The scene seen through a lens with COLMAP ``RADIAL`` distortion ``(k1, k2)``
    (``SIMPLE_RADIAL`` where ``k2 = 0``).

    Each observed pixel ``p`` becomes ``c + f · u · (1 + k1 ρ + k2 ρ²)`` with
    ``u = (p − c) / f`` and ``ρ = |u|²`` (normalised coordinates; f and c of the scene's
    camera); the noise already in ``p`` is distorted with it. ``k1 < 0`` is barrel
    distortion. Returns a copy (observations only).
    """
    f = np.asarray(scene.intrinsics[:2], dtype=float)
    centre = np.asarray(scene.intrinsics[2:4], dtype=float)
    normalised = (scene.observations - centre) / f
    radius2 = np.sum(normalised**2, axis=-1, keepdims=True)
    distorted = centre + f * normalised * (1.0 + k1 * radius2 + k2 * radius2**2)
    shape = scene.observations.shape[:2]
    observed = np.ones(shape, dtype=bool) if scene.visible is None else scene.visible
    return replace(scene, observations=np.where(observed[..., None], distorted, 0.0))


def with_division_distortion(scene: SyntheticScene, division: float) -> SyntheticScene:
    """The scene seen through a lens that follows Fitzgibbon's division model: each
    observed pixel ``p`` becomes the ``d`` with ``p = c + (d − c) / (1 + λ r²)``,
    ``r = |d − c| / s`` (``λ = division``; ``c`` the scene's principal point, ``s`` half
    the image diagonal). ``λ < 0`` is barrel distortion; no COLMAP model holds it
    exactly, as with many real wide lenses. Returns a copy (observations only).

    Solves ``λ r_u r² − r + r_u = 0`` for the distorted radius ``r`` (the root that
    tends to ``r_u`` as ``λ → 0``); ``r_u = |p − c| / s``.
    """
    centre = np.asarray(scene.intrinsics[2:4], dtype=float)
    scale = 0.5 * float(np.hypot(scene.width, scene.height))
    offset = scene.observations - centre
    undistorted = np.linalg.norm(offset, axis=-1, keepdims=True) / scale
    product = division * undistorted
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.where(
            np.abs(product) > 1e-12,
            (1.0 - np.sqrt(1.0 - 4.0 * product * undistorted)) / (2.0 * product),
            undistorted,
        )
        ratio = np.where(undistorted > 0, radius / undistorted, 1.0)
    shape = scene.observations.shape[:2]
    observed = np.ones(shape, dtype=bool) if scene.visible is None else scene.visible
    distorted = centre + offset * ratio
    return replace(scene, observations=np.where(observed[..., None], distorted, 0.0))
