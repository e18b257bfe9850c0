"""A synthetic building facade: a plane with a little relief, photographed from the street.

Like a person photographing a church entrance: ``num_images`` hand-held shots
taken while walking sideways in front of the facade, each aimed at a slightly
different spot of it (yaw, pitch and a little roll vary by several degrees).

Geometry (world coordinates, metres; the world's y axis points down, as in
:mod:`.motions`): the facade is the plane ``z = distance`` seen from cameras near
``z = 0``. ``relief`` is the depth relief relative to that distance: most points
lie on the plane, the rest on blocks recessed or protruding by up to
``relief · distance`` (a door recessed by the full relief, windows recessed by
half of it, pilasters and a cornice protruding by half of it). With
``relief = 0.3`` the same generator gives a scene spread through depth (every
point at a uniform depth offset), the general-scene reference of
``benchmarks/planar_facade.py``.

Observations follow :func:`.motions.scene_from_poses` (uniform pixel noise in
``[-noise_px, +noise_px]``, COLMAP pixel convention); then a share
``outlier_ratio`` of the tracks gets one of its visible observations replaced by a
uniformly random pixel of that image (``scene.outliers`` / ``outlier_views``).
"""

from __future__ import annotations

import numpy as np

from .motions import scene_from_poses
from .scenes import (
    DEFAULT_HEIGHT,
    DEFAULT_INTRINSICS,
    DEFAULT_WIDTH,
    SyntheticScene,
    _as_generator,
)

#: Blocks of the facade: (x0, x1, y0, y1) in metres (facade centred at x = 0, y = 0,
#: y down) and their depth offset in units of the relief (positive: recessed).
FACADE_BLOCKS = np.array(
    [
        [-1.2, 1.2, -1.0, 3.5, 1.0],  # door
        [-5.5, -3.5, -2.5, 0.5, 0.5],  # windows
        [3.5, 5.5, -2.5, 0.5, 0.5],
        [-5.5, -3.5, 1.5, 3.5, 0.5],
        [3.5, 5.5, 1.5, 3.5, 0.5],
        [-2.3, -1.7, -4.0, 3.5, -0.5],  # pilasters beside the door
        [1.7, 2.3, -4.0, 3.5, -0.5],
        [-8.0, 8.0, -4.5, -4.0, -0.5],  # cornice
    ]
)
#: Share of the points drawn on the blocks (the rest lie on the plane).
BLOCK_SHARE = 0.25


def facade_points(
    num_points: int, relief: float, distance: float, rng: np.random.Generator
) -> np.ndarray:
    """Points (num_points, 3) of a 16 m x 10 m facade at depth ``distance`` with ``relief``.

    ``relief`` ≥ 0.2 gives a scene spread through depth instead (uniform offsets in
    ``±relief · distance``), see the module docstring.
    """
    x = rng.uniform(-8.0, 8.0, num_points)
    y = rng.uniform(-5.0, 5.0, num_points)
    offset = np.zeros(num_points)
    if relief >= 0.2:
        offset = rng.uniform(-1.0, 1.0, num_points)
    else:
        on_blocks = rng.random(num_points) < BLOCK_SHARE
        block = rng.integers(0, len(FACADE_BLOCKS), num_points)
        x0, x1, y0, y1, depth = FACADE_BLOCKS[block].T
        x = np.where(on_blocks, rng.uniform(x0, x1), x)
        y = np.where(on_blocks, rng.uniform(y0, y1), y)
        # Points that fall inside a block (also those drawn on the plane) take its depth.
        inside = (x[:, None] >= FACADE_BLOCKS[:, 0]) & (x[:, None] <= FACADE_BLOCKS[:, 1])
        inside &= (y[:, None] >= FACADE_BLOCKS[:, 2]) & (y[:, None] <= FACADE_BLOCKS[:, 3])
        first = np.argmax(inside, axis=1)
        offset = np.where(inside.any(axis=1), FACADE_BLOCKS[first, 4], 0.0)
    z = distance * (1.0 + relief * offset)
    return np.stack([x, y, z], axis=1)


