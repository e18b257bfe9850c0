"""``colmap-trifocal evaluate`` and ``colmap-trifocal synthetic``: parse, run, write outputs."""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from ..common.arguments import finite_float, seed
from ..common.errors import CalibrationError
from ..common.files import file_identity, refuse_overwriting_input
from ..datasets import DATASET_KINDS, read_scene
from .protocol import DEFAULT_METHODS, EVALUATION_METHODS, EvaluationOptions, evaluate_scene
from .records import RunRecord
from .report import markdown_table, summarize, with_prior_rows, write_outputs
from .runner import run_tasks
from .synthetic_experiment import NOISE_LEVELS, SYNTHETIC_METHODS, run_synthetic_case


def add_evaluate_parser(commands: argparse._SubParsersAction) -> None:
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
        "--mapping-runs", type=int, default=3, help="runs of the mapping baseline (default 3)"
    )
    parser.add_argument("--max-image-size", type=int, default=1600)
    _add_common(parser, "evaluation")
    parser.add_argument(
        "--cache", type=Path, help="keep the per-scene databases here (default: temporary)"
    )


def add_synthetic_parser(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser("synthetic", help="the paper's synthetic experiment")
    parser.add_argument(
        "--noise", default=",".join(f"{n:g}" for n in NOISE_LEVELS), help="pixel noise levels"
    )
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--points", type=int, default=500, help="tracks per scene")
    parser.add_argument(
        "--perturbation", type=finite_float, default=5.0, help="prior ±%% (default 5)"
    )
    parser.add_argument("--outliers", type=float, default=0.0, help="outlier track fraction")
    parser.add_argument("--methods", default=",".join(SYNTHETIC_METHODS))
    _add_common(parser, "synthetic")


def _add_common(parser: argparse.ArgumentParser, stem: str) -> None:
    parser.add_argument("--seed", type=seed, default=0)
    parser.add_argument(
        "--output",
        type=Path,
        default=Path(stem),
        help=f"folder for {stem}.csv, {stem}.md and {stem}.png (default ./{stem})",
    )
    parser.add_argument("--json", type=Path, metavar="OUT", help="write every run as JSON")
    parser.add_argument("--workers", type=int, help="local processes (default: one per core)")
    parser.add_argument("--dask", metavar="ADDRESS", help="run on this Dask scheduler instead")


def _numbers(text: str, name: str, kind: type = float) -> list:
    try:
        values = [kind(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise CalibrationError(
            f"malformed {name} {text!r}: expected comma-separated numbers"
        ) from None
    if not values:
        raise CalibrationError(f"{name} is empty")
    if not all(math.isfinite(v) for v in values):
        raise CalibrationError(f"invalid {name} {text!r}: values must be finite")
    return values


def _ranges(text: str) -> tuple[tuple[float, float], ...]:
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


def _methods(text: str, allowed: tuple[str, ...]) -> tuple[str, ...]:
    methods = tuple(m.strip() for m in text.split(",") if m.strip())
    unknown = [m for m in methods if m not in allowed]
    if unknown or not methods:
        raise CalibrationError(
            f"unknown method {unknown[0] if unknown else ''!r} (choose from {','.join(allowed)})"
        )
    return methods


def _check_outputs(args: argparse.Namespace) -> None:
    if args.runs < 1:
        raise CalibrationError("--runs must be at least 1")
    if args.json is not None and not args.json.parent.is_dir():
        raise CalibrationError(f"cannot write --json: folder {args.json.parent} does not exist")


def _refuse_overwriting_dataset(args: argparse.Namespace, stem: str) -> None:
    """Refuse outputs that are files of the dataset (or of the cache) being evaluated.

    Every regular file below ``PATH`` and ``--cache`` counts as an input, except files
    no dataset reader reads: JSON files and this command's own outputs
    (``evaluation.csv``, ``.md``, ``.png``), which a rerun replaces. Compared by file
    identity, so symlinks and hard links are caught.
    """
    own = {f"{stem}.csv", f"{stem}.md", f"{stem}.png"}
    outputs = {"--output": [args.output / name for name in sorted(own)], "--json": [args.json]}
    targets = {
        file_identity(path): (option, path)
        for option, paths in outputs.items()
        for path in paths
        if path is not None and file_identity(path) is not None
    }
    if not targets:
        return
    for folder in (args.path, args.cache):
        if folder is None or not Path(folder).exists():
            continue
        files = [Path(folder)] if Path(folder).is_file() else Path(folder).rglob("*")
        for path in files:
            if path.suffix.lower() == ".json" or path.name in own or not path.is_file():
                continue
            hit = targets.get(file_identity(path))
            if hit is not None:
                option, output = hit
                refuse_overwriting_input(output, [path], option, "a file of the dataset")


def _finish(records: list[RunRecord], args: argparse.Namespace, stem: str, title: str) -> None:
    try:
        paths = write_outputs(records, args.output, stem, title)
        if args.json is not None:
            args.json.write_text(json.dumps([r.to_json() for r in records], indent=1) + "\n")
    except OSError as exc:
        raise CalibrationError(f"cannot write the results: {exc.strerror or exc}") from None
    print(markdown_table(summarize(with_prior_rows(records))), end="")
    print(f"wrote {paths['csv']}, {paths['markdown']}, {paths['png']}")


def scenes_at(kind: str, path: Path) -> list:
    """The scene at ``path``, or every scene in its sub-folders."""
    if not path.exists():
        raise CalibrationError(f"{path} does not exist")
    try:
        return [read_scene(kind, path)]
    except CalibrationError as error:
        scenes = []
        if path.is_dir():
            for child in sorted(p for p in path.iterdir() if p.is_dir()):
                try:
                    scenes.append(read_scene(kind, child))
                except CalibrationError:
                    continue
        if not scenes:
            raise error from None
        return scenes


def run_evaluate(args: argparse.Namespace, progress: bool) -> int:
    _check_outputs(args)
    _refuse_overwriting_dataset(args, "evaluation")
    options = EvaluationOptions(
        image_counts=tuple(_numbers(args.images, "--images", int)),
        perturbations=_ranges(args.perturbation),
        runs=args.runs,
        mapping_runs=args.mapping_runs,
        methods=_methods(args.methods, EVALUATION_METHODS),
        seed=args.seed,
        max_image_size=args.max_image_size,
        cache=args.cache,
        workers=args.workers,
        dask_address=args.dask,
        progress=progress,
    )
    if min(options.image_counts) < 3:
        raise CalibrationError("--images: every sequence needs at least 3 images")
    start = time.perf_counter()
    scenes = scenes_at(args.kind, args.path)
    for scene in scenes:  # all checked before the first (long) evaluation
        if not Path(scene.image_dir).is_dir():
            raise CalibrationError(
                f"scene {scene.name}: image folder {scene.image_dir} does not exist"
            )
    records = [r for scene in scenes for r in evaluate_scene(scene, options)]
    _finish(records, args, "evaluation", f"{args.kind}: {args.runs} runs")
    print(f"{len(records)} results in {time.perf_counter() - start:.0f} s")
    return 0


def _synthetic_task(task: tuple) -> list[RunRecord]:
    noise, run, seed, methods, points, fraction, outliers = task
    return run_synthetic_case(noise, run, seed, methods, points, fraction, outliers)


def run_synthetic(args: argparse.Namespace, progress: bool) -> int:
    _check_outputs(args)
    noise_levels = _numbers(args.noise, "--noise")
    if min(noise_levels) < 0:
        raise CalibrationError("--noise levels must be >= 0")
    if not 0 <= args.perturbation < 100:
        raise CalibrationError("--perturbation must be in [0, 100) percent")
    if args.points < 10:
        raise CalibrationError("--points must be at least 10")
    if not 0 <= args.outliers < 1:
        raise CalibrationError("--outliers must be in [0, 1)")
    methods = _methods(args.methods, (*SYNTHETIC_METHODS, "msac"))
    seeds = np.random.SeedSequence(args.seed).generate_state(args.runs)
    tasks = [
        (noise, run, int(seeds[run]), methods, args.points, args.perturbation / 100, args.outliers)
        for noise in noise_levels
        for run in range(args.runs)
    ]
    start = time.perf_counter()
    results = run_tasks(_synthetic_task, tasks, args.workers, args.dask, "synthetic runs", progress)
    records = [r for rs in results for r in rs]
    _finish(records, args, "synthetic", f"synthetic: {args.points} points, {args.runs} runs")
    print(f"{len(records)} results in {time.perf_counter() - start:.0f} s")
    return 0
