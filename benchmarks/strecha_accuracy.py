"""Accuracy of every method on the Strecha scenes (issue protocol).

SIFT at 1600 px, exhaustive matching, one PINHOLE camera; prior = ground truth
with each parameter perturbed by a uniform ±5 %; N seeds. Prints mean / median /
max of the mean relative error of (fx, fy, cx, cy) in percent and the mean time,
for direct, msac, msac-opt, fundamental and pycolmap.calibrate_view_graph.

    python benchmarks/strecha_accuracy.py [--seeds 20] [--scenes fountain-P11,Herz-Jesus-P8]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pycolmap

from colmap_trifocal import CalibrationOptions, calibrate_contents
from colmap_trifocal.database.features import build_database
from colmap_trifocal.database.snapshot import read_database
from colmap_trifocal.datasets.strecha import (
    default_datasets_root,
    ground_truth_intrinsics,
    scene_images,
)

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("msac-opt", "msac", "direct", "fundamental")


def mean_relative_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    return float(np.mean(np.abs(estimate / truth - 1.0)) * 100.0)


def view_graph_estimate(database: Path, prior: np.ndarray, work: Path) -> np.ndarray:
    """pycolmap.calibrate_view_graph on a copy of the database, started from ``prior``."""
    copy = work / "view_graph.db"
    shutil.copyfile(database, copy)
    db = pycolmap.Database.open(copy)
    camera = db.read_all_cameras()[0]
    camera.params = prior
    db.update_camera(camera)
    db.close()
    pycolmap.calibrate_view_graph(copy)
    db = pycolmap.Database.open(copy)
    params = np.array(db.read_all_cameras()[0].params, dtype=float)
    db.close()
    copy.unlink()
    return params


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--scenes", default="fountain-P11,Herz-Jesus-P8")
    parser.add_argument("--cache", type=Path, default=ROOT / ".cache")
    args = parser.parse_args()
    datasets = default_datasets_root(ROOT) / "strecha"
    args.cache.mkdir(exist_ok=True)
    for scene in args.scenes.split(","):
        folder = datasets / scene
        database = args.cache / f"{scene}_1600.db"
        if not database.exists():
            build_database(folder / "images", database, scene_images(folder))
        truth = ground_truth_intrinsics(folder)
        contents = read_database(database)
        errors: dict[str, list[float]] = {m: [] for m in (*METHODS, "calibrate_view_graph")}
        seconds: dict[str, list[float]] = {m: [] for m in errors}
        with tempfile.TemporaryDirectory() as tmp:
            for seed in range(args.seeds):
                rng = np.random.default_rng(1000 + seed)
                prior = truth * (1.0 + rng.uniform(-0.05, 0.05, 4))
                for method in METHODS:
                    options = CalibrationOptions(method=method, prior=tuple(prior), seed=seed)
                    start = time.perf_counter()
                    (result,) = calibrate_contents(contents, options)
                    seconds[method].append(time.perf_counter() - start)
                    errors[method].append(mean_relative_error(result.intrinsics, truth))
                start = time.perf_counter()
                estimate = view_graph_estimate(database, prior, Path(tmp))
                seconds["calibrate_view_graph"].append(time.perf_counter() - start)
                errors["calibrate_view_graph"].append(mean_relative_error(estimate, truth))
                print(
                    f"{scene} seed {seed:2d} prior {mean_relative_error(prior, truth):.2f}% "
                    + " ".join(f"{m} {v[-1]:.3f}%" for m, v in errors.items()),
                    flush=True,
                )
        print(f"\n{scene}: {args.seeds} seeds, ±5 % prior, mean relative error of fx, fy, cx, cy")
        print("| method | mean % | median % | max % | mean time s |\n|---|---|---|---|---|")
        for method, values in errors.items():
            print(
                f"| {method} | {np.mean(values):.3f} | {np.median(values):.3f} | "
                f"{np.max(values):.3f} | {np.mean(seconds[method]):.2f} |"
            )
        print(flush=True)


if __name__ == "__main__":
    main()
