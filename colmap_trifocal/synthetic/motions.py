"""Synthetic image sequences whose camera motion hides some intrinsics.

Each function returns a :class:`.synthetic.SyntheticScene` with per-view
visibility (points behind a camera or outside its image are not observed), one
shared pinhole camera and uniform pixel noise in ``[-noise_px, +noise_px]``.

Conventions: world-to-camera poses ``x_cam = R X + t``; camera axes x right,
y down, z forward; the world's y axis points down too, so "level" cameras have
their y axis along the world's and yaw is a rotation about it. Pixels follow
COLMAP (centre of the top-left pixel at (0.5, 0.5)). Lengths in metres.

* :func:`forward_driving`: a car-mounted camera moving along its optical axis,
  yawing by a few degrees (planar motion: fy is not determined).
* :func:`driving_turn`: the same car turning a corner (90° by default; still
  planar motion, but with much more rotation than :func:`forward_driving`).
* :func:`planar_orbit`: a level camera circling an object at constant height
  (planar motion: fy is not determined).
* :func:`pure_translation`: no rotation at all (nothing is determined).
* :func:`handheld_indoor`: a small handheld VGA set in a room (short baseline,
  a few hundred noisy tracks: everything is determined, but only weakly).
* :func:`general_motion`: cameras in general position around a cube of points
  (:func:`.synthetic.make_scene`; everything is determined).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..geometry.trifocal import intrinsics_matrix
from .scenes import (
    DEFAULT_HEIGHT,
    DEFAULT_INTRINSICS,
    DEFAULT_WIDTH,
    SyntheticScene,
    _as_generator,
    _project,
    look_at_rotations,
    make_scene,
)

MOTIONS = ("general", "planar", "forward", "translation")


def yaw_rotations(angles: np.ndarray) -> np.ndarray:
    """World-to-camera rotations (m, 3, 3) of level cameras yawed by ``angles`` (radians).

    Yaw 0 looks along world +z; a positive yaw turns the optical axis towards +x.
    """
    c, s = np.cos(angles), np.sin(angles)
    zero, one = np.zeros_like(angles), np.ones_like(angles)
    rows_x = np.stack([c, zero, -s], axis=-1)  # camera x axis in world coordinates
    rows_y = np.stack([zero, one, zero], axis=-1)
    rows_z = np.stack([s, zero, c], axis=-1)  # optical axis
    return np.stack([rows_x, rows_y, rows_z], axis=1)


def scene_from_poses(  # noqa: PLR0913 (a scene generator: the poses, points and every knob)
    rotations: np.ndarray,
    centers: np.ndarray,
    points: np.ndarray,
    noise_px: float,
    rng: np.random.Generator,
    intrinsics: np.ndarray | None = None,
    width: int = DEFAULT_WIDTH,
    height: int = DEFAULT_HEIGHT,
    min_depth: float = 0.5,
) -> SyntheticScene:
    """Observe ``points`` (n, 3) from cameras ``rotations`` (m, 3, 3) at ``centers`` (m, 3).

    Points closer than ``min_depth`` or outside an image are not visible there;
    points seen by fewer than two cameras are dropped.
    """
    params = np.asarray(DEFAULT_INTRINSICS if intrinsics is None else intrinsics, dtype=float)
    K = intrinsics_matrix(params)
    translations = -np.einsum("mij,mj->mi", rotations, centers)
    pixels, depth = _project(K, rotations, translations, points)
    visible = (
        (depth > min_depth)
        & (pixels[..., 0] >= 0)
        & (pixels[..., 0] <= width)
        & (pixels[..., 1] >= 0)
        & (pixels[..., 1] <= height)
    )
    keep = visible.sum(axis=0) >= 2
    pixels, visible, points = pixels[:, keep], visible[:, keep], points[keep]
    observations = pixels + rng.uniform(-noise_px, noise_px, size=pixels.shape)
    observations[~visible] = 0.0  # never observed: keep the array finite
    n = len(points)
    return SyntheticScene(
        K=K,
        intrinsics=params.copy(),
        rotations=rotations,
        translations=translations,
        points=points,
        observations=observations,
        outliers=np.zeros(n, dtype=bool),
        outlier_views=np.full(n, -1),
        width=width,
        height=height,
        visible=visible,
    )


def forward_driving(
    num_images: int = 10,
    noise_px: float = 0.5,
    seed: int | np.random.Generator | None = 0,
    yaw_deg: float = 3.0,
    step: float = 1.5,
    num_points: int = 4000,
) -> SyntheticScene:
    """A car driving down a street: forward steps of ``step`` m, yaw within ±``yaw_deg``.

    The camera is level, 1.5 m above the road; points lie on building fronts 4–10 m
    to either side (up to 6 m above the camera), on the road, and 5–80 m ahead.
    """
    rng = _as_generator(seed)
    phase = np.linspace(0.0, np.pi, num_images)
    yaws = np.deg2rad(yaw_deg) * np.sin(phase) + rng.normal(0.0, np.deg2rad(0.2), num_images)
    centers = np.stack(
        [rng.normal(0.0, 0.05, num_images), np.zeros(num_images), step * np.arange(num_images)],
        axis=1,
    )
    facades = num_points * 3 // 4
    side = rng.choice([-1.0, 1.0], facades)
    facade_points = np.stack(
        [
            side * rng.uniform(4.0, 10.0, facades),
            rng.uniform(-6.0, 1.5, facades),
            rng.uniform(5.0, 80.0, facades),
        ],
        axis=1,
    )
    road = num_points - facades
    road_points = np.stack(
        [rng.uniform(-4.0, 4.0, road), np.full(road, 1.5), rng.uniform(3.0, 40.0, road)], axis=1
    )
    points = np.concatenate([facade_points, road_points])
    return scene_from_poses(yaw_rotations(yaws), centers, points, noise_px, rng)


def driving_turn(
    num_images: int = 12,
    noise_px: float = 0.5,
    seed: int | np.random.Generator | None = 0,
    turn_deg: float = 90.0,
    length: float = 24.0,
    radius: float = 8.0,
    num_points: int = 8000,
) -> SyntheticScene:
    """A car driving ``length`` m that turns right by ``turn_deg`` on an arc of ``radius`` m.

    The path is straight, then the arc (centred on the path), then straight again;
    frames are equally spaced along it, the camera level and looking along the
    path (±0.2° jitter). Points lie on building fronts 4–10 m to either side of the
    path (up to 6 m above the camera) and on the road. All rotations are about the
    vertical axis, so fy is still not determined (planar motion).
    """
    rng = _as_generator(seed)
    turn = np.deg2rad(turn_deg)
    arc = radius * turn
    straight = max(0.0, (length - arc) / 2.0)

    def pose_at(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (n, 3) and headings (n,) at arc lengths ``s`` (n,)."""
        phi = np.clip((s - straight) / radius, 0.0, turn)
        before = np.minimum(s, straight)
        after = np.maximum(s - straight - arc, 0.0)
        x = radius * (1.0 - np.cos(phi)) + after * np.sin(turn)
        z = before + radius * np.sin(phi) + after * np.cos(turn)
        return np.stack([x, np.zeros_like(s), z], axis=1), phi

    centers, headings = pose_at(np.linspace(0.0, 2 * straight + arc, num_images))
    yaws = headings + rng.normal(0.0, np.deg2rad(0.2), num_images)
    s = rng.uniform(-5.0, 2 * straight + arc + 30.0, num_points)
    base, heading = pose_at(s)
    right = np.stack([np.cos(heading), np.zeros_like(s), -np.sin(heading)], axis=1)
    facade = rng.random(num_points) < 0.75
    side = rng.choice([-1.0, 1.0], num_points)
    lateral = np.where(
        facade, side * rng.uniform(4.0, 10.0, num_points), rng.uniform(-4.0, 4.0, num_points)
    )
    height = np.where(facade, rng.uniform(-6.0, 1.5, num_points), 1.5)
    points = base + lateral[:, None] * right
    points[:, 1] = height
    return scene_from_poses(yaw_rotations(yaws), centers, points, noise_px, rng)


