"""A triplet's tracks as calibrated cameras at K see them.

For a tensor (cameras ``P2``, ``P3`` of its ML projective fit, in coordinates
normalised by the start K0) and a camera K: the essential matrices ``E = [a]ₓ A`` of
``K⁻¹ K0 [A | a]`` (view 1 is ``[I | 0]``), decomposed by cheirality
(:func:`geometry.motion.recover_pose`, on up to ``CHEIRALITY_TRACKS`` of the tracks),
view 3's baseline scale by linear least squares on the tracks triangulated from views
1–2, and the tracks triangulated from all three views. The projective fit's own cost
is the reference the calibrated fit's likelihood ratio is measured against. Pixels in
COLMAP's convention.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ...common.parallel import MIN_FORKED_JOBS, map_jobs
from ...common.sampling import evenly_spaced
from ...geometry.motion import recover_pose
from ...geometry.projective_ba import refined_cost
from ...geometry.tensor_estimation import TripletTensor
from ...geometry.trifocal import intrinsics_matrix

#: Tracks per triplet at most (evenly spaced among its inliers): as many as the
#: tensor's own refinement uses (``TensorEstimationOptions.max_refined_tracks``). Fewer
#: cost the polish its efficiency where noise is all there is: at 400, the synthetic
#: three-view cube's error rose from the bundle-adjustment floor to 1.14 times it, and
#: one of entry-P10's runs left its std (docs/accuracy.md, eighteenth session).
MAX_TRACKS = 500
#: The projective fit that λ is measured against starts at the tensor's cameras,
#: already the ML fit of (up to 500 of) these tracks: a few iterations converge.
PROJECTIVE_ITERATIONS = 20
#: The projective refinement's relative cost decrease at which it stops.
PROJECTIVE_TOLERANCE = 1e-9
#: Unknowns of a projective triplet beyond its points (two 3x4 cameras, less gauge).
PROJECTIVE_PARAMETERS = 18
#: Tracks (evenly spaced) whose cheirality chooses among an essential matrix's four
#: decompositions: where the chosen one has at least ``DECISIVE_SHARE`` of them in front
#: of both cameras (the others then have few), a hundred choose as all 500 would, at a
#: fifth of the cost; a vote less clear (a K far off, a lens's bent tracks) is
#: taken again on every track.
CHEIRALITY_TRACKS = 100
DECISIVE_SHARE = 0.9


def calibrated_cameras(
    tensor: TripletTensor, x: np.ndarray, start: np.ndarray, intrinsics: np.ndarray
) -> np.ndarray | None:
    """Calibrated cameras (3, 3, 4) ``[R | t]`` of a tensor's views under K, view 1 ``[I|0]``.

    Args:
        tensor: its ``P2``, ``P3`` are in coordinates normalised by ``start``.
        x: the triplet's inlier tracks (3, n, 2) normalised by ``intrinsics``.
        start: (fx0, fy0, cx0, cy0) of the tensor's normalisation, pixels.
        intrinsics: (fx, fy, cx, cy) of K, pixels.

    Returns None when OpenCV cannot decompose an essential matrix.
    """
    M = np.linalg.solve(intrinsics_matrix(start), intrinsics_matrix(intrinsics))  # K0⁻¹ K
    M_inverse = np.linalg.inv(M)
    voters = x[:, evenly_spaced(x.shape[1], CHEIRALITY_TRACKS)]
    poses = []
    for view, P in ((1, tensor.P2), (2, tensor.P3)):
        A, a = M_inverse @ P[:, :3] @ M, M_inverse @ P[:, 3]
        essential = np.cross(a, A, axisa=0, axisb=0, axisc=0)  # [a]ₓ A
        essential = essential / np.linalg.norm(essential)
        try:
            count, R, t, _ = recover_pose(essential, voters[0], voters[view])
            if count < DECISIVE_SHARE * voters.shape[1] and voters.shape[1] < x.shape[1]:
                count, R, t, _ = recover_pose(essential, x[0], x[view])
        except cv2.error:
            return None
        if count == 0:
            return None
        poses.append((R, t))
    (R2, t2), (R3, t3) = poses
    cameras = np.stack([np.eye(3, 4), np.hstack([R2, t2[:, None]]), np.eye(3, 4)])
    points = triangulate(cameras[:2], x[:2])
    # View 3's baseline scale s: x3 ∥ R3 X + s t3, least squares over the tracks.
    rays = np.concatenate([x[2], np.ones((x.shape[1], 1))], axis=1)
    rotated = np.cross(rays, points @ R3.T)
    baseline = np.cross(rays, np.broadcast_to(t3, rays.shape))
    scale = -np.sum(rotated * baseline) / max(float(np.sum(baseline * baseline)), 1e-300)
    cameras[2] = np.hstack([R3, scale * t3[:, None]])
    return cameras


def triangulate(cameras: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Points (n, 3) from normalised tracks x (v, n, 2) and cameras (v, 3, 4) (linear DLT).

    Each point's homogeneous coordinates are the least singular vector of its DLT rows
    A (2v, 4), taken as the least eigenvector of AᵀA (4, 4): the same vector, and half
    the cost of an SVD of every A.
    """
    rows = np.concatenate(
        [
            x[..., 0:1] * cameras[:, None, 2] - cameras[:, None, 0],
            x[..., 1:2] * cameras[:, None, 2] - cameras[:, None, 1],
        ],
        axis=0,
    )  # (2v, n, 4)
    A = np.swapaxes(rows, 0, 1)
    homogeneous = np.linalg.eigh(np.swapaxes(A, 1, 2) @ A)[1][..., 0]
    w = homogeneous[:, 3:]
    return homogeneous[:, :3] / np.where(np.abs(w) > 1e-12, w, 1e-12)


