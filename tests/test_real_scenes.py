"""The real-data tier: every real scene, both databases, from COLMAP's guess and ±5 % priors.

The same scenes and databases as ``benchmarks/real.py`` (``benchmarks/real_scenes.py``),
the same runs (the stored camera, then priors within ±5 % of the truth, seeds 0-4), and
per run the checks the product is measured by:

* the error (mean relative error of fx, fy, cx, cy) is at most the scene's bar;
* the result is never further from the truth than the start it was given;
* each parameter's error is within ``MAX_Z`` of its std, and over the scene's runs at least
  ``MIN_COVERAGE`` of the errors are within 2 std.

``BARS`` hold the scene's bar: issue 35's target max(1.25 × pycolmap's mapping + BA of the
same database, 0.5 %) where it is met, else the measured error with a margin, so that no
change regresses a scene silently. ``KNOWN_FAILURES`` lists what a scene does not reach
yet. An accuracy or start entry must still fail (else it is stale and the test says so);
a z or coverage entry that passes is reported as a warning, as these checks sit on a
threshold that a last-digit difference of another machine's arithmetic can cross.
The benchmark's figures: ``docs/accuracy.md``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_dataset
from real_scenes import DATABASE_KINDS, SCENES, SCENES_BY_NAME, prior_5

from colmap_trifocal import CalibrationOptions, calibrate_database

pytestmark = [pytest.mark.real_data, pytest.mark.slow]

#: Seeds of the runs from a prior (the stored camera is also run with each).
SEEDS = (0, 1, 2, 3, 4)
#: No parameter's error may exceed this many stds.
MAX_Z = 4.0
#: Share of the errors within 2 std over a scene's runs.
MIN_COVERAGE = 0.75

#: The error bar of every run, percent, per (scene, database).
BARS: dict[tuple[str, str], float] = {
    ("fountain-P11", "default"): 0.50,
    ("fountain-P11", "pinhole"): 0.50,
    ("Herz-Jesus-P8", "default"): 0.50,
    ("Herz-Jesus-P8", "pinhole"): 0.50,
    ("entry-P10", "default"): 0.50,
    ("entry-P10", "pinhole"): 0.50,
    ("euroc-V1_01", "default"): 4.5,
    ("euroc-V1_01", "pinhole"): 4.0,
    ("lego", "default"): 1.5,
    ("lego", "pinhole"): 1.37,
    # A ring's focal length at a held principal point may stay at a ±5 % prior (seeds
    # 0-4: up to 3.4 % off over the four parameters); from the guess the error is ~1 %.
    ("temple-ring", "default"): 3.5,
    ("temple-ring", "pinhole"): 3.5,
    ("kitti-seq2", "default"): 1.8,
    ("kitti-seq2", "pinhole"): 1.8,
    # Real images through a phone-like lens: 0.10-0.27 % in every run (0.52 % behind the
    # fountain's PINHOLE camera, where pycolmap's mapping, which cannot bend its tracks
    # either, ends 3.3 % off); 17 % from the guess before the lens search's finer steps.
    ("fountain-P11-lens", "default"): 0.50,
    ("fountain-P11-lens", "pinhole"): 0.80,
    ("entry-P10-lens", "default"): 0.50,
    ("entry-P10-lens", "pinhole"): 0.50,
}

#: Checks on a threshold of a statistic: a known failure of these that passes only warns.
STATISTICAL = frozenset({"z", "coverage"})

#: Checks a scene does not pass yet (issue 35): "start" (a run ends further from the
#: truth than its start), "z" (an error beyond MAX_Z std), "coverage".
KNOWN_FAILURES: dict[tuple[str, str], set[str]] = {
    ("kitti-seq2", "pinhole"): {"coverage"},
    # Through the lens behind a PINHOLE camera the facade's cx comes out 12-23 px short in
    # every run (0.4-0.75 %); the seed-4 prior's std says 4.6 px (|z| 5.0).
    ("entry-P10-lens", "pinhole"): {"z"},
}


@dataclass
class Run:
    """One calibration of a scene's database."""

    label: str
    error: float  # percent
    start_error: float  # percent
    z: np.ndarray  # |error| / std of each parameter with a std


def mean_error(values: np.ndarray, truth: np.ndarray) -> float:
    return float(np.mean(np.abs(np.asarray(values) / truth - 1.0)) * 100.0)


def calibrate(database: Path, truth: np.ndarray, prior: tuple | None, seed: int) -> Run:
    (result,) = calibrate_database(database, CalibrationOptions(prior=prior, seed=seed))
    std = np.array([np.nan if s is None else s for s in result.std.values()], float)
    z = np.abs(result.intrinsics - truth)[std > 0] / std[std > 0]
    label = "guess" if prior is None else "prior"
    return Run(
        f"{label} seed {seed}",
        mean_error(result.intrinsics, truth),
        mean_error(np.array(result.prior), truth),
        z,
    )


def failed_checks(runs: list[Run], bar: float) -> dict[str, list[str]]:
    """The checks the runs fail, each with what failed."""
    failed: dict[str, list[str]] = {}
    for run in runs:
        if run.error > bar:
            failed.setdefault("accuracy", []).append(f"{run.label}: {run.error:.2f} % > {bar} %")
        if run.error > run.start_error + 1e-9:
            failed.setdefault("start", []).append(
                f"{run.label}: {run.error:.2f} % from a start {run.start_error:.2f} % off"
            )
        if np.any(run.z > MAX_Z):
            failed.setdefault("z", []).append(f"{run.label}: |z| {np.max(run.z):.1f}")
    z = np.concatenate([run.z for run in runs])
    coverage = float(np.mean(z <= 2.0)) if len(z) else 1.0
    if coverage < MIN_COVERAGE:
        failed["coverage"] = [f"{coverage:.0%} of the errors within 2 std"]
    return failed


@pytest.mark.parametrize("kind", DATABASE_KINDS)
@pytest.mark.parametrize("name", [scene.name for scene in SCENES])
def test_real_scene(name: str, kind: str, real_scene_database: Callable[[str, str], Path]) -> None:
    truth = SCENES_BY_NAME[name].truth(shared_dataset(""))
    database = real_scene_database(name, kind)
    runs = [calibrate(database, truth, None, seed) for seed in SEEDS]
    runs += [calibrate(database, truth, prior_5(truth, seed), seed) for seed in SEEDS]
    failed = failed_checks(runs, BARS[name, kind])
    known = KNOWN_FAILURES.get((name, kind), set())
    unexpected = {check: what for check, what in failed.items() if check not in known}
    assert unexpected == {}, unexpected
    stale = known - set(failed)
    if stale & STATISTICAL:
        warnings.warn(f"{name} {kind} now passes {sorted(stale & STATISTICAL)}", stacklevel=1)
    stale -= STATISTICAL
    assert not stale, f"{name} {kind} now passes {sorted(stale)}: remove it from KNOWN_FAILURES"


def test_every_scene_and_database_has_a_bar() -> None:
    assert set(BARS) == {(s.name, k) for s in SCENES for k in DATABASE_KINDS}
