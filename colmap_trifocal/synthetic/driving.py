"""Synthetic driving sequences with a KITTI-like camera, straight or with a turn.

A car drives ``num_images`` frames of ``step`` m along a street: a straight leg,
then (``turn_deg`` ≠ 0) an arc of radius ``turn_radius`` turning right by
``turn_deg``, then a straight leg again. The camera looks along the direction of
travel (yaw jitter 0.3°, pitch jitter 0.3°), 1.5 m above the road. Building fronts
line the street 4–10 m to either side (up to 6 m above the camera), and the road
carries texture, everywhere along the path and 40 m beyond its ends.

Conventions as in :mod:`.motions` (world y down, yaw about it, world-to-camera
poses, COLMAP pixels, metres). Default camera: KITTI's grey camera, 1241 x 376,
f = 718.856 px.
"""

from __future__ import annotations

import numpy as np

from .motions import scene_from_poses, yaw_rotations
from .scenes import SyntheticScene, _as_generator

#: KITTI odometry camera 0 (fx, fy, cx, cy) in COLMAP's pixel convention, 1241 x 376.
KITTI_INTRINSICS = np.array([718.856, 718.856, 607.6928, 185.7157])
KITTI_WIDTH = 1241
KITTI_HEIGHT = 376


def _path(
    length: np.ndarray, first_leg: float, turn: float, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Positions (k, 3) and headings (k,) (radians, yaw) at arc lengths ``length`` (k,).

    Straight along +z up to ``first_leg``, then an arc of ``radius`` turning by
    ``turn`` (radians, positive: right, towards +x), then straight on.
    """
    arc = radius * abs(turn)
    side = np.sign(turn) if turn else 1.0
    s1 = np.clip(length, None, first_leg)
    s2 = np.clip(length - first_leg, 0.0, arc)
    s3 = np.clip(length - first_leg - arc, 0.0, None)
    heading = side * s2 / radius
    # Arc: centre at (side · radius, first_leg) in (x, z).
    x = side * radius * (1.0 - np.cos(heading * side))
    z = s1 + radius * np.sin(heading * side)
    x = x + s3 * np.sin(heading)
    z = z + s3 * np.cos(heading)
    return np.stack([x, np.zeros_like(x), z], axis=1), heading


def _street_points(
    num_points: int,
    total: float,
    first_leg: float,
    turn: float,
    turn_radius: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """(n, 3) points on the facades and the road along the path (see
    :func:`driving_sequence`), ``total`` m of it driven."""
    # Points along the street, from 10 m before the start to 40 m beyond the end.
    along = rng.uniform(-10.0, total + 40.0, num_points)
    base, heading = _path(along, first_leg, turn, turn_radius)
    normal = np.stack([np.cos(heading), np.zeros_like(heading), -np.sin(heading)], axis=1)
    facades = num_points * 3 // 4
    lateral = np.concatenate(
        [
            rng.choice([-1.0, 1.0], facades) * rng.uniform(4.0, 10.0, facades),
            rng.uniform(-4.0, 4.0, num_points - facades),
        ]
    )
    heights = np.concatenate([rng.uniform(-6.0, 1.5, facades), np.full(num_points - facades, 1.5)])
    points = base + lateral[:, None] * normal
    points[:, 1] = heights
    return points


def _shaky_rotations(headings: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """World-to-camera rotations (m, 3, 3) looking along ``headings`` (rad), yaw and pitch
    jittered by 0.3°."""
    num_images = len(headings)
    yaws = headings + rng.normal(0.0, np.deg2rad(0.3), num_images)
    rotations = yaw_rotations(yaws)
    pitch = rng.normal(0.0, np.deg2rad(0.3), num_images)
    c, s = np.cos(pitch), np.sin(pitch)
    tilt = np.zeros((num_images, 3, 3))
    tilt[:, 0, 0] = 1.0
    tilt[:, 1, 1], tilt[:, 1, 2], tilt[:, 2, 1], tilt[:, 2, 2] = c, -s, s, c
    return tilt @ rotations


def driving_sequence(  # noqa: PLR0913 (a scene generator: every knob a keyword with a default)
    num_images: int = 50,
    turn_deg: float = 0.0,
    noise_px: float = 0.5,
    seed: int | np.random.Generator | None = 0,
    step: float = 1.0,
    turn_radius: float = 12.0,
    num_points: int = 12000,
    intrinsics: np.ndarray | None = None,
    width: int = KITTI_WIDTH,
    height: int = KITTI_HEIGHT,
) -> SyntheticScene:
    """A drive of ``num_images`` frames, ``step`` m apart, turning by ``turn_deg`` midway.

    Args:
        num_images: frames.
        turn_deg: total turn (degrees, positive: right); 0 is a straight drive.
        noise_px: half-width of the uniform pixel noise, pixels.
        seed: int seed or a numpy Generator.
        step: distance between frames along the path, metres.
        turn_radius: radius of the turn, metres.
        num_points: points drawn along the street (those seen by fewer than 2
            frames are dropped).
        intrinsics: (fx, fy, cx, cy), pixels; default :data:`KITTI_INTRINSICS`.
        width, height: image size, pixels.
    """
    rng = _as_generator(seed)
    turn = np.deg2rad(turn_deg)
    total = step * (num_images - 1)
    arc = turn_radius * abs(turn)
    first_leg = max((total - arc) / 2.0, 0.0)
    centers, headings = _path(step * np.arange(num_images), first_leg, turn, turn_radius)
    centers[:, 0] += rng.normal(0.0, 0.05, num_images)
    points = _street_points(num_points, total, first_leg, turn, turn_radius, rng)
    return scene_from_poses(
        _shaky_rotations(headings, rng),
        centers,
        points,
        noise_px,
        rng,
        intrinsics=KITTI_INTRINSICS if intrinsics is None else intrinsics,
        width=width,
        height=height,
        min_depth=1.0,
    )