def planar_orbit(
    num_images: int = 8,
    noise_px: float = 0.5,
    seed: int | np.random.Generator | None = 0,
    arc_deg: float = 80.0,
    radius: float = 6.0,
    num_points: int = 3000,
) -> SyntheticScene:
    """A level camera on an arc of ``arc_deg`` around a 3 m cube, at constant height."""
    rng = _as_generator(seed)
    angles = np.deg2rad(np.linspace(-arc_deg / 2, arc_deg / 2, num_images))
    axes = np.stack([np.sin(angles), np.zeros(num_images), np.cos(angles)], axis=1)
    centers = -radius * axes
    rotations = yaw_rotations(angles + rng.normal(0.0, np.deg2rad(1.0), num_images))
    points = rng.uniform(-1.5, 1.5, size=(num_points, 3))
    return scene_from_poses(rotations, centers, points, noise_px, rng)


def pure_translation(
    num_images: int = 8,
    noise_px: float = 0.5,
    seed: int | np.random.Generator | None = 0,
    num_points: int = 3000,
) -> SyntheticScene:
    """Cameras with one orientation, moved within a 2 m cube, facing points 6–12 m away."""
    rng = _as_generator(seed)
    rotations = np.broadcast_to(np.eye(3), (num_images, 3, 3)).copy()
    centers = rng.uniform(-1.0, 1.0, size=(num_images, 3))
    points = rng.uniform([-3.0, -2.0, 6.0], [3.0, 2.0, 12.0], size=(num_points, 3))
    return scene_from_poses(rotations, centers, points, noise_px, rng)


