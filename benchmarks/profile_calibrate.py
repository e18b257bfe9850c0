"""Where calibrate_database spends its time and memory, on one database.

Runs one ``calibrate_database`` call under cProfile (``--workers 1`` by default,
so the tensor estimation runs in this process and is visible to the profiler),
while a thread samples this process's RSS every ``--interval`` seconds and a
logging handler records when each stage starts (the package logs one INFO line
per stage). Prints:

* the stages: time between consecutive log lines and the peak RSS in each;
* the cumulative seconds of the pipeline's main functions, looked up by name in
  the profile (those that exist in the installed version);
* the top functions by cumulative and by own time.

    python benchmarks/profile_calibrate.py DATABASE [--prior FX,FY,CX,CY] [--top 25]
        [--pstats out.prof]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import logging
import pstats
import threading
import time
from pathlib import Path

import psutil

from colmap_trifocal import CalibrationOptions, calibrate_database

#: Functions of the pipeline whose cumulative time is shown, by module and name.
STAGE_FUNCTIONS = (
    ("snapshot.py", "read_database"),
    ("camera_input.py", "camera_input"),
    ("triplet_selection.py", "select_camera_triplets"),
    ("parallax.py", "plane_parallax"),
    ("focal_search.py", "search_focal"),
    ("tensor_estimation.py", "calibrated_hypothesis"),
    ("tensor_set.py", "at"),
    ("tensor_set.py", "with_second_starts"),
    ("tensor_estimation.py", "estimate_triplet_tensor"),
    ("projective_ba.py", "refine_triplet"),
    ("selfcalibration.py", "solve_with_fallback"),
    ("polish.py", "not_worth_it"),
    ("triplet_bundle.py", "polish_intrinsics"),
    ("assessment.py", "assess"),
    ("fundamental.py", "calibrate_fundamental"),
)


class StageLog(logging.Handler):
    """Keeps (time, message) of every log record of the package."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.records: list[tuple[float, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append((time.perf_counter(), record.getMessage()))


class MemorySampler(threading.Thread):
    """Samples this process's RSS (bytes) with timestamps until stopped."""

    def __init__(self, interval: float) -> None:
        super().__init__(daemon=True)
        self.interval = interval
        self.samples: list[tuple[float, int]] = []
        self._stop_event = threading.Event()
        self._process = psutil.Process()

    def run(self) -> None:
        while not self._stop_event.is_set():
            self.samples.append((time.perf_counter(), self._process.memory_info().rss))
            self._stop_event.wait(self.interval)

    def stop(self) -> None:
        self._stop_event.set()
        self.join()


def stage_table(
    start: float, end: float, records: list[tuple[float, str]], samples: list[tuple[float, int]]
) -> str:
    """One row per interval between log lines: seconds, peak RSS, the line that closed it."""
    marks = [(start, "(start)"), *records, (end, "(end: calibrate_database returned)")]
    lines = ["| until log line | seconds | peak RSS MB |", "|---|---|---|"]
    for (t0, _), (t1, message) in zip(marks[:-1], marks[1:], strict=True):
        inside = [rss for t, rss in samples if t0 <= t <= t1]
        peak = max(inside) / 2**20 if inside else float("nan")
        lines.append(f"| {message[:90]} | {t1 - t0:.2f} | {peak:.0f} |")
    return "\n".join(lines)


def function_table(stats: pstats.Stats) -> str:
    """Cumulative seconds and calls of the pipeline functions found in the profile."""
    raw = stats.stats  # type: ignore[attr-defined]
    lines = ["| function | calls | cumulative s | own s |", "|---|---|---|---|"]
    for module, name in STAGE_FUNCTIONS:
        for (filename, line, function), (_, calls, own, cumulative, _) in raw.items():
            if function == name and filename.endswith(module) and "colmap_trifocal" in filename:
                lines.append(
                    f"| {module}:{line} {function} | {calls} | {cumulative:.2f} | {own:.2f} |"
                )
    return "\n".join(lines)


def top(stats: pstats.Stats, key: str, count: int) -> str:
    """The ``count`` first rows of the profile sorted by ``key``."""
    stream = io.StringIO()
    stats.stream = stream  # type: ignore[attr-defined]
    stats.sort_stats(key).print_stats(count)
    text = stream.getvalue()
    return text[text.find("   ncalls") :]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("database", type=Path)
    parser.add_argument("--prior", help="FX,FY,CX,CY (default: the stored camera)")
    parser.add_argument("--method", default="msac-opt")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=1, help="1: everything in this process")
    parser.add_argument("--top", type=int, default=25, help="rows of the top-function lists")
    parser.add_argument("--interval", type=float, default=0.02, help="RSS sampling, seconds")
    parser.add_argument("--pstats", type=Path, help="also write the raw profile here")
    args = parser.parse_args(argv)

    handler = StageLog()
    package = logging.getLogger("colmap_trifocal")
    package.addHandler(handler)
    package.setLevel(logging.INFO)
    prior = tuple(float(v) for v in args.prior.split(",")) if args.prior else None
    options = CalibrationOptions(
        method=args.method, prior=prior, seed=args.seed, workers=args.workers
    )
    sampler = MemorySampler(args.interval)
    sampler.start()
    profiler = cProfile.Profile()
    start = time.perf_counter()
    profiler.enable()
    (camera,) = calibrate_database(args.database, options)
    profiler.disable()
    end = time.perf_counter()
    sampler.stop()
    if args.pstats:
        profiler.dump_stats(args.pstats)
    stats = pstats.Stats(profiler)
    print(
        f"{args.database}: {args.method}, workers {args.workers}: {end - start:.2f} s (profiled), "
        f"peak RSS {max(r for _, r in sampler.samples) / 2**20:.0f} MB; "
        f"fx {camera.fx:.1f} fy {camera.fy:.1f} cx {camera.cx:.1f} cy {camera.cy:.1f}, "
        f"{camera.num_inlier_triplets}/{camera.num_triplets} triplets\n"
    )
    print(stage_table(start, end, handler.records, sampler.samples))
    print()
    print(function_table(stats))
    print(f"\ntop {args.top} by cumulative time:\n")
    print(top(stats, "cumulative", args.top))
    print(f"top {args.top} by own time:\n")
    print(top(stats, "tottime", args.top))


if __name__ == "__main__":
    main()
