"""The calibrated bundle adjustment of the agreeing triplets (intrinsics/triplet_bundle.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from colmap_trifocal import CalibrationOptions, calibrate_contents
from colmap_trifocal.geometry.tensor_estimation import TripletTensor
from colmap_trifocal.geometry.trifocal import normalize_tensor, tensor_from_cameras
from colmap_trifocal.intrinsics.polish import calibrated_tracks
from colmap_trifocal.intrinsics.polish.calibrated_tracks import (
    Observed,
    calibrated_cameras,
    triangulate,
)
from colmap_trifocal.intrinsics.polish.camera_setup import Refined, pycolmap_camera_setup
from colmap_trifocal.intrinsics.polish.shared_camera import SharedCamera, agree_and_adjust
from colmap_trifocal.intrinsics.solve.parametrization import FULL, SINGLE_FOCAL, FreeParameters
from colmap_trifocal.synthetic.database import scene_contents
from colmap_trifocal.synthetic.facade import facade_scene


def _relative_cameras(scene, views: tuple[int, int, int]) -> np.ndarray:
    """True calibrated cameras (3, 3, 4) of the views, relative to the first."""
    R1, t1 = scene.rotations[views[0]], scene.translations[views[0]]
    cameras = [np.eye(3, 4)]
    for view in views[1:]:
        R = scene.rotations[view] @ R1.T
        cameras.append(np.hstack([R, (scene.translations[view] - R @ t1)[:, None]]))
    return np.stack(cameras)


def _true_tensor(cameras: np.ndarray, seen: np.ndarray, sigma_px: float = 1.0) -> TripletTensor:
    """A tensor of the true calibrated cameras (3, 3, 4) over the tracks ``seen`` (all inliers)."""
    return TripletTensor(
        image_ids=(1, 2, 3),
        tensor=normalize_tensor(tensor_from_cameras(cameras[1], cameras[2])),
        P2=cameras[1],
        P3=cameras[2],
        camera_covariance=np.eye(24),
        num_tracks=int(seen.sum()),
        num_inliers=int(seen.sum()),
        sigma_px=sigma_px,
        inliers=np.ones(int(seen.sum()), dtype=bool),
    )


def test_calibrated_cameras_recover_the_true_relative_poses():
    scene = facade_scene(relief=0.3, seed=0, noise_px=0.0, num_points=400)
    views = (0, 3, 6)
    seen = np.all(scene.visible[list(views)], axis=0) & ~scene.outliers
    truth = scene.intrinsics
    pixels = scene.observations[list(views)][:, seen]
    normalised = (pixels - truth[2:]) / truth[:2]
    cameras = _relative_cameras(scene, views)
    # Projective cameras: any scale.
    tensor = replace(_true_tensor(cameras, seen), P2=cameras[1] * 3.0, P3=cameras[2] * -0.5)
    found = calibrated_cameras(tensor, normalised, truth, truth)
    assert found is not None
    for view in (1, 2):
        np.testing.assert_allclose(found[view][:, :3], cameras[view][:, :3], atol=1e-6)
    # Translations agree up to one common scale (the baseline of views 1-2 is unit).
    scale = np.linalg.norm(cameras[1][:, 3])
    np.testing.assert_allclose(found[1][:, 3] * scale, cameras[1][:, 3], atol=1e-6)
    np.testing.assert_allclose(found[2][:, 3] * scale, cameras[2][:, 3], atol=1e-5)
    # Triangulated points reproject onto the tracks.
    points = triangulate(found, normalised)
    projected = points @ found[2][:, :3].T + found[2][:, 3]
    np.testing.assert_allclose(projected[:, :2] / projected[:, 2:], normalised[2], atol=1e-8)


@pytest.mark.parametrize(
    ("free_parameters", "expected"),
    [
        (FULL, ("PINHOLE", True, True)),
        (SINGLE_FOCAL, ("SIMPLE_PINHOLE", True, True)),
        (FreeParameters("held"), ("PINHOLE", False, True)),
        (FreeParameters("free", cx=False, cy=False), ("PINHOLE", True, False)),
        (FreeParameters("free", cx=True, cy=False), None),
        (FreeParameters("held", cx=False, cy=False), None),
    ],
)
def test_camera_setup_follows_the_free_parameters(free_parameters, expected):
    setup = pycolmap_camera_setup(free_parameters)
    if expected is None:
        assert setup is None
    else:
        assert setup is not None
        assert (setup.model, setup.refined.focal, setup.refined.principal_point) == expected
        assert not setup.refined.distortion


def _facade_run(triplet_bundle: bool, seed: int = 3):
    scene = facade_scene(relief=0.01, seed=seed, noise_px=1.0, num_points=1000)
    truth = scene.intrinsics
    signs = np.random.default_rng(seed + 99).choice([-1.0, 1.0], 4)
    prior = tuple(truth * (1.0 + 0.05 * signs))
    options = CalibrationOptions(prior=prior, seed=seed, triplet_bundle=triplet_bundle)
    (result,) = calibrate_contents(scene_contents(scene), options)
    return float(np.abs(result.intrinsics / truth - 1.0).mean() * 100.0), result


def test_planar_facade_polished_to_the_general_scene_accuracy():
    """1 % relief, seeds 2–4: 13–19 of 20 tensors agree on the constraints alone
    (0.15–0.21 %); the polish brings every one to 0.05–0.10 % (mean 0.070 %; over
    seeds 0–5 0.061 % against 0.126 %). Seed 3 in detail: the constraint estimate the
    polish started from is reported, and the std covers."""
    polished, constraints_only, runs = [], [], {}
    for seed in (2, 3, 4):
        after, result = _facade_run(True, seed)
        before_error, before = _facade_run(False, seed)
        assert result.triplet_bundle["used"] and before.triplet_bundle is None
        assert result.num_inlier_triplets >= 18 and after < before_error, seed
        polished.append(after)
        constraints_only.append(before_error)
        runs[seed] = (result, before)
    assert np.mean(polished) < 0.08  # the general scene (30 % relief) is at 0.02-0.04 %
    assert np.mean(polished) < 0.6 * np.mean(constraints_only)
    result, before = runs[3]
    started = np.array(list(result.triplet_bundle["constraints"].values()))
    np.testing.assert_allclose(started, before.intrinsics, rtol=1e-9)
    truth = facade_scene(relief=0.01, seed=3, noise_px=1.0, num_points=1000).intrinsics
    for index, name in enumerate(("fx", "fy", "cx", "cy")):
        std = result.std[name]
        if std is None:  # fy tied to fx where the triplets cannot tell them apart
            assert result.source[name] == "tied" and result.fy == result.fx
        else:
            assert abs(result.intrinsics[index] - truth[index]) < 2 * std, name


def test_triangulate_is_the_least_singular_vector_of_the_dlt() -> None:
    """On noisy tracks in three views: the DLT's least-squares point (its SVD)."""
    rng = np.random.default_rng(3)
    cameras = np.stack([np.eye(3, 4)] * 3)
    cameras[1, :, 3], cameras[2, :, 3] = [1.0, 0.1, 0.0], [2.0, -0.1, 0.2]
    points = rng.normal(size=(200, 3)) + [0.0, 0.0, 6.0]
    seen = np.einsum("vij,nj->vni", cameras[:, :, :3], points) + cameras[:, None, :, 3]
    x = seen[..., :2] / seen[..., 2:] + rng.normal(scale=1e-3, size=(3, 200, 2))
    rows = np.concatenate(
        [
            x[..., 0:1] * cameras[:, None, 2] - cameras[:, None, 0],
            x[..., 1:2] * cameras[:, None, 2] - cameras[:, None, 1],
        ],
        axis=0,
    )
    least = np.linalg.svd(np.swapaxes(rows, 0, 1))[2][:, -1]
    np.testing.assert_allclose(triangulate(cameras, x), least[:, :3] / least[:, 3:], atol=1e-9)