@dataclass
class Observed:
    """A tensor's tracks for the polish and their projective fit (the λ reference)."""

    index: int  # position among the tensors
    tensor: TripletTensor
    pixels: np.ndarray  # (3, n, 2) inlier tracks, pixels
    projective_cost: float  # C_proj, px²
    sigma2: float  # σ² = C_proj / (3n − 18), px²


def observed_tracks(
    tensors: list[TripletTensor],
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    max_tracks: int = MAX_TRACKS,
    workers: int | None = None,
) -> list[Observed]:
    """Each tensor's inlier tracks (at most ``MAX_TRACKS``, evenly spaced) and their
    projective cost, from a projective bundle adjustment warm-started at its cameras
    (over ``workers`` threads, or forked processes from ``MIN_FORKED_JOBS`` tensors;
    None: one per core).

    The tensor's own noise estimate comes from the tracks its last refinement used,
    not these, so C_proj is measured on exactly the tracks λ compares.
    """
    jobs = [(index, tensor, tracks, start, max_tracks) for index, tensor in enumerate(tensors)]
    observed = map_jobs(_observed_job, jobs, workers, processes=len(jobs) >= MIN_FORKED_JOBS)
    return [o for o in observed if o is not None]


def _observed_job(job: tuple[Any, ...]) -> Observed | None:
    return observed_triplet(*job)


def observed_triplet(
    index: int,
    tensor: TripletTensor,
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    max_tracks: int = MAX_TRACKS,
) -> Observed | None:
    """One tensor's :class:`Observed` (the tensor at position ``index``; see
    :func:`observed_tracks`), None where its tracks are too few or its projective fit
    gives no finite cost."""
    pixels = inlier_pixels(tensor, tracks, max_tracks)
    if pixels.shape[1] <= PROJECTIVE_PARAMETERS // 3:
        return None
    squared_errors, sigma = refined_cost(
        (pixels - start[2:]) / start[:2],
        tensor.P2,
        tensor.P3,
        start[:2],
        max_iterations=PROJECTIVE_ITERATIONS,
        tolerance=PROJECTIVE_TOLERANCE,
    )
    cost = float(squared_errors.sum())
    if not (np.isfinite(cost) and sigma > 0):
        return None
    return Observed(index, tensor, pixels, cost, sigma**2)


def inlier_pixels(
    tensor: TripletTensor,
    tracks: dict[tuple[int, int, int], np.ndarray],
    max_tracks: int = MAX_TRACKS,
) -> np.ndarray:
    """A tensor's inlier tracks (3, n, 2) in pixels, at most ``max_tracks`` evenly spaced."""
    pixels = tracks[tensor.image_ids][:, tensor.inliers]
    return pixels[:, evenly_spaced(pixels.shape[1], max_tracks)]
