"""``colmap-trifocal synthetic``: the paper's synthetic experiment (noise levels x runs)."""

from __future__ import annotations

import argparse
import sys
import time

from ..common.arguments import finite_float
from ..common.errors import CalibrationError
from .experiments import add_common_flags, check_outputs, finish, methods, numbers

#: The most tracks a synthetic scene takes (1e12 asked for terabytes before).
MAX_POINTS = 100_000
#: The largest pixel noise level: beyond it the images are noise (1e300 overflowed).
MAX_NOISE_PX = 100.0


def add_parser(commands: argparse._SubParsersAction) -> None:
    """``synthetic``: noise levels, runs, points, prior perturbation, outliers, methods."""
    from ..evaluation.synthetic_experiment import NOISE_LEVELS, SYNTHETIC_METHODS

    parser = commands.add_parser("synthetic", help="the paper's synthetic experiment")
    parser.add_argument(
        "--noise", default=",".join(f"{n:g}" for n in NOISE_LEVELS), help="pixel noise levels"
    )
    parser.add_argument("--runs", type=int, default=100, help="runs per noise level (default 100)")
    parser.add_argument("--points", type=int, default=500, help="tracks per scene")
    parser.add_argument(
        "--perturbation", type=finite_float, default=5.0, help="prior ±%% (default 5)"
    )
    parser.add_argument("--outliers", type=float, default=0.0, help="outlier track fraction")
    parser.add_argument(
        "--methods",
        default=",".join(SYNTHETIC_METHODS),
        help=f"comma-separated, from {','.join((*SYNTHETIC_METHODS, 'msac'))}",
    )
    add_common_flags(parser, "synthetic")


def run(args: argparse.Namespace) -> int:
    """Check, run every (noise level, run) case, write and print the summary; exit 0."""
    import numpy as np

    from ..evaluation.runner import run_tasks
    from ..evaluation.synthetic_experiment import SYNTHETIC_METHODS, run_synthetic_task

    check_outputs(args, "synthetic")
    noise_levels = numbers(args.noise, "--noise")
    if min(noise_levels) < 0:
        raise CalibrationError("--noise levels must be >= 0")
    if max(noise_levels) > MAX_NOISE_PX:
        raise CalibrationError(
            f"--noise levels must be at most {MAX_NOISE_PX:g} px, got {max(noise_levels):g}"
        )
    if not 0 <= args.perturbation < 100:
        raise CalibrationError("--perturbation must be in [0, 100) percent")
    if args.points < 10:
        raise CalibrationError("--points must be at least 10")
    if args.points > MAX_POINTS:
        raise CalibrationError(f"--points must be at most {MAX_POINTS}, got {args.points}")
    if not 0 <= args.outliers < 1:
        raise CalibrationError("--outliers must be in [0, 1)")
    chosen = methods(args.methods, (*SYNTHETIC_METHODS, "msac"))
    seeds = np.random.SeedSequence(args.seed).generate_state(args.runs)
    tasks = [
        (noise, run, int(seeds[run]), chosen, args.points, args.perturbation / 100, args.outliers)
        for noise in noise_levels
        for run in range(args.runs)
    ]
    began = time.perf_counter()
    results = run_tasks(
        run_synthetic_task,
        tasks,
        args.workers,
        args.dask,
        "synthetic runs",
        progress=sys.stderr.isatty(),
    )
    records = [r for rs in results for r in rs]
    finish(records, args, "synthetic", f"synthetic: {args.points} points, {args.runs} runs")
    print(f"{len(records)} results in {time.perf_counter() - began:.0f} s")
    return 0