def facade_scene(  # noqa: PLR0913 (a scene generator: every knob a keyword with a default)
    relief: float = 0.02,
    num_images: int = 10,
    noise_px: float = 0.5,
    outlier_ratio: float = 0.05,
    seed: int | np.random.Generator | None = 0,
    num_points: int = 4000,
    distance: float = 10.0,
    walk: float = 6.0,
    intrinsics: np.ndarray | None = None,
    width: int = DEFAULT_WIDTH,
    height: int = DEFAULT_HEIGHT,
) -> SyntheticScene:
    """Hand-held shots of a facade ``distance`` m away, walking ``walk`` m sideways.

    Args:
        relief: depth relief of the facade relative to ``distance`` (0.01–0.05 for a
            real facade; ≥ 0.2: a general scene, see :func:`facade_points`).
        num_images: shots, evenly spaced along the walk (centres jittered by 0.3 m).
        noise_px: half-width of the uniform pixel noise, pixels.
        outlier_ratio: share of the tracks with one observation replaced by a random pixel.
        seed: int seed or a numpy Generator.
        num_points: facade points drawn (those seen by fewer than 2 images are dropped).
        distance: distance from the walk to the facade plane, metres.
        walk: length of the sideways walk, metres.
        intrinsics: (fx, fy, cx, cy), pixels; default the Strecha camera (3072 x 2048).
        width, height: image size, pixels.
    """
    rng = _as_generator(seed)
    points = facade_points(num_points, relief, distance, rng)
    rotations, centers = _handheld_poses(num_images, walk, distance, rng)
    scene = scene_from_poses(
        rotations,
        centers,
        points,
        noise_px,
        rng,
        intrinsics=DEFAULT_INTRINSICS if intrinsics is None else intrinsics,
        width=width,
        height=height,
    )
    _add_outliers(scene, outlier_ratio, rng)
    return scene


def _handheld_poses(
    num_images: int, walk: float, distance: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera rotations (m, 3, 3) and centres (m, 3) of shots along the walk,
    each aimed at a spot of the facade ``distance`` m away (see :func:`facade_scene`)."""
    along = np.linspace(-walk / 2.0, walk / 2.0, num_images)
    centers = np.stack(
        [
            along + rng.normal(0.0, 0.3, num_images),
            rng.normal(0.0, 0.3, num_images),
            rng.normal(0.0, 0.3, num_images),
        ],
        axis=1,
    )
    # Each shot aims at a spot of the facade near the door: yaw and pitch vary by
    # several degrees between shots, and the photographer holds the camera not quite level.
    targets = np.stack(
        [
            rng.uniform(-2.5, 2.5, num_images),
            rng.uniform(-1.5, 1.5, num_images),
            np.full(num_images, distance),
        ],
        axis=1,
    )
    rotations = _level_look_at(targets - centers, rng.normal(0.0, np.deg2rad(2.0), num_images))
    return rotations, centers


def _level_look_at(directions: np.ndarray, rolls: np.ndarray) -> np.ndarray:
    """World-to-camera rotations (m, 3, 3) with optical axes ``directions`` and ``rolls`` (rad).

    Roll 0: the camera's x axis is horizontal (orthogonal to the world's y axis).
    """
    z = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    c, s = np.cos(rolls)[:, None], np.sin(rolls)[:, None]
    return np.stack([c * x + s * y, -s * x + c * y, z], axis=1)


def _add_outliers(scene: SyntheticScene, ratio: float, rng: np.random.Generator) -> None:
    """Replace one visible observation of a share ``ratio`` of the tracks by a random pixel."""
    count = int(round(ratio * scene.num_points))
    if count == 0:
        return
    assert scene.visible is not None
    corrupted = rng.choice(scene.num_points, size=count, replace=False)
    # A random view among those that see the track (argmax of random keys over them).
    keys = np.where(scene.visible[:, corrupted], rng.random((scene.num_cameras, count)), -1.0)
    views = np.argmax(keys, axis=0)
    scene.observations[views, corrupted] = rng.uniform(
        [0.0, 0.0], [float(scene.width), float(scene.height)], size=(count, 2)
    )
    scene.outliers[corrupted] = True
    scene.outlier_views[corrupted] = views
