"""``colmap-trifocal run`` against plain pycolmap on the same database (Strecha scenes).

Both start from the same SIFT database (1600 px, exhaustive, one PINHOLE camera at
COLMAP's default guess). Plain pycolmap: incremental mapping refining focal length
and principal point. Ours: TrifocalCalib, mapping with the estimate fixed, global
bundle adjustment of focal length and principal point. Prints registered images,
mean relative error of (fx, fy, cx, cy) against gt_dense_cameras and the times.

    python benchmarks/pipeline_vs_colmap.py [--scenes fountain-P11]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pycolmap

from colmap_trifocal.database.features import build_database
from colmap_trifocal.datasets.strecha import (
    default_datasets_root,
    ground_truth_intrinsics,
    scene_images,
)
from colmap_trifocal.reconstruction.mapping import camera_intrinsics
from colmap_trifocal.reconstruction.workflow import RunOptions, run_pipeline

ROOT = Path(__file__).resolve().parents[1]


def plain_pycolmap(
    database: Path, images: Path, work: Path
) -> tuple[pycolmap.Reconstruction, float]:
    """COLMAP's incremental mapping refining focal length and principal point."""
    copy = work / "plain.db"
    shutil.copyfile(database, copy)
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = True
    options.ba_refine_principal_point = True
    options.random_seed = 0
    start = time.perf_counter()
    models = pycolmap.incremental_mapping(copy, images, work / "plain", options)
    seconds = time.perf_counter() - start
    return max(models.values(), key=lambda r: r.num_reg_images()), seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", default="fountain-P11")
    parser.add_argument("--cache", type=Path, default=ROOT / ".cache")
    args = parser.parse_args()
    pycolmap.logging.minloglevel = 2
    args.cache.mkdir(exist_ok=True)
    for scene in args.scenes.split(","):
        folder = default_datasets_root(ROOT) / "strecha" / scene
        database = args.cache / f"{scene}_1600.db"
        start = time.perf_counter()
        if not database.exists():
            build_database(folder / "images", database, scene_images(folder))
        features_seconds = time.perf_counter() - start
        truth = ground_truth_intrinsics(folder)
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            report = run_pipeline(
                folder / "images", work / "ours", RunOptions(database=database)
            ).to_json()
            plain, plain_seconds = plain_pycolmap(database, folder / "images", work)
        (camera,) = report["cameras"]
        ours = {
            k: np.array([camera[k][p] for p in ("fx", "fy", "cx", "cy")])
            for k in ("trifocal", "refined")
        }
        plain_k = camera_intrinsics(next(iter(plain.cameras.values())))

        def error(k: np.ndarray, truth: np.ndarray = truth) -> float:
            return float(np.mean(np.abs(k / truth - 1)) * 100)

        s = report["seconds"]
        ours_total = s["calibrate"] + s["mapping"] + s["refine"]
        print(f"\n{scene} (features and matching: {features_seconds:.1f} s, shared)")
        print("| pipeline | registered | error % | time s (after matching) |")
        print("|---|---|---|---|")
        print(f"| TrifocalCalib only | - | {error(ours['trifocal']):.3f} | {s['calibrate']:.1f} |")
        print(
            f"| TrifocalCalib + mapping + BA (f, pp) | {report['num_registered_images']}/"
            f"{report['num_images']} | {error(ours['refined']):.3f} | {ours_total:.1f} "
            f"(calibrate {s['calibrate']:.1f}, mapping {s['mapping']:.1f}, "
            f"BA {s['refine']:.1f}) |"
        )
        print(
            f"| pycolmap default camera, mapping refining f + pp | {plain.num_reg_images()}/"
            f"{plain.num_images()} | {error(plain_k):.3f} | {plain_seconds:.1f} |"
        )


if __name__ == "__main__":
    main()
