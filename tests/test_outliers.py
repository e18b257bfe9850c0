"""Outlier stress (short): msac-opt within 1 % with half of the verified matches wrong.

The database is ``benchmarks/outlier_stress.py``'s: the demo scene (10 images, 1500
points, 0.5 px noise, cameras turned by 5°), a ±5 % prior, and in every pair a share of
the verified matches given a random partner keypoint. The full table (0–80 %, both
methods, breakdown points) is the benchmark's.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from colmap_trifocal import CalibrationOptions, calibrate_database
from colmap_trifocal.database.snapshot import read_database

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from outlier_stress import make_outlier_database  # noqa: E402


def _wrong_share(path: Path, truth_path: Path) -> float:
    """Share of verified matches that differ from the outlier-free database's."""
    contents, clean = read_database(path), read_database(truth_path)
    wrong = total = 0
    for pair, matches in clean.matches.items():
        wrong += int(np.sum(np.any(contents.matches[pair] != matches, axis=1)))
        total += len(matches)
    return wrong / total


def test_the_outliers_are_in_the_verified_matches(tmp_path: Path) -> None:
    """The stress is real: half of the verified matches point to a wrong keypoint."""
    noisy, clean = tmp_path / "noisy.db", tmp_path / "clean.db"
    make_outlier_database(noisy, 0.5, seed=0, num_points=300)
    make_outlier_database(clean, 0.0, seed=0, num_points=300)
    assert _wrong_share(noisy, clean) == pytest.approx(0.5, abs=0.02)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_msac_opt_within_one_percent_at_half_outliers(tmp_path: Path, seed: int) -> None:
    path = tmp_path / "database.db"
    truth, prior = make_outlier_database(path, 0.5, seed)
    assert np.mean(np.abs(prior / truth - 1)) == pytest.approx(0.05)
    (result,) = calibrate_database(path, CalibrationOptions(method="msac-opt", seed=seed))
    error = np.mean(np.abs(result.intrinsics / truth - 1))
    assert error < 0.01, f"mean relative error {100 * error:.3f} % at 50 % outliers"
