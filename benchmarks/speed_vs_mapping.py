"""Time TrifocalCalib against COLMAP's own ways of getting intrinsics, on one database.

In the same run and on the same database (each on its own copy, all started from
the same camera):

* ``calibrate_database`` with each method (``msac-opt``, ``msac``, ``direct``,
  ``fundamental``); every call is a full, independent run (database read,
  triplets, focal search, tensors, solve), as a user would run it;
* ``pycolmap.calibrate_view_graph`` (``reestimate_relative_pose=False``, seeded);
* ``pycolmap.incremental_mapping`` refining focal length and principal point
  while mapping (the reconstruction that calibrating first is meant to
  precede; its final camera is an estimate too), followed by the global
  bundle adjustment of f and pp the project uses for refinement (timed apart).

Prints a table of seconds (median over ``--runs``), the ratio mapping / method
and, with ``--truth``, the mean relative error of (fx, fy, cx, cy).

    python benchmarks/speed_vs_mapping.py DATABASE [--images DIR] [--runs 3]
    python benchmarks/speed_vs_mapping.py /work/bench_data/fountain-P11.db \\
        --build ../shared/datasets/strecha/fountain-P11/images \\
        --truth 2759.48,2764.16,1520.69,1006.81
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from benchlib import (
    PARAMETER_NAMES,
    Stopwatch,
    copy_with_camera,
    database_summary,
    load_average,
    mean_relative_error,
    parse_intrinsics,
    quiet_stderr,
    stored_intrinsics,
)

from colmap_trifocal import CalibrationOptions, calibrate_database
from colmap_trifocal.database.features import build_database
from colmap_trifocal.reconstruction.mapping import mapping_options

CALIBRATE_METHODS = ("msac-opt", "msac", "direct", "fundamental")


@dataclass
class Timing:
    """Seconds of every run of one method and its last estimate."""

    name: str
    seconds: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)
    estimate: np.ndarray | None = None
    note: str = ""

    @property
    def median(self) -> float:
        return float(np.median(self.seconds)) if self.seconds else float("nan")

    @property
    def median_cpu(self) -> float:
        return float(np.median(self.cpu)) if self.cpu else float("nan")

    def add(self, watch: Stopwatch) -> None:
        self.seconds.append(watch.seconds)
        self.cpu.append(watch.cpu)


def build_if_missing(database: Path, images: Path, max_image_size: int) -> float:
    """Build the database (SIFT, exhaustive, one PINHOLE camera) unless it exists; seconds."""
    if database.exists():
        print(f"using the cached database {database}")
        return 0.0
    database.parent.mkdir(parents=True, exist_ok=True)
    partial = database.with_suffix(".partial.db")
    partial.unlink(missing_ok=True)
    print(f"building {database} from {images} (SIFT at {max_image_size} px, exhaustive) ...")
    with Stopwatch() as watch, quiet_stderr():
        build_database(images, partial, max_image_size=max_image_size)
    partial.rename(database)
    print(f"built in {watch.seconds:.1f} s")
    return watch.seconds


def time_calibrate(
    database: Path, method: str, prior: np.ndarray, seed: int, workers: int | None
) -> tuple[Stopwatch, np.ndarray, str]:
    """One full ``calibrate_database`` call: its stopwatch, (fx, fy, cx, cy), a note."""
    options = CalibrationOptions(
        method=method, prior=tuple(map(float, prior)), seed=seed, workers=workers
    )
    with Stopwatch() as watch:
        (result,) = calibrate_database(database, options)
    note = f"{result.num_inlier_triplets}/{result.num_triplets} triplets"
    return watch, result.intrinsics, note


def time_view_graph(
    database: Path, prior: np.ndarray, seed: int, work: Path
) -> tuple[Stopwatch, np.ndarray]:
    """``pycolmap.calibrate_view_graph`` on a copy started from ``prior``: seconds, estimate."""
    copy = copy_with_camera(database, work / "view_graph.db", prior)
    options = pycolmap.ViewGraphCalibrationOptions()
    options.random_seed = seed
    options.reestimate_relative_pose = False
    with Stopwatch() as watch, quiet_stderr():
        ok = pycolmap.calibrate_view_graph(str(copy), options)
    estimate = stored_intrinsics(copy) if ok else np.full(4, np.nan)
    copy.unlink()
    return watch, estimate


def time_mapping(
    database: Path, prior: np.ndarray, images: Path | None, seed: int, work: Path
) -> tuple[Stopwatch, Stopwatch | None, np.ndarray, np.ndarray, int, int]:
    """Incremental mapping refining f and pp on a copy, then global BA of f and pp.

    Returns the stopwatches of mapping and of the BA, the camera after mapping and after the
    global bundle adjustment, registered and total images.
    """
    copy = copy_with_camera(database, work / "mapping.db", prior)
    output = work / "sparse"
    output.mkdir(exist_ok=True)
    options = mapping_options(refine_intrinsics=True, seed=seed, colours=images is not None)
    with Stopwatch() as watch, quiet_stderr():
        models = pycolmap.incremental_mapping(copy, images or output, output, options)
    if not models:
        return watch, None, np.full(4, np.nan), np.full(4, np.nan), 0, 0
    model = max(models.values(), key=lambda r: r.num_reg_images())
    mapped = camera_of(model)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = True
    ba.refine_principal_point = True
    ba.refine_extra_params = False
    ba.print_summary = False
    with Stopwatch() as ba_watch, quiet_stderr():
        pycolmap.bundle_adjustment(model, ba)
    refined = camera_of(model)
    with pycolmap.Database.open(str(copy)) as db:
        total = db.num_images()
    copy.unlink()
    return watch, ba_watch, mapped, refined, model.num_reg_images(), total


def camera_of(model: pycolmap.Reconstruction) -> np.ndarray:
    """(fx, fy, cx, cy) of the (first) camera of a reconstruction."""
    camera = next(iter(model.cameras.values()))
    return np.array(
        [
            camera.focal_length_x,
            camera.focal_length_y,
            camera.principal_point_x,
            camera.principal_point_y,
        ]
    )


def print_table(
    timings: list[Timing],
    mapping: float,
    mapping_cpu: float,
    truth: np.ndarray | None,
    prior: np.ndarray,
) -> None:
    """Markdown table: method, median wall and CPU seconds, runs, mapping / method, error."""
    print(
        "| method | median s | runs s | CPU s | mapping / method (wall) | (CPU) | error % "
        "| fx | fy | cx | cy | note |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    if truth is not None:
        print(
            f"| (start: the prior) | - | - | - | - | - | {mean_relative_error(prior, truth):.3f} | "
            + " | ".join(f"{v:.1f}" for v in prior)
            + " | |"
        )
    for t in timings:
        runs = ", ".join(f"{s:.2f}" for s in t.seconds)
        ratio = mapping / t.median if t.median > 0 and not t.name.startswith(" ") else np.nan
        ratio_cpu = (
            mapping_cpu / t.median_cpu
            if t.median_cpu > 0 and not t.name.startswith(" ")
            else np.nan
        )
        if t.estimate is None:
            error, values = "-", " | ".join("-" for _ in PARAMETER_NAMES)
        else:
            error = f"{mean_relative_error(t.estimate, truth):.3f}" if truth is not None else "-"
            values = " | ".join(f"{v:.1f}" for v in t.estimate)
        shown = "-" if np.isnan(ratio) else f"{ratio:.1f}"
        shown_cpu = "-" if np.isnan(ratio_cpu) else f"{ratio_cpu:.1f}"
        print(
            f"| {t.name} | {t.median:.2f} | {runs} | {t.median_cpu:.2f} | {shown} | {shown_cpu} "
            f"| {error} | {values} | {t.note} |"
        )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "database", type=Path, help="COLMAP database (built with --build if missing)"
    )
    parser.add_argument("--images", type=Path, help="image folder (mapping colours; optional)")
    parser.add_argument(
        "--build",
        type=Path,
        metavar="IMAGES",
        help="build DATABASE from this image folder first (SIFT, exhaustive, one PINHOLE "
        "camera) unless it exists (the cache)",
    )
    parser.add_argument(
        "--max-image-size", type=int, default=1600, help="SIFT image size (--build)"
    )
    parser.add_argument("--runs", type=int, default=1, help="timed runs of each method")
    parser.add_argument(
        "--truth", help="ground truth FX,FY,CX,CY, or a ground_truth.json / Strecha .camera file"
    )
    parser.add_argument(
        "--prior", help="starting camera FX,FY,CX,CY for every method (default: the stored camera)"
    )
    parser.add_argument(
        "--methods",
        default=",".join((*CALIBRATE_METHODS, "view_graph", "mapping")),
        help="comma-separated subset of msac-opt,msac,direct,fundamental,view_graph,mapping",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--workers", type=int, default=None, help="calibrate workers (default: cores)"
    )
    parser.add_argument("--json", type=Path, help="write the timings and estimates here")
    args = parser.parse_args(argv)

    pycolmap.logging.minloglevel = 2
    if args.build is not None:
        build_if_missing(args.database, args.build, args.max_image_size)
        args.images = args.images or args.build
    if not args.database.exists():
        parser.error(f"no database at {args.database} (use --build IMAGES)")
    truth = parse_intrinsics(args.truth) if args.truth else None
    prior = parse_intrinsics(args.prior) if args.prior else stored_intrinsics(args.database)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    summary = database_summary(args.database)
    print(
        f"{args.database}: {summary['images']} images, {summary['pairs']} verified pairs, "
        f"{summary['keypoints_per_image']:.0f} keypoints/image, "
        f"{summary['matches_per_pair']:.0f} inlier matches/pair; "
        f"start {', '.join(f'{v:.1f}' for v in prior)}; {args.runs} run(s)",
        flush=True,
    )

    timings: list[Timing] = []
    mapping_seconds = mapping_cpu = float("nan")
    load_before = load_average()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for method in methods:
            if method in CALIBRATE_METHODS:
                timing = Timing(f"calibrate {method}")
                for run in range(args.runs):
                    watch, estimate, note = time_calibrate(
                        args.database, method, prior, args.seed + run, args.workers
                    )
                    timing.add(watch)
                    timing.estimate, timing.note = estimate, note
            elif method == "view_graph":
                timing = Timing("pycolmap.calibrate_view_graph (focal only)")
                for run in range(args.runs):
                    watch, estimate = time_view_graph(args.database, prior, args.seed + run, work)
                    timing.add(watch)
                    timing.estimate = estimate
            elif method == "mapping":
                timing = Timing("pycolmap.incremental_mapping (refine f, pp)")
                ba = Timing("  + global BA of f, pp (after mapping)")
                for run in range(args.runs):
                    watch, ba_watch, mapped, refined, registered, total = time_mapping(
                        args.database, prior, args.images, args.seed + run, work
                    )
                    timing.add(watch)
                    if ba_watch is not None:
                        ba.add(ba_watch)
                    timing.estimate, ba.estimate = mapped, refined
                    timing.note = f"registered {registered}/{total} images"
                mapping_seconds, mapping_cpu = timing.median, timing.median_cpu
                timings += [timing, ba]
                print(f"  {timing.name}: {timing.median:.2f} s", flush=True)
                continue
            else:
                parser.error(f"unknown method {method!r}")
            timings.append(timing)
            print(f"  {timing.name}: {timing.median:.2f} s", flush=True)

    print(
        f"\n1-minute load average: {load_before:.2f} before, {load_average():.2f} after "
        f"({os.cpu_count()} cores; a load above the core count means other processes "
        "competed for the CPU and wall-clock times are inflated)"
    )
    print_table(timings, mapping_seconds, mapping_cpu, truth, prior)
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "database": str(args.database),
                    "summary": summary,
                    "prior": prior.tolist(),
                    "truth": None if truth is None else truth.tolist(),
                    "load_average": [load_before, load_average()],
                    "results": [
                        {
                            "name": t.name,
                            "seconds": t.seconds,
                            "cpu_seconds": t.cpu,
                            "estimate": None if t.estimate is None else t.estimate.tolist(),
                            "note": t.note,
                        }
                        for t in timings
                    ],
                },
                indent=2,
            )
        )
    sys.stdout.flush()


if __name__ == "__main__":
    main()