@pytest.mark.parametrize("views", [(0, 3, 6), (1, 2, 4), (2, 5, 9)])
def test_calibrated_cameras_voted_by_a_subset_are_those_every_track_votes(
    views: tuple[int, int, int], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``CHEIRALITY_TRACKS`` evenly spaced tracks choose each essential matrix's
    decomposition as all of them do: the same cameras, on noisy tracks at a K 3 % off."""
    scene = facade_scene(relief=0.3, seed=1, noise_px=0.5, num_points=1500)
    seen = np.all(scene.visible[list(views)], axis=0) & ~scene.outliers
    assert seen.sum() > 3 * calibrated_tracks.CHEIRALITY_TRACKS
    truth = scene.intrinsics
    K = truth * np.array([1.03, 1.03, 1.0, 1.0]) + np.array([0.0, 0.0, 8.0, -6.0])
    normalised = (scene.observations[list(views)][:, seen] - K[2:]) / K[:2]
    cameras = _relative_cameras(scene, views)
    tensor = _true_tensor(cameras, seen, sigma_px=0.5)
    subset = calibrated_cameras(tensor, normalised, truth, K)
    monkeypatch.setattr(calibrated_tracks, "CHEIRALITY_TRACKS", 10**9)
    everything = calibrated_cameras(tensor, normalised, truth, K)
    assert subset is not None and everything is not None
    np.testing.assert_array_equal(subset, everything)


class _CountingCamera(SharedCamera):
    """A shared camera that records the triplets each of its solves adjusted."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.solved: list[list[int]] = []

    def solve(self, which: list[int], refined: Refined, **kwargs):
        self.solved.append(list(which))
        return super().solve(which, refined, **kwargs)


def _jointly_adjusted_facade(behind: int | None = None) -> tuple[_CountingCamera, np.ndarray]:
    """Four triplets of a noisy facade in one shared camera started 3 % from the truth,
    adjusted together with the camera free; and the truth (fx, fy, cx, cy). The triplet
    ``behind`` (if any) is added with its calibrated cameras' translations reversed
    (the wrong decomposition: its points triangulate behind the cameras) and left out
    of that adjustment."""
    scene = facade_scene(relief=0.3, seed=2, noise_px=0.5, num_points=1500)
    truth = scene.intrinsics
    start = truth * np.array([1.03, 1.03, 1.0, 1.0])
    shared = _CountingCamera(start, "PINHOLE", scene.width, scene.height)
    for index, views in enumerate([(0, 3, 6), (1, 4, 7), (2, 5, 8), (3, 6, 9)]):
        seen = np.all(scene.visible[list(views)], axis=0) & ~scene.outliers
        pixels = scene.observations[list(views)][:, seen]
        n = pixels.shape[1]
        tensor = _true_tensor(_relative_cameras(scene, views), seen, sigma_px=0.5)
        observed = Observed(index, tensor, pixels, 0.25 * (3 * n - 18), 0.25)
        cameras = calibrated_cameras(tensor, (pixels - start[2:]) / start[:2], truth, start)
        assert cameras is not None
        if index == behind:
            cameras[1:, :, 3] *= -1.0
        shared.add(observed, cameras)
    everything = [p for p in range(len(shared.triplets)) if p != behind]
    assert shared.adjust(everything, Refined(focal=True, principal_point=True))
    shared.solved.clear()
    return shared, truth


def test_triplets_adjusted_with_the_camera_are_not_adjusted_again() -> None:
    """After a joint adjustment every triplet is at its own optimum for that camera, and
    the camera at its optimum for them: where they all agree, the rounds told so run no
    solve at all (neither one by one nor together) and reach the same camera and
    agreement as rounds that redo both."""
    refined = Refined(focal=True, principal_point=True)
    told, truth = _jointly_adjusted_facade()
    fresh, _ = _jointly_adjusted_facade()
    everything = list(range(len(told.triplets)))
    limit = 1e6  # every triplet agrees
    skipped = agree_and_adjust(told, limit, refined, adjusted=everything)
    redone = agree_and_adjust(fresh, limit, refined)
    assert skipped is not None and redone is not None
    assert skipped.agreeing == redone.agreeing == everything
    # The fresh rounds adjust each triplet alone, then all together; the told ones stop.
    assert fresh.solved == [[p] for p in everything] + [everything]
    assert told.solved == []
    np.testing.assert_allclose(told.intrinsics(), fresh.intrinsics(), rtol=1e-7)
    np.testing.assert_allclose(skipped.ratios, redone.ratios, atol=1e-3)
    assert np.abs(told.intrinsics() / truth - 1).max() < 0.01


def test_a_triplet_with_a_point_behind_its_cameras_is_not_adjusted_and_never_agrees() -> None:
    """Its λ is inf from the start; the rounds adjust and choose from the others."""
    shared, truth = _jointly_adjusted_facade(behind=1)
    assert not shared.triplets[1].in_front
    assert not np.isfinite(shared.ratios()[1])
    agreement = agree_and_adjust(shared, 1e6, Refined(focal=True, principal_point=True))
    assert agreement is not None
    assert [1] not in shared.solved
    assert [[0], [2], [3]] == shared.solved[:3]
    assert agreement.agreeing == [0, 2, 3]
    assert not np.isfinite(agreement.ratios[1])
    assert np.abs(shared.intrinsics() / truth - 1).max() < 0.01


def test_a_triplet_carried_behind_its_cameras_is_marked_and_left_out() -> None:
    """A triplet whose points an adjustment carried behind its cameras leaves the
    adjusted set: it is marked as such, its λ is inf, and the rounds neither adjust it
    alone nor choose it."""
    shared, truth = _jointly_adjusted_facade()
    everything = list(range(len(shared.triplets)))
    assert shared.still_in_front(everything) == everything
    moved = shared.triplets[2]
    for point_id in moved.point_ids[:5]:  # five points mirrored through the first camera
        point = shared.reconstruction.points3D[int(point_id)]
        point.xyz = -point.xyz
    shared.reconstruction = shared.reconstruction  # forget the points as read
    assert shared.still_in_front(everything) == [0, 1, 3]
    assert not moved.in_front and all(shared.triplets[p].in_front for p in (0, 1, 3))
    assert not np.isfinite(shared.ratios()[2])
    agreement = agree_and_adjust(shared, 1e6, Refined(focal=True, principal_point=True))
    assert agreement is not None and agreement.agreeing == [0, 1, 3]
    assert [2] not in shared.solved
    assert np.abs(shared.intrinsics() / truth - 1).max() < 0.01
