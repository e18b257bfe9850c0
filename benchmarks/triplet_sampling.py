"""Accuracy and time of calibrating from a bounded sample of triplets against all of them.

On one database with a known camera: msac-opt from the same ±5 % priors (one per
seed) with at most 10, 20 (the default) and 40 triplets chosen by
:func:`colmap_trifocal.geometry.tracks.select_triplets`, and with every triplet of the
view graph that has enough tracks (``max_triplets=None``). Prints the mean and
max of the mean relative error of (fx, fy, cx, cy) in percent and the mean time.

    python benchmarks/triplet_sampling.py DATABASE --truth FX,FY,CX,CY [--seeds 5]
        [--counts 10,20,40,all]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from colmap_trifocal import CalibrationOptions, calibrate_contents
from colmap_trifocal.database.snapshot import read_database


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("database", type=Path)
    parser.add_argument("--truth", required=True, help="FX,FY,CX,CY in pixels")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--counts", default="10,20,40,all", help="triplets per run; all: every one")
    args = parser.parse_args()
    truth = np.array([float(v) for v in args.truth.split(",")])
    contents = read_database(args.database)
    counts = [None if c == "all" else int(c) for c in args.counts.split(",")]
    print("| triplets | used | mean error % | max error % | mean seconds |")
    print("|---|---|---|---|---|")
    for count in counts:
        errors, seconds, used = [], [], []
        for seed in range(args.seeds):
            rng = np.random.default_rng(1000 + seed)
            prior = truth * (1.0 + rng.uniform(-0.05, 0.05, 4))
            options = CalibrationOptions(prior=tuple(prior), seed=seed, max_triplets=count)
            start = time.perf_counter()
            (result,) = calibrate_contents(contents, options)
            seconds.append(time.perf_counter() - start)
            errors.append(100.0 * np.mean(np.abs(result.intrinsics / truth - 1.0)))
            used.append(result.num_triplets)
        label = "all" if count is None else str(count)
        print(
            f"| {label} | {np.mean(used):.0f} | {np.mean(errors):.3f} | {np.max(errors):.3f} | "
            f"{np.mean(seconds):.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
