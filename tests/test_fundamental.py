"""Tests for the FundamentalCalib baseline (Mendonça & Cipolla self-calibration)."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.intrinsics.baselines.essential_cost import EssentialProblem, essential_cost
from colmap_trifocal.intrinsics.baselines.fundamental import (
    FundamentalCalibResult,
    _calibrate,
    _Settings,
    calibrate_from_fundamentals,
)

# Ground-truth intrinsics (pixels) of a 3072 x 2048 camera (COLMAP pixel convention).
TRUE_K = np.array([2759.48, 2764.16, 1520.69, 1006.81])
WIDTH, HEIGHT = 3072, 2048


def kmat(theta: np.ndarray) -> np.ndarray:
    """Calibration matrix of ``theta = (fx, fy, cx, cy)``."""
    fx, fy, cx, cy = theta
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def skew(t: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[t]x``."""
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation about a (not necessarily unit) axis by ``angle`` radians."""
    k = skew(axis / np.linalg.norm(axis))
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * k @ k


def make_scene(
    rng: np.random.Generator, num_cams: int = 7, num_points: int = 600
) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Cameras (world-to-camera ``R, t``: ``x_cam = R X + t``) around a point cloud.

    Camera centres lie ~10 units from the cloud, at viewing directions 10–30° apart; each
    looks at a jittered target near the cloud centre and has a random roll, so optical axes
    do not meet in one point (avoids the critical configuration for focal estimation).
    """
    points = rng.uniform(-2.5, 2.5, size=(num_points, 3))
    rots, trans = [], []
    for _ in range(num_cams):
        tilt = np.deg2rad(rng.uniform(5.0, 22.0))
        azim = rng.uniform(0.0, 2.0 * np.pi)
        direction = np.array(
            [np.sin(tilt) * np.cos(azim), np.sin(tilt) * np.sin(azim), -np.cos(tilt)]
        )
        centre = -rng.uniform(9.0, 12.0) * direction
        target = rng.uniform(-0.8, 0.8, size=3)
        z = target - centre
        z /= np.linalg.norm(z)
        x = np.cross(np.array([0.0, 1.0, 0.0]), z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        r = np.stack([x, y, z])  # rows: camera axes in world
        r = rotation(np.array([0.0, 0.0, 1.0]), rng.uniform(-0.3, 0.3)) @ r  # roll
        rots.append(r)
        trans.append(-r @ centre)
    return rots, trans, points


def relative_pose(
    r1: np.ndarray, t1: np.ndarray, r2: np.ndarray, t2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pose of camera 2 relative to camera 1: ``x2 = R x1 + t``."""
    r = r2 @ r1.T
    return r, t2 - r @ t1


def exact_fundamentals(
    rots: list[np.ndarray], trans: list[np.ndarray], theta: np.ndarray
) -> np.ndarray:
    """``F_ij = K^-T [t]x R K^-1`` for all pairs ``i < j`` as an ``(n, 3, 3)`` stack."""
    kinv = np.linalg.inv(kmat(theta))
    fs = []
    for i in range(len(rots)):
        for j in range(i + 1, len(rots)):
            r, t = relative_pose(rots[i], trans[i], rots[j], trans[j])
            fs.append(kinv.T @ skew(t) @ r @ kinv)
    return np.array(fs)


def project(r: np.ndarray, t: np.ndarray, theta: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel projections ``(m, 2)`` of world points."""
    xc = points @ r.T + t
    xh = xc @ kmat(theta).T
    return xh[:, :2] / xh[:, 2:3]


def eight_point(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Hartley-normalised 8-point algorithm, rank 2 enforced; ``x2ᵀ F x1 = 0``."""

    def normaliser(x: np.ndarray) -> np.ndarray:
        mean = x.mean(axis=0)
        scale = np.sqrt(2.0) / np.mean(np.linalg.norm(x - mean, axis=1))
        return np.array(
            [[scale, 0.0, -scale * mean[0]], [0.0, scale, -scale * mean[1]], [0.0, 0.0, 1.0]]
        )

    t1, t2 = normaliser(x1), normaliser(x2)
    h1 = np.c_[x1, np.ones(len(x1))] @ t1.T
    h2 = np.c_[x2, np.ones(len(x2))] @ t2.T
    a = np.einsum("mi,mj->mij", h2, h1).reshape(len(x1), 9)
    f = np.linalg.svd(a)[2][-1].reshape(3, 3)
    u, s, vt = np.linalg.svd(f)
    f = u @ np.diag([s[0], s[1], 0.0]) @ vt
    return t2.T @ f @ t1


def noisy_fundamentals(
    rng: np.random.Generator,
    rots: list[np.ndarray],
    trans: list[np.ndarray],
    points: np.ndarray,
    theta: np.ndarray,
    noise_px: float = 0.5,
    points_per_pair: int = 300,
) -> tuple[np.ndarray, np.ndarray]:
    """F's from noisy projections (8-point) and their match counts, pairs ``i < j``."""
    proj = [project(r, t, theta, points) for r, t in zip(rots, trans, strict=True)]
    inside = [(p[:, 0] > 0) & (p[:, 0] < WIDTH) & (p[:, 1] > 0) & (p[:, 1] < HEIGHT) for p in proj]
    fs, counts = [], []
    for i in range(len(rots)):
        for j in range(i + 1, len(rots)):
            idx = np.flatnonzero(inside[i] & inside[j])
            idx = rng.choice(idx, size=min(points_per_pair, len(idx)), replace=False)
            x1 = proj[i][idx] + rng.normal(0.0, noise_px, size=(len(idx), 2))
            x2 = proj[j][idx] + rng.normal(0.0, noise_px, size=(len(idx), 2))
            fs.append(eight_point(x1, x2))
            counts.append(len(idx))
    return np.array(fs), np.array(counts, dtype=float)


def corrupt(rng: np.random.Generator, fs: np.ndarray, fraction: float) -> np.ndarray:
    """Replace ``fraction`` of the F's by wrong rank-2 matrices of realistic scale.

    A wrong F is ``K^-T E' K^-1`` (true K) with ``E'`` a random rank-2 matrix whose
    singular values are ``1`` and ``U(0.2, 0.8)``, i.e. clearly not an essential matrix.
    """
    out = fs.copy()
    n_bad = int(round(fraction * len(fs)))
    kinv = np.linalg.inv(kmat(TRUE_K))
    for k in rng.choice(len(fs), size=n_bad, replace=False):
        u = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        v = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        e = u @ np.diag([1.0, rng.uniform(0.2, 0.8), 0.0]) @ v.T
        out[k] = kinv.T @ e @ kinv
    return out


def rel_err(est: np.ndarray, truth: np.ndarray = TRUE_K) -> np.ndarray:
    """Relative error per parameter (fx, fy, cx, cy)."""
    return np.abs(est - truth) / np.abs(truth)


def perturbed_prior(rng: np.random.Generator, truth: np.ndarray = TRUE_K) -> np.ndarray:
    """Prior with every parameter off by a random ±5 %."""
    return truth * (1.0 + rng.choice([-1.0, 1.0], size=4) * rng.uniform(0.03, 0.05, size=4))


@pytest.fixture
def scene() -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    return make_scene(np.random.default_rng(1))


def test_exact_fundamentals_satisfy_epipolar_constraint(scene) -> None:
    rots, trans, points = scene
    fs = exact_fundamentals(rots, trans, TRUE_K)
    x1 = np.c_[project(rots[0], trans[0], TRUE_K, points), np.ones(len(points))]
    x2 = np.c_[project(rots[1], trans[1], TRUE_K, points), np.ones(len(points))]
    f = fs[0] / np.linalg.norm(fs[0])
    residual = np.abs(np.einsum("mi,ij,mj->m", x2, f, x1))
    assert residual.max() < 1e-9


@pytest.mark.parametrize("robust", [False, True])
def test_exact_recovery_all_parameters(scene, robust: bool) -> None:
    rots, trans, _ = scene
    fs = exact_fundamentals(rots, trans, TRUE_K)
    prior = perturbed_prior(np.random.default_rng(2))
    res = calibrate_from_fundamentals(fs, prior, robust=robust)
    assert isinstance(res, FundamentalCalibResult)
    assert res.success
    assert res.num_pairs == len(fs) == 21
    assert res.intrinsics.shape == (4,)
    assert np.max(rel_err(res.intrinsics)) < 1e-6
    assert res.cost < 1e-12


def test_single_focal_recovery(scene) -> None:
    rots, trans, _ = scene
    truth = np.array([2761.0, 2761.0, 1520.69, 1006.81])
    fs = exact_fundamentals(rots, trans, truth)
    prior = np.array([2900.0, 2650.0, 1536.0, 1024.0])
    res = calibrate_from_fundamentals(fs, prior, single_focal=True)
    assert res.success
    assert res.intrinsics[0] == res.intrinsics[1]
    assert np.max(rel_err(res.intrinsics, truth)) < 1e-6


def test_single_focal_returns_equal_focals_when_truth_differs(scene) -> None:
    rots, trans, _ = scene
    fs = exact_fundamentals(rots, trans, TRUE_K)
    res = calibrate_from_fundamentals(fs, TRUE_K * 1.03, single_focal=True)
    assert res.intrinsics[0] == res.intrinsics[1]
    # the common focal lies near the two true ones (they differ by 0.17 %)
    assert abs(res.intrinsics[0] / np.mean(TRUE_K[:2]) - 1.0) < 0.01


@pytest.mark.parametrize("robust", [False, True])
def test_noisy_fundamentals_within_two_percent(scene, robust: bool) -> None:
    rots, trans, points = scene
    rng = np.random.default_rng(3)
    fs, counts = noisy_fundamentals(rng, rots, trans, points, TRUE_K)
    assert counts.min() >= 200
    prior = perturbed_prior(rng)
    res = calibrate_from_fundamentals(fs, prior, weights=counts, robust=robust)
    assert res.success
    assert np.mean(rel_err(res.intrinsics)) < 0.02
    assert np.mean(rel_err(res.intrinsics)) < 0.5 * np.mean(rel_err(prior))
    assert 0.0 < res.cost < essential_cost(fs, prior, counts)


def test_robust_loss_helps_with_wrong_fundamentals(scene) -> None:
    rots, trans, points = scene
    rng = np.random.default_rng(4)
    fs, counts = noisy_fundamentals(rng, rots, trans, points, TRUE_K)
    bad = corrupt(rng, fs, 0.2)
    prior = perturbed_prior(rng)
    plain = calibrate_from_fundamentals(bad, prior, weights=counts, robust=False)
    robust = calibrate_from_fundamentals(bad, prior, weights=counts, robust=True)
    assert robust.success
    assert np.mean(rel_err(robust.intrinsics)) < 0.02
    assert np.mean(rel_err(robust.intrinsics)) < np.mean(rel_err(plain.intrinsics))


def test_cost_vanishes_at_truth_and_grows_when_perturbed(scene) -> None:
    rots, trans, _ = scene
    fs = exact_fundamentals(rots, trans, TRUE_K)
    at_truth = essential_cost(fs, TRUE_K)
    assert at_truth < 1e-20
    for k in range(4):
        theta = TRUE_K.copy()
        theta[k] *= 1.02
        assert essential_cost(fs, theta) > 1e-6 > at_truth
    # the alternative normalisation also vanishes at the truth
    assert essential_cost(fs, TRUE_K, form="normalized") < 1e-20
    # the cost does not depend on the scale of F
    theta = TRUE_K * 1.05
    assert essential_cost(fs * 1e5, theta) == pytest.approx(essential_cost(fs, theta), rel=1e-9)


@pytest.mark.parametrize("form", ["ratio", "normalized"])
@pytest.mark.parametrize("single_focal", [False, True])
def test_analytic_jacobian_matches_finite_differences(scene, form, single_focal) -> None:
    rots, trans, _ = scene
    rng = np.random.default_rng(5)
    g = rng.normal(size=(6, 3, 3))
    sqrt_w = rng.uniform(0.5, 2.0, size=6)
    problem = EssentialProblem(g, sqrt_w, single_focal, form)
    x = np.array([1.05, 0.03, -0.02]) if single_focal else np.array([1.05, 0.97, 0.03, -0.02])
    jac = problem.jacobian(x)
    h = 1e-6
    num = np.empty_like(jac)
    for p in range(len(x)):
        dx = np.zeros_like(x)
        dx[p] = h
        rp = problem.residuals(x + dx)
        rm = problem.residuals(x - dx)
        num[:, p] = (rp - rm) / (2.0 * h)
    np.testing.assert_allclose(jac, num, rtol=1e-5, atol=1e-7)


def test_normalized_form_recovers_exact_intrinsics(scene) -> None:
    rots, trans, _ = scene
    fs = exact_fundamentals(rots, trans, TRUE_K)
    settings = _Settings(single_focal=False, form="normalized", loss="linear", f_scale=1.0)
    res = _calibrate(fs, TRUE_K * 0.96, None, settings)
    assert np.max(rel_err(res.intrinsics)) < 1e-6


def test_zero_weight_pairs_are_ignored(scene) -> None:
    rots, trans, _ = scene
    fs = exact_fundamentals(rots, trans, TRUE_K)
    bad = corrupt(np.random.default_rng(6), fs, 0.2)
    weights = np.where(np.all(bad == fs, axis=(1, 2)), 1.0, 0.0)
    res = calibrate_from_fundamentals(bad, TRUE_K * 1.04, weights=weights, robust=False)
    assert res.num_pairs == int(weights.sum()) < len(fs)
    assert np.max(rel_err(res.intrinsics)) < 1e-6


def test_rank_deficient_fundamentals_are_dropped(scene) -> None:
    rots, trans, _ = scene
    fs = exact_fundamentals(rots, trans, TRUE_K)
    fs[2] = np.outer(fs[2][:, 0], fs[2][0])  # rank 1
    res = calibrate_from_fundamentals(fs, TRUE_K * 1.04)
    assert res.num_pairs == len(fs) - 1
    assert np.max(rel_err(res.intrinsics)) < 1e-6
    rank1 = np.stack([np.outer(f[:, 0], f[0]) for f in fs[:3]])
    with pytest.raises(CalibrationError, match="at least 2"):
        calibrate_from_fundamentals(rank1, TRUE_K)


def test_error_for_a_single_pair(scene) -> None:
    rots, trans, _ = scene
    fs = exact_fundamentals(rots, trans, TRUE_K)
    with pytest.raises(CalibrationError, match="at least 2"):
        calibrate_from_fundamentals(fs[:1], TRUE_K)
    with pytest.raises(CalibrationError, match="at least 2"):
        calibrate_from_fundamentals(fs[0], TRUE_K)
    with pytest.raises(CalibrationError, match="at least 2"):
        calibrate_from_fundamentals(fs[:3], TRUE_K, weights=np.array([1.0, 0.0, 0.0]))


@pytest.mark.parametrize(
    "prior",
    [
        np.array([2700.0, 2700.0, 1500.0]),
        np.array([2700.0, np.nan, 1500.0, 1000.0]),
        np.array([-2700.0, 2700.0, 1500.0, 1000.0]),
        np.array([2700.0, 0.0, 1500.0, 1000.0]),
        np.array([2700.0, 2700.0, np.inf, 1000.0]),
    ],
)
def test_error_for_bad_prior(scene, prior: np.ndarray) -> None:
    rots, trans, _ = scene
    fs = exact_fundamentals(rots, trans, TRUE_K)
    with pytest.raises(CalibrationError, match="prior"):
        calibrate_from_fundamentals(fs, prior)


def test_error_for_bad_inputs(scene) -> None:
    rots, trans, _ = scene
    fs = exact_fundamentals(rots, trans, TRUE_K)
    with pytest.raises(CalibrationError):
        calibrate_from_fundamentals(fs[:, :2], TRUE_K)
    with pytest.raises(CalibrationError):
        calibrate_from_fundamentals(np.full((3, 3, 3), np.nan), TRUE_K)
    with pytest.raises(CalibrationError):
        calibrate_from_fundamentals(fs, TRUE_K, weights=-np.ones(len(fs)))
    with pytest.raises(CalibrationError):
        calibrate_from_fundamentals(fs, TRUE_K, weights=np.ones(3))
