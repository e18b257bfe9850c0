"""How calibrate's time and memory grow with the number of images (synthetic databases).

For each image count (default 10, 30, 100, 300) and view graph, a synthetic COLMAP
database is built once (cached in ``--out``) and ``calibrate_database`` (msac-opt,
a ±5 % prior, seeded) is run in a fresh Python subprocess. The parent samples the
memory of the subprocess and all its descendants (the tensor workers) every
``--interval`` seconds with psutil and reports the peak of the sum of their PSS
(proportional set size: pages shared between the forked workers and their parent
are split between them, so the sum is the memory the tree really holds) and, for
comparison, of their RSS (which counts shared pages once per process and so
overstates a forked pool).

The databases: ``pycolmap.synthesize_dataset`` places the cameras (one shared
PINHOLE camera, the Strecha K at 3072x2048; cameras on a sphere of radius 5
looking at the origin) and the 3D points (on the unit sphere), and writes images
and keypoints (every point projects into every image, plus unmatched random
keypoints up to ``--keypoints`` per image); ``pycolmap.synthesize_noise`` adds
Gaussian keypoint noise. Its match configurations are not used for the pairs:
``EXHAUSTIVE`` writes every pair with every point (no occlusion: a point on the
far side of the sphere is matched too) and costs O(points²) per pair;
``CHAINED`` writes only pairs (i, i+1), which have no 3-cycles and hence give no
triplet at all; ``SPARSE`` removes random pairs while keeping the graph connected
(random, not local, neighbours; O(pairs²)). Instead this script writes the
verified two-view geometries itself (``match_sparsity = 1`` makes pycolmap write
none), with occlusion by the sphere (a point is seen only from the side its
surface faces) and one of these view graphs:

* ``knn`` (default): every image is matched with its ``--neighbours`` nearest
  images by viewing direction, like a user who matches by retrieval or
  sequentially (tens of neighbours per image, not all n(n−1)/2 pairs);
* ``exhaustive``: every pair that shares at least 15 points (COLMAP's minimum
  number of inliers for a verified pair).

Wall-clock times are inflated when other processes compete for the cores: the
table also gives the CPU seconds of the subprocess tree and the 1-minute load
average when each run started.

A share ``--outliers`` of each pair's verified matches are wrong (random keypoint
pairs), as geometric verification lets some through. The true F is stored.

    python benchmarks/scaling.py [--sizes 10,30,100,300] [--graphs knn,exhaustive] \\
        [--out benchmark_output/synthetic] [--plot scaling.png]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sqlite3
import subprocess
import sys
import time
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np
import psutil
import pycolmap
from tqdm import tqdm

STRECHA_K = (2759.48, 2764.16, 1520.69, 1006.81)
WIDTH, HEIGHT = 3072, 2048
MIN_INLIERS = 15


@dataclass
class Measurement:
    """One calibrate run: sizes, time, peak memory, error."""

    graph: str
    images: int
    pairs: int
    view_graph_triplets: int
    triplets: int | None = None
    inlier_triplets: int | None = None
    calibrate_seconds: float | None = None
    process_seconds: float | None = None
    process_cpu_seconds: float | None = None
    load_average: float | None = None
    peak_pss_mb: float | None = None
    peak_rss_mb: float | None = None
    error_percent: float | None = None
    status: str = "ok"


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def view_graph(
    directions: np.ndarray, common: np.ndarray, graph: str, k: int
) -> list[tuple[int, int]]:
    """Index pairs (i < j) of the view graph (see the module docstring)."""
    n = len(directions)
    if graph == "exhaustive":
        return [(i, j) for i, j in combinations(range(n), 2) if common[i, j] >= MIN_INLIERS]
    if graph != "knn":
        raise SystemExit(f"error: unknown graph {graph!r} (knn or exhaustive)")
    cosines = directions @ directions.T
    np.fill_diagonal(cosines, -np.inf)
    pairs = set()
    for i in range(n):
        for j in np.argsort(-cosines[i])[: min(k, n - 1)]:
            if common[i, j] >= MIN_INLIERS:
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def count_triangles(pairs: list[tuple[int, int]]) -> int:
    """Triplets whose three pairs are all in the view graph (candidates for tensors)."""
    neighbours: dict[int, set[int]] = {}
    for a, b in pairs:
        neighbours.setdefault(a, set()).add(b)
        neighbours.setdefault(b, set()).add(a)
    return sum(len({c for c in neighbours[a] & neighbours[b] if c > b}) for a, b in pairs)


def build_database(
    path: Path,
    num_images: int,
    graph: str,
    seed: int,
    points: int,
    keypoints: int,
    noise_px: float,
    outliers: float,
    neighbours: int,
) -> dict:
    """Write the synthetic database; returns its ground truth and statistics (also as JSON)."""
    partial = path.with_suffix(".partial.db")
    partial.unlink(missing_ok=True)
    rng = np.random.default_rng(seed)
    pycolmap.set_random_seed(seed)
    options = pycolmap.SyntheticDatasetOptions(
        num_rigs=1,
        num_cameras_per_rig=1,
        num_frames_per_rig=num_images,
        num_points3D=points,
        num_points2D_without_point3D=max(0, keypoints - points),
        camera_model_id=pycolmap.CameraModelId.PINHOLE,
        camera_params=list(STRECHA_K),
        camera_width=WIDTH,
        camera_height=HEIGHT,
        match_config=pycolmap.SyntheticDatasetMatchConfig.SPARSE,
        match_sparsity=1.0,  # no pairs: written below
    )
    truth = np.array(STRECHA_K)
    prior = truth * (1.0 + rng.uniform(-0.05, 0.05, 4))
    with pycolmap.Database.open(str(partial)) as db:
        reconstruction = pycolmap.synthesize_dataset(options, db)
        pycolmap.synthesize_noise(
            pycolmap.SyntheticNoiseOptions(point2D_stddev=noise_px), reconstruction, db
        )
        image_ids = sorted(reconstruction.images)
        point_ids = sorted(reconstruction.points3D)
        column = {p: c for c, p in enumerate(point_ids)}
        xyz = np.array([reconstruction.points3D[p].xyz for p in point_ids])
        # index[i, c]: keypoint of point c in image i (-1: not observed).
        index = np.full((len(image_ids), len(point_ids)), -1, np.int64)
        centers, rotations, translations, counts = [], [], [], []
        for row, image_id in enumerate(image_ids):
            image = reconstruction.images[image_id]
            for k, p2d in enumerate(image.points2D):
                if p2d.has_point3D():
                    index[row, column[p2d.point3D_id]] = k
            pose = image.cam_from_world()
            rotations.append(pose.rotation.matrix())
            translations.append(pose.translation)
            centers.append(image.projection_center())
            counts.append(image.num_points2D())
        centers = np.array(centers)
        # Occlusion by the sphere: a point is seen from where its surface faces.
        visible = (index >= 0) & ((centers @ xyz.T) - 1.0 > 0.0)
        common = visible.astype(np.float32) @ visible.T.astype(np.float32)
        directions = centers / np.linalg.norm(centers, axis=1, keepdims=True)
        pairs = view_graph(directions, common, graph, neighbours)
        K = np.array([[truth[0], 0, truth[2]], [0, truth[1], truth[3]], [0, 0, 1.0]])
        Kinv = np.linalg.inv(K)
        matches_per_pair = []
        for i, j in tqdm(pairs, desc=f"{graph}-{num_images}: pairs", leave=False):
            shared = visible[i] & visible[j]
            inliers = np.column_stack([index[i, shared], index[j, shared]])
            wrong = int(round(len(inliers) * outliers / max(1e-9, 1.0 - outliers)))
            if wrong:
                bad = np.column_stack(
                    [rng.integers(0, counts[i], wrong), rng.integers(0, counts[j], wrong)]
                )
                inliers = np.concatenate([inliers, bad])
                inliers = inliers[rng.permutation(len(inliers))]
            R = rotations[j] @ rotations[i].T
            t = translations[j] - R @ translations[i]
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            geometry.F = Kinv.T @ skew(t) @ R @ Kinv
            geometry.inlier_matches = inliers.astype(np.uint32)
            db.write_two_view_geometry(image_ids[i], image_ids[j], geometry)
            matches_per_pair.append(len(inliers))
        camera = db.read_all_cameras()[0]
        camera.params = prior
        db.update_camera(camera)
        db.clear_descriptors()  # random bytes nothing downstream reads; 1 KB per keypoint
    with sqlite3.connect(partial) as connection:
        connection.execute("VACUUM")
    partial.rename(path)
    info = {
        "graph": graph,
        "images": num_images,
        "seed": seed,
        "truth": truth.tolist(),
        "prior": prior.tolist(),
        "pairs": len(pairs),
        "view_graph_triplets": count_triangles(pairs),
        "keypoints_per_image": float(np.mean(counts)),
        "visible_points_per_image": float(visible.sum(1).mean()),
        "matches_per_pair": float(np.mean(matches_per_pair)) if matches_per_pair else 0.0,
        "noise_px": noise_px,
        "outliers": outliers,
        "neighbours": neighbours if graph == "knn" else None,
    }
    path.with_suffix(".json").write_text(json.dumps(info, indent=1))
    return info


def tree_memory(process: psutil.Process) -> tuple[float, float]:
    """Sum of PSS and of RSS (bytes) of a process and all its descendants."""
    pss = rss = 0.0
    try:
        members = [process, *process.children(recursive=True)]
    except psutil.NoSuchProcess:
        return 0.0, 0.0
    for member in members:
        try:
            info = member.memory_full_info()
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
        pss += info.pss
        rss += info.rss
    return pss, rss


def kill_tree(process: psutil.Process) -> None:
    """Kill a process we started and its descendants (by pid)."""
    try:
        members = process.children(recursive=True)
    except psutil.NoSuchProcess:
        members = []
    for member in [*members, process]:
        try:
            member.kill()
        except psutil.NoSuchProcess:
            pass


def measure(
    database: Path,
    info: dict,
    seed: int,
    timeout: float,
    interval: float,
    log: Path,
    workers: int | None = None,
) -> Measurement:
    """calibrate_database in a fresh subprocess, sampling the memory of its process tree."""
    result = Measurement(info["graph"], info["images"], info["pairs"], info["view_graph_triplets"])
    command = [
        sys.executable,
        __file__,
        "--child",
        str(database),
        "--prior",
        ",".join(map(str, info["prior"])),
        "--seed",
        str(seed),
        *(["--workers", str(workers)] if workers is not None else []),
    ]
    peak_pss = peak_rss = 0.0
    result.load_average = os.getloadavg()[0]
    cpu_start = children_cpu()
    start = time.perf_counter()
    with log.open("w") as stderr:
        child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=stderr, text=True)
        process = psutil.Process(child.pid)
        while child.poll() is None:
            pss, rss = tree_memory(process)
            peak_pss, peak_rss = max(peak_pss, pss), max(peak_rss, rss)
            if time.perf_counter() - start > timeout:
                kill_tree(process)
                child.wait()
                result.status = f"timeout after {timeout:.0f} s; last log: {last_line(log)}"
                break
            time.sleep(interval)
        output = child.stdout.read() if child.stdout else ""
    result.process_seconds = time.perf_counter() - start
    result.process_cpu_seconds = children_cpu() - cpu_start
    result.peak_pss_mb, result.peak_rss_mb = peak_pss / 2**20, peak_rss / 2**20
    if result.status != "ok":
        return result
    if child.returncode != 0:
        result.status = f"exit {child.returncode}: {last_line(log)}"
        return result
    data = json.loads(output.strip().splitlines()[-1])
    result.calibrate_seconds = data["seconds"]
    result.triplets, result.inlier_triplets = data["num_triplets"], data["num_inlier_triplets"]
    truth = np.array(info["truth"])
    result.error_percent = float(np.mean(np.abs(np.array(data["intrinsics"]) / truth - 1)) * 100)
    return result


def children_cpu() -> float:
    """User + system CPU seconds of the finished (waited-for) subprocesses and theirs."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def last_line(log: Path) -> str:
    """The last non-empty line (or progress-bar update) of a log file."""
    text = log.read_text(errors="replace").replace("\r", "\n")
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else "(empty)"


