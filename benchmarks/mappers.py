"""Incremental vs global mapping, each with and without TrifocalCalib (Strecha scenes).

Every configuration starts from the same COLMAP-default database: SIFT at 1600 px,
exhaustive matching, ``pycolmap.extract_features`` defaults, i.e. one SIMPLE_RADIAL
camera per image at f = 1.2 · max(w, h), centred (built once, cached in ``--cache``).

* plain incremental: ``pycolmap.incremental_mapping`` with default options (focal
  length and distortion refined per camera, principal point fixed);
* plain global: ``pycolmap.global_mapping`` with default options (GLOMAP; focal
  length and distortion refined, principal point fixed);
* ``run --mapper incremental|global``: TrifocalCalib on the grouped cameras, the
  images of the group sharing one camera, mapping with the estimate held fixed, then
  bundle adjustment of focal length and principal point (``--refine ba``).

K error: mean relative error of (fx, fy, cx, cy) against ``gt_dense_cameras``, in %,
averaged over the registered images' cameras (the plain runs keep one camera per
image). Time: wall-clock seconds of mapping (plain) or of calibrate + mapping +
refine (run, with the three stages; feature extraction and matching are shared and
not counted).

    python benchmarks/mappers.py [--scenes fountain-P11,Herz-Jesus-P8] [--seed 0]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pycolmap

from colmap_trifocal.common.log import silenced_stderr
from colmap_trifocal.database.features import build_database
from colmap_trifocal.datasets.strecha import (
    default_datasets_root,
    ground_truth_intrinsics,
    scene_images,
)
from colmap_trifocal.reconstruction.mapping import camera_intrinsics
from colmap_trifocal.reconstruction.workflow import RunOptions, run_pipeline

ROOT = Path(__file__).resolve().parents[1]


def k_error(reconstruction: pycolmap.Reconstruction, truth: np.ndarray) -> float:
    """Mean relative error (%) of (fx, fy, cx, cy) over the registered images' cameras."""
    ids = {image.camera_id for image in reconstruction.images.values() if image.has_pose}
    estimates = np.array([camera_intrinsics(reconstruction.cameras[c]) for c in ids])
    return float(np.mean(np.abs(estimates / truth - 1)) * 100)


def plain(
    mapper: str, database: Path, work: Path, seed: int
) -> tuple[pycolmap.Reconstruction, float, str]:
    """pycolmap's own mapper with default options on a copy of the database."""
    copy = work / f"plain_{mapper}.db"
    shutil.copyfile(database, copy)
    output = work / f"plain_{mapper}"
    output.mkdir()
    start = time.perf_counter()
    with silenced_stderr():
        if mapper == "global":
            options = pycolmap.GlobalPipelineOptions()
            options.random_seed = seed
            options.mapper.random_seed = seed
            options.mapper.global_positioning.use_gpu = False
            options.mapper.bundle_adjustment.ceres.use_gpu = False
            models = pycolmap.global_mapping(copy, output, output, options)
        else:
            options = pycolmap.IncrementalPipelineOptions()
            options.random_seed = seed
            options.extract_colors = False
            models = pycolmap.incremental_mapping(copy, output, output, options)
    seconds = time.perf_counter() - start
    return max(models.values(), key=lambda r: r.num_reg_images()), seconds, "mapping"


def ours(
    mapper: str, database: Path, work: Path, seed: int
) -> tuple[pycolmap.Reconstruction, float, str]:
    """``colmap-trifocal run --database DB --mapper MAPPER``."""
    workspace = work / f"run_{mapper}"
    options = RunOptions(database=database, mapper=mapper, seed=seed)
    start = time.perf_counter()
    with silenced_stderr():
        report = run_pipeline(None, workspace, options).to_json()
    seconds = time.perf_counter() - start - report["seconds"]["features"]  # the copy
    stages = " + ".join(f"{report['seconds'][k]:.0f}" for k in ("calibrate", "mapping", "refine"))
    return pycolmap.Reconstruction(workspace / "sparse" / "0"), seconds, stages


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", default="fountain-P11,Herz-Jesus-P8")
    parser.add_argument("--cache", type=Path, default=ROOT / ".cache")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    pycolmap.logging.minloglevel = 2
    args.cache.mkdir(exist_ok=True)
    header = "scene | mapper | TrifocalCalib | registered | K error % | fx, fy, cx, cy | seconds"
    print(f"| {header} | stages |")
    print("|---|---|---|---|---|---|---|---|")
    for scene in args.scenes.split(","):
        folder = default_datasets_root(ROOT) / "strecha" / scene
        database = args.cache / f"{scene}_colmap_default_1600.db"
        if not database.exists():
            with silenced_stderr():
                build_database(
                    folder / "images",
                    database,
                    scene_images(folder),
                    camera_model="SIMPLE_RADIAL",
                    camera_mode="auto",
                )
        truth = ground_truth_intrinsics(folder)
        num_images = len(scene_images(folder))
        for mapper in ("incremental", "global"):
            for label, function in (("no", plain), ("yes", ours)):
                with tempfile.TemporaryDirectory() as tmp:
                    model, seconds, stages = function(mapper, database, Path(tmp), args.seed)
                    ids = {i.camera_id for i in model.images.values() if i.has_pose}
                    mean = np.mean([camera_intrinsics(model.cameras[c]) for c in ids], axis=0)
                    print(
                        f"| {scene} | {mapper} | {label} | {model.num_reg_images()}/{num_images} "
                        f"| {k_error(model, truth):.2f} | {', '.join(f'{v:.1f}' for v in mean)} "
                        f"| {seconds:.1f} | {stages} |",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
