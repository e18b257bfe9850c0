"""Mapping on synthetic drives: plain pycolmap against ``run`` (issue 13, item 4).

Each drive (``synthetic.driving.driving_sequence``: KITTI camera 1241 x 376,
f = 718.856 px, 1 m steps, 0.5 px noise) is written with COLMAP's default camera
(f = 1.2 · max(w, h), centred; verified matches of every pair, as an exhaustive
matcher would keep them). Then:

* plain: ``pycolmap.incremental_mapping`` with COLMAP's defaults (focal length
  refined, principal point held) from that camera;
* run: ``run_pipeline(None, WS, RunOptions(database=db))`` (TrifocalCalib, mapping
  with retries seeded from the calibration's best triplets, final BA).

Printed per drive: registered images, the error (%) of the final fx, fy, cx, cy
against the truth and their mean, the attempts and the seeded pair, seconds.

    python benchmarks/hard_mapping.py [--drives 12:0,20:0,20:30] [--points 3000] [--seed 0]
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap

from colmap_trifocal.reconstruction.workflow import RunOptions, run_pipeline
from colmap_trifocal.synthetic.database import scene_contents, write_database
from colmap_trifocal.synthetic.driving import driving_sequence

NAMES = ("fx", "fy", "cx", "cy")


def plain_mapping(database: Path, work: Path) -> tuple[int, np.ndarray | None]:
    """Registered images and (fx, fy, cx, cy) of plain pycolmap's largest model (px)."""
    copy = work / "plain.db"
    shutil.copyfile(database, copy)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = 1
    models = pycolmap.incremental_mapping(copy, work, work / "plain", options)
    if not models:
        return 0, None
    model = max(models.values(), key=lambda m: m.num_reg_images())
    camera = next(iter(model.cameras.values()))
    intrinsics = np.array(
        [
            camera.focal_length_x,
            camera.focal_length_y,
            camera.principal_point_x,
            camera.principal_point_y,
        ]
    )
    return model.num_reg_images(), intrinsics


def percent(values: np.ndarray | None, truth: np.ndarray) -> str:
    """Relative errors (%) and their mean |.|, or a dash."""
    if values is None:
        return "–"
    error = (values / truth - 1) * 100
    return " / ".join(f"{e:+.2f}" for e in error) + f" (mean {np.mean(np.abs(error)):.2f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--drives", default="12:0,20:0,20:30", help="frames:turn-degrees, comma separated"
    )
    parser.add_argument("--points", type=int, default=3000, help="points along the street")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=Path("benchmark_output/hard_mapping"))
    args = parser.parse_args()
    pycolmap.logging.minloglevel = 2
    rows = []
    for drive in args.drives.split(","):
        frames, turn = int(drive.split(":")[0]), float(drive.split(":")[1])
        scene = driving_sequence(frames, turn, seed=args.seed, num_points=args.points)
        truth = scene.intrinsics
        default = np.array([1.2 * scene.width] * 2 + [scene.width / 2, scene.height / 2])
        work = args.output / f"{frames}-{turn:g}-seed{args.seed}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        database = write_database(scene_contents(scene), work / "drive.db", intrinsics=default)

        clock = time.perf_counter()
        registered, intrinsics = plain_mapping(database, work)
        plain_seconds = time.perf_counter() - clock

        clock = time.perf_counter()
        report = run_pipeline(
            None, work / "ws", RunOptions(database=database, seed=args.seed)
        ).to_json()
        run_seconds = time.perf_counter() - clock
        camera = report["cameras"][0]
        trifocal = np.array([camera["trifocal"][n] for n in NAMES])
        refined = np.array([camera["refined"][n] for n in NAMES])
        mapping = report["mapping"]
        attempts = ", ".join(
            f"{a['init_min_tri_angle']:g}°{' seeded' if a['init_pair'] else ''}: "
            f"{a['num_registered_images']}"
            for a in mapping["attempts"]
        )
        seeded = mapping["seeded_pair"]
        pair = (
            "–"
            if seeded is None
            else f"{seeded['image_ids'][0]}+{seeded['image_ids'][1]} "
            f"({seeded['tri_angle']:.1f}°, forward {seeded['forward_motion']:.4f})"
        )
        rows.append(
            (
                f"{frames} frames, {turn:g}° turn",
                f"{registered}/{frames}",
                percent(intrinsics, truth),
                f"{report['num_registered_images']}/{frames}",
                percent(trifocal, truth),
                percent(refined, truth),
                attempts,
                pair,
                f"{plain_seconds:.0f} / {run_seconds:.0f}",
            )
        )
        print(" | ".join(rows[-1]), flush=True)
    print()
    print(
        "| drive | plain: registered | plain: error % fx / fy / cx / cy | run: registered "
        "| TrifocalCalib error % | run: final error % | attempts (registered) | seeded pair "
        "| seconds plain / run |"
    )
    print("|" + "---|" * 9)
    for row in rows:
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