def child_main(database: Path, prior: str, seed: int, workers: int | None) -> None:
    """Run in the subprocess: one calibrate_database call, result as one JSON line."""
    import logging

    from colmap_trifocal import CalibrationOptions, calibrate_database

    logging.basicConfig(level=logging.INFO, format="%(relativeCreated)8.0f ms %(message)s")
    logging.getLogger("colmap_trifocal").setLevel(logging.INFO)
    options = CalibrationOptions(
        method="msac-opt",
        prior=tuple(float(v) for v in prior.split(",")),
        seed=seed,
        progress=True,
        workers=workers,
    )
    start = time.perf_counter()
    (camera,) = calibrate_database(database, options)
    seconds = time.perf_counter() - start
    print(
        json.dumps(
            {
                "seconds": seconds,
                "intrinsics": camera.intrinsics.tolist(),
                "num_triplets": camera.num_triplets,
                "num_inlier_triplets": camera.num_inlier_triplets,
            }
        )
    )


def print_table(rows: list[Measurement]) -> None:
    def fmt(value: float | int | None, spec: str) -> str:
        return "-" if value is None else format(value, spec)

    print(
        "| graph | images | pairs | view-graph triplets | triplets used (inliers) | "
        "calibrate s | process s | process CPU s | load | peak PSS MB | peak RSS MB | error % "
        "| status |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        used = "-" if r.triplets is None else f"{r.triplets} ({r.inlier_triplets})"
        print(
            f"| {r.graph} | {r.images} | {r.pairs} | {r.view_graph_triplets} | {used} | "
            f"{fmt(r.calibrate_seconds, '.2f')} | {fmt(r.process_seconds, '.2f')} | "
            f"{fmt(r.process_cpu_seconds, '.2f')} | {fmt(r.load_average, '.1f')} | "
            f"{fmt(r.peak_pss_mb, '.0f')} | {fmt(r.peak_rss_mb, '.0f')} | "
            f"{fmt(r.error_percent, '.3f')} | {r.status} |"
        )


def plot(rows: list[Measurement], path: Path) -> None:
    """Time and peak PSS against the number of images (log-log), one line per graph."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for graph in sorted({r.graph for r in rows}):
        done = [r for r in rows if r.graph == graph and r.calibrate_seconds is not None]
        if not done:
            continue
        n = [r.images for r in done]
        axes[0].plot(n, [r.calibrate_seconds for r in done], "o-", label=graph)
        axes[1].plot(n, [r.peak_pss_mb for r in done], "o-", label=graph)
    axes[0].axhline(30, color="grey", ls=":", label="30 s bar")
    axes[1].axhline(2048, color="grey", ls=":", label="2 GB bar")
    for ax, label in zip(axes, ("calibrate seconds", "peak PSS of the tree, MB"), strict=True):
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            axis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
        ax.set_xlabel("images")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle("calibrate_database (msac-opt, ±5 % prior) on synthetic databases")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", default="10,30,100,300", help="image counts")
    parser.add_argument("--graphs", default="knn,exhaustive", help="knn and/or exhaustive")
    parser.add_argument("--neighbours", type=int, default=20, help="knn: neighbours per image")
    parser.add_argument(
        "--exhaustive-max", type=int, default=300, help="skip exhaustive graphs above this size"
    )
    parser.add_argument(
        "--out", type=Path, default=Path("benchmark_output/synthetic"), help="database cache"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--points", type=int, default=6000, help="3D points (unit sphere)")
    parser.add_argument("--keypoints", type=int, default=8000, help="keypoints per image")
    parser.add_argument("--noise", type=float, default=0.5, help="keypoint noise std, pixels")
    parser.add_argument("--outliers", type=float, default=0.1, help="share of wrong matches")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per calibrate run")
    parser.add_argument("--interval", type=float, default=0.05, help="memory sampling, seconds")
    parser.add_argument(
        "--workers", type=int, help="calibrate's worker processes (default: its own, one per core)"
    )
    parser.add_argument("--plot", type=Path, help="write a PNG of time and memory vs images")
    parser.add_argument("--json", type=Path, help="write the measurements here")
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--prior", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child is not None:
        child_main(args.child, args.prior, args.seed, args.workers)
        return

    pycolmap.logging.minloglevel = 2
    args.out.mkdir(parents=True, exist_ok=True)
    rows: list[Measurement] = []
    for graph in [g.strip() for g in args.graphs.split(",") if g.strip()]:
        for n in [int(v) for v in args.sizes.split(",")]:
            if graph == "exhaustive" and n > args.exhaustive_max:
                continue
            name = f"{graph}{args.neighbours if graph == 'knn' else ''}-{n}-seed{args.seed}"
            database = args.out / f"{name}.db"
            if database.exists():
                info = json.loads(database.with_suffix(".json").read_text())
            else:
                start = time.perf_counter()
                info = build_database(
                    database, n, graph, args.seed, args.points, args.keypoints,
                    args.noise, args.outliers, args.neighbours,
                )  # fmt: skip
                print(f"built {database} in {time.perf_counter() - start:.1f} s", flush=True)
            print(
                f"{name}: {info['pairs']} pairs, {info['view_graph_triplets']} view-graph "
                f"triplets, {info['matches_per_pair']:.0f} matches/pair; calibrating ...",
                flush=True,
            )
            row = measure(
                database, info, args.seed, args.timeout, args.interval,
                database.with_suffix(f".workers{args.workers}.log" if args.workers else ".log"),
                args.workers,
            )  # fmt: skip
            rows.append(row)
            print(
                f"  {row.calibrate_seconds or float('nan'):.2f} s, peak PSS "
                f"{row.peak_pss_mb:.0f} MB, error {row.error_percent or float('nan'):.3f} %, "
                f"{row.status}",
                flush=True,
            )
    print()
    print_table(rows)
    if args.plot:
        plot(rows, args.plot)
        print(f"\nplot: {args.plot}")
    if args.json:
        args.json.write_text(json.dumps([r.__dict__ for r in rows], indent=1))


if __name__ == "__main__":
    main()
