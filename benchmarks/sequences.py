"""Sequences (issue 13, item 3): triplets by track count vs. by geometric information.

Synthetic drives (:func:`colmap_trifocal.synthetic.driving.driving_sequence`: 50
frames 1 m apart, KITTI camera 1241x376, f = 718.856 px, 0.5 px noise, every pair
with common points matched), straight and with a 90° right turn; and, with
``--kitti DB``, a COLMAP database of the shared KITTI drive (51 frames, 98° turn;
build it with ``colmap_trifocal.database.features.build_database(...,
max_image_size=1241, matcher="sequential")``). For each: msac-opt from a ±5 %
prior (random signs) and from COLMAP's default camera, with the track-count
selection (``sequence=False``, the behaviour before) and the sequence selection
(``sequence=True``). Prints the error of each parameter, which are reported
determined (``-``: not), their std and the frame gaps spanned by the triplets.

    python benchmarks/sequences.py [--turns 0,90] [--seeds 2] [--kitti /tmp/kitti.db]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from colmap_trifocal import CalibrationOptions, calibrate_contents, calibrate_database
from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.intrinsics.results import PARAMETER_NAMES
from colmap_trifocal.synthetic.database import scene_contents
from colmap_trifocal.synthetic.driving import KITTI_INTRINSICS, driving_sequence


def row(label: str, start: str, sequence: bool, truth: np.ndarray, run) -> None:
    """Calibrate with ``run(options)`` and print one table row."""
    if start == "prior":
        signs = np.array([1.0, -1.0, 1.0, -1.0])
        options = CalibrationOptions(prior=tuple(truth * (1.0 + 0.05 * signs)))
    else:
        options = CalibrationOptions(no_prior=True)
    options.sequence, options.workers = sequence, 1
    clock = time.process_time()
    selection = "information" if sequence else "tracks"
    try:
        (result,) = run(options)
    except CalibrationError as error:
        print(f"| {label} | {start} | {selection} | error: {error} |||||||", flush=True)
        return
    seconds = time.process_time() - clock
    error = (result.intrinsics / truth - 1.0) * 100.0
    cells = " | ".join(
        f"{e:+.2f}{'' if result.observable[n] else ' (-)'}"
        for e, n in zip(error, PARAMETER_NAMES, strict=True)
    )
    std = "/".join(
        "-" if result.std[n] is None else f"{result.std[n]:.1f}" for n in PARAMETER_NAMES
    )
    gaps = np.array([max(t.image_ids) - min(t.image_ids) for t in result.triplets])
    print(
        f"| {label} | {start} | {selection} | {result.num_inlier_triplets}/{result.num_triplets} "
        f"| {cells} | {std} | {np.median(gaps):g} ({gaps.min()}–{gaps.max()}) | {seconds:.0f} |",
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--turns", default="0,90", help="turns of the synthetic drives, degrees")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--starts", default="prior,default")
    parser.add_argument("--kitti", help="COLMAP database of the shared KITTI drive")
    args = parser.parse_args()
    print(
        "| drive | start | selection | agree | fx % | fy % | cx % | cy % | std px "
        "| gap median (range) | CPU s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    starts = args.starts.split(",")
    for turn in map(float, args.turns.split(",")) if args.turns else []:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            scene = driving_sequence(turn_deg=turn, seed=seed)
            contents = scene_contents(scene)
            for start in starts:
                for sequence in (False, True):

                    def run(options, contents=contents, seed=seed):
                        options.seed = seed
                        return calibrate_contents(contents, options)

                    row(f"turn {turn:g}°, seed {seed}", start, sequence, scene.intrinsics, run)
    if args.kitti:
        for start in starts:
            for sequence in (False, True):
                row(
                    "KITTI (98° turn)",
                    start,
                    sequence,
                    KITTI_INTRINSICS,
                    lambda options: calibrate_database(args.kitti, options),
                )


if __name__ == "__main__":
    main()