#: A VGA phone-like camera (63° horizontal field of view), principal point off centre.
HANDHELD_INTRINSICS = np.array([525.0, 525.0, 316.4, 243.1])


def handheld_indoor(
    num_images: int = 17,
    noise_px: float = 1.0,
    seed: int | np.random.Generator | None = 0,
    walk: float = 0.5,
    num_points: int = 300,
) -> SyntheticScene:
    """A handheld 640x480 camera walked ``walk`` m across a room, looking at one corner.

    The camera stays 1.4–1.6 m high, moves along a slight arc and aims at points
    of the far corner (two walls 3–4.5 m away and furniture in front of them), with
    ±4° pitch and ±3° roll of an unsteady hand. Few, noisy tracks (uniform
    ±``noise_px``) and a short baseline: a small handheld set
    (docs/hard_scenes.md).
    """
    rng = _as_generator(seed)
    along = np.linspace(-walk / 2, walk / 2, num_images)
    centers = np.stack([along, rng.uniform(-0.1, 0.1, num_images), 0.15 * along**2], axis=1)
    walls = num_points * 2 // 3
    left = rng.random(walls) < 0.5
    depth = rng.uniform(0.0, 1.5, walls)
    wall_points = np.where(
        left[:, None],
        np.stack([np.full(walls, -1.8), rng.uniform(-1.2, 1.3, walls), 3.0 + depth], axis=1),
        np.stack([-1.8 + 2.4 * depth, rng.uniform(-1.2, 1.3, walls), np.full(walls, 4.5)], axis=1),
    )
    furniture = rng.uniform([-1.5, 0.0, 2.2], [0.8, 1.3, 4.2], size=(num_points - walls, 3))
    points = np.concatenate([wall_points, furniture])
    aim = np.array([-0.4, 0.0, 3.8]) + rng.normal(0.0, 0.3, (num_images, 3))
    pitch = rng.uniform(-np.deg2rad(4.0), np.deg2rad(4.0), num_images)
    directions = aim - centers
    directions[:, 1] += np.tan(pitch) * np.linalg.norm(directions, axis=1)
    rolls = rng.uniform(-np.deg2rad(3.0), np.deg2rad(3.0), num_images)
    return scene_from_poses(
        look_at_rotations(directions, rolls),
        centers,
        points,
        noise_px,
        rng,
        intrinsics=HANDHELD_INTRINSICS,
        width=640,
        height=480,
    )


def general_motion(
    num_images: int = 8,
    noise_px: float = 0.5,
    seed: int | np.random.Generator | None = 0,
    num_points: int = 1500,
) -> SyntheticScene:
    """Cameras in general position around a cube of points (every point in every view)."""
    scene = make_scene(num_points, num_images, noise_px, 0.0, seed)
    scene.visible = np.ones((num_images, num_points), dtype=bool)
    return scene


def motion_scene(
    motion: str, num_images: int = 8, noise_px: float = 0.5, seed: int = 0
) -> SyntheticScene:
    """One of :data:`MOTIONS` by name."""
    makers: dict[str, Callable[..., SyntheticScene]] = {
        "general": general_motion,
        "planar": planar_orbit,
        "forward": forward_driving,
        "translation": pure_translation,
    }
    if motion not in makers:
        raise ValueError(f"unknown motion {motion!r} (choose from {MOTIONS})")
    return makers[motion](num_images=num_images, noise_px=noise_px, seed=seed)
