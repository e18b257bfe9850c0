"""What the cores give ``calibrate`` on the real scenes, and whether the cost bar is in reach.

For each database of ``real.py`` (cached in ``--out``; built there on first use), the
same runs as ``real.py`` (the stored camera and ±5 % priors, seeds ``--seeds``), each
calibrated twice in turn: with every core (``workers=None``, as ``real.py`` and the
command line run it) and with all the work on one core (``workers=1``). Interleaved, so
that a machine that slows down or speeds up during the run weighs on both alike.

Per database it prints the mean and slowest seconds of both, their ratio (what the other
cores give), and the **floor**: the one-core mean divided by the cores this process may
use, the time of the same work perfectly spread over every core (``calibrate`` uses at
most 8 workers: beyond 8 cores the floor is optimistic). Where ``real.py``'s ``real.json`` in
``--out`` has the database's mapping, the cost bar of issue 35 (calibrate ≤
max(mapping / 10, 1 s)) is beside it: a floor above the bar means that no parallel
schedule of today's work meets it on this machine, only less work.

    python benchmarks/cores.py [--scenes entry-P10,euroc-V1_01] [--databases pinhole]
        [--seeds 0-4] [--starts guess,prior] [--out benchmark_output/real]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
from real import (  # noqa: I001 (benchmarks/ is on sys.path)
    BENCHMARKS,
    add_run_arguments,
    parse_seeds,
    scene_databases,
    start_prior,
)
from real_scenes import SCENES

from colmap_trifocal import CalibrationOptions, calibrate_database
from colmap_trifocal.datasets.strecha import default_datasets_root


def cost_bars(out: Path) -> dict[tuple[str, str], float]:
    """(scene, database) → issue 35's cost bar in seconds, from ``out/real.json``'s
    summary (none where it has no row, no mapping, or the scene too few images)."""
    report = out / "real.json"
    if not report.exists():
        return {}
    rows = json.loads(report.read_text())["summary"]
    return {
        (row["scene"], row["database"]): float(row["cost_bar"])
        for row in rows
        if row.get("cost_bar") is not None
    }


def timed(database: Path, options: CalibrationOptions) -> float:
    """Wall seconds of one ``calibrate_database`` call."""
    start = time.perf_counter()
    calibrate_database(database, options)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--scenes", help="comma-separated names (default: every scene)")
    add_run_arguments(parser)
    args = parser.parse_args()
    root = default_datasets_root(BENCHMARKS.parent)
    args.out.mkdir(parents=True, exist_ok=True)
    cores = len(os.sched_getaffinity(0))
    bars = cost_bars(args.out)
    print(
        f"# calibrate on every core ({cores}) and on one, {time.strftime('%Y-%m-%d %H:%M')}, "
        f"load {os.getloadavg()[0]:.2f}; seconds are mean / slowest run\n"
    )
    print(
        "| scene | database | every core s | one core s | ratio | floor s "
        "(one core / cores) | bar s | floor ≤ bar |"
    )
    print("|---|---|---|---|---|---|---|---|")
    names = args.scenes.split(",") if args.scenes else [s.name for s in SCENES]
    for scene, truth, kind, database in scene_databases(
        names, args.databases.split(","), root, args.out
    ):
        calibrate_database(database, CalibrationOptions(seed=0))  # caches warm
        every, one = [], []
        for start in args.starts.split(","):
            for seed in parse_seeds(args.seeds):
                prior = start_prior(start, truth, seed)
                for workers, seconds in ((None, every), (1, one)):
                    options = CalibrationOptions(seed=seed, prior=prior, workers=workers)
                    seconds.append(timed(database, options))
        floor = float(np.mean(one)) / cores
        bar = bars.get((scene.name, kind))
        judged = ("", "") if bar is None else (f"{bar:.2f}", "yes" if floor <= bar else "NO")
        print(
            f"| {scene.name} | {kind} | {np.mean(every):.2f} / {max(every):.2f} "
            f"| {np.mean(one):.2f} / {max(one):.2f} | {np.mean(one) / np.mean(every):.2f} "
            f"| {floor:.2f} | {judged[0]} | {judged[1]} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
