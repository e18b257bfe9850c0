"""``colmap-trifocal evaluate KIND PATH``: the paper's protocol on a dataset with ground truth.

Every scene is read and every output checked before the first (long) evaluation.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..common.arguments import integer_in
from ..common.errors import CalibrationError
from .experiments import (
    MAX_RUNS,
    add_common_flags,
    check_outputs,
    dataset_inputs,
    finish,
    methods,
    numbers,
)

#: The longest sequence ``--images`` takes (1e12 images asked for terabytes before).
MAX_IMAGES = 100_000
#: The largest ``--max-image-size`` (pixels of the longest side SIFT sees).
MAX_IMAGE_SIZE = 32_768


def add_parser(commands: argparse._SubParsersAction) -> None:
    """``evaluate KIND PATH``: sequences, perturbation ranges, runs, methods."""
    from ..datasets import DATASET_KINDS
    from ..evaluation.protocol import DEFAULT_METHODS, EVALUATION_METHODS

    parser = commands.add_parser(
        "evaluate", help="the paper's protocol on a dataset with ground truth (tables, plots)"
    )
    parser.add_argument("kind", choices=DATASET_KINDS, help="dataset format")
    parser.add_argument("path", type=Path, help="a scene folder, or a folder of scene folders")
    parser.add_argument("--images", default="8,16,32", help="sequence lengths (default 8,16,32)")
    parser.add_argument(
        "--perturbation", default="0-5,5-10", help="prior perturbation ranges in %% (0-5,5-10)"
    )
    parser.add_argument("--runs", type=int, default=100, help="seeded runs per configuration")
    parser.add_argument(
        "--methods",
        default=",".join(DEFAULT_METHODS),
        help=f"comma-separated, from {','.join(EVALUATION_METHODS)} (mapping is slow)",
    )
    parser.add_argument(
        "--mapping-runs",
        type=integer_in(0, MAX_RUNS),
        default=3,
        help="runs of the mapping baseline (default 3)",
    )
    parser.add_argument(
        "--max-image-size",
        type=integer_in(100, MAX_IMAGE_SIZE),
        default=1600,
        help="longest image side for SIFT, in pixels (default 1600)",
    )
    add_common_flags(parser, "evaluation")
    parser.add_argument(
        "--cache", type=Path, help="keep the per-scene databases here (default: temporary)"
    )


def run(args: argparse.Namespace) -> int:
    """Check, evaluate every scene, write and print the summary; exit status 0."""
    from ..evaluation.protocol import (
        EVALUATION_METHODS,
        EvaluationOptions,
        evaluate_scene,
        scenes_at,
    )

    check_outputs(
        args,
        "evaluation",
        lambda: dataset_inputs({"PATH": args.path, "--cache": args.cache}, "evaluation"),
    )
    options = EvaluationOptions(
        image_counts=tuple(numbers(args.images, "--images", int, (0, MAX_IMAGES))),
        perturbations=_ranges(args.perturbation),
        runs=args.runs,
        mapping_runs=args.mapping_runs,
        methods=methods(args.methods, EVALUATION_METHODS),
        seed=args.seed,
        max_image_size=args.max_image_size,
        cache=args.cache,
        workers=args.workers,
        dask_address=args.dask,
        progress=sys.stderr.isatty(),
    )
    if min(options.image_counts) < 3:
        raise CalibrationError("--images: every sequence needs at least 3 images")
    began = time.perf_counter()
    scenes = scenes_at(args.kind, args.path)
    for scene in scenes:  # all checked before the first (long) evaluation
        if not Path(scene.image_dir).is_dir():
            raise CalibrationError(
                f"scene {scene.name}: image folder {scene.image_dir} does not exist"
            )
    records = [r for scene in scenes for r in evaluate_scene(scene, options)]
    finish(records, args, "evaluation", f"{args.kind}: {args.runs} runs")
    print(f"{len(records)} results in {time.perf_counter() - began:.0f} s")
    return 0


def _ranges(text: str) -> tuple[tuple[float, float], ...]:
    """``LOW-HIGH`` percent ranges, comma-separated, with 0 <= LOW <= HIGH < 100."""
    ranges = []
    for part in text.split(","):
        try:
            low, high = (float(v) for v in part.split("-"))
        except ValueError:
            raise CalibrationError(
                f"malformed --perturbation {part!r}: expected LOW-HIGH in percent, e.g. 0-5"
            ) from None
        if not 0 <= low <= high < 100:
            raise CalibrationError(
                f"invalid --perturbation {part!r}: need 0 <= LOW <= HIGH < 100 (percent)"
            )
        ranges.append((low, high))
    return tuple(ranges)
