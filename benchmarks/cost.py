"""What ``calibrate`` costs, stage by stage, with its accuracy beside it.

One calibration (msac-opt, seeded, every core) per input, run one after another in
this process; the databases are built once and cached in ``--out``. Prints one row
per input: wall seconds of each stage (``CameraCalibration.stage_seconds``; only the
total where the installed version has no stages), the mean relative error of
(fx, fy, cx, cy), the agreeing triplets, and the largest |error| / std. Where the
input allows it, pycolmap's incremental mapping of the same database is timed in
the same run (``--mapping``), and the ratio is printed. The 300- and 1000-image
scenes run in a subprocess whose peak RSS is the memory figure.

Inputs (``--inputs``, comma-separated):

* ``demo``: the demo database (10 images, 5 % prior stored);
* ``fountain``, ``herz-jesus``: the shared Strecha scenes, SIFT at 1600 px, one
  PINHOLE camera, from COLMAP's default camera (``--no-prior``);
* ``fountain-default``, ``herz-jesus-default``: COLMAP's default database (one
  SIMPLE_RADIAL camera per image), from the stored camera;
* ``facade``: the synthetic facade at 1 % relief, ±5 % prior;
* ``drone``: 10 VGA frames of a drone's 65° camera over ground of 5 % relief through a
  k1 = −0.28 lens, COLMAP's default SIMPLE_RADIAL camera (a database, so ``--mapping``
  times pycolmap on it);
* ``straight``: a synthetic straight drive, ±5 % prior;
* ``telephoto``: a synthetic 10° ring from COLMAP's default camera;
* ``kitti``: the shared KITTI drive (51 frames), from COLMAP's default camera;
* ``rendered30``: the 30 photo-like 3072x2048 images of ``render_photos.py`` (Strecha
  camera), SIFT at 1600 px, from COLMAP's default camera: the 30-image scene that
  ``calibrate`` is compared with mapping on;
* ``synthetic300``, ``synthetic1000``: 300 and 1000 images (``scaling.py``'s knn graph).

    python benchmarks/cost.py [--inputs demo,fountain,...] [--seed 0] [--mapping]
        [--out benchmark_output/cost]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap

from colmap_trifocal import CalibrationOptions, calibrate_contents, calibrate_database
from colmap_trifocal.common.timing import STAGES
from colmap_trifocal.database.cameras import CameraInfo
from colmap_trifocal.database.features import build_database
from colmap_trifocal.datasets import read_scene
from colmap_trifocal.datasets.strecha import default_datasets_root, ground_truth_intrinsics
from colmap_trifocal.datasets.strecha import scene_images as strecha_images
from colmap_trifocal.synthetic.database import CAMERA_ID, scene_contents, write_database
from colmap_trifocal.synthetic.demo import make_demo_database
from colmap_trifocal.synthetic.facade import facade_scene
from colmap_trifocal.synthetic.lenses import drone_survey, narrow_lens, with_radial_distortion
from colmap_trifocal.synthetic.motions import forward_driving

BENCHMARKS = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCHMARKS))
from benchlib import quiet_stderr  # noqa: E402

DEFAULT_INPUTS = (
    "demo,fountain,herz-jesus,fountain-default,herz-jesus-default,facade,straight,"
    "telephoto,kitti,drone,rendered30,synthetic300,synthetic1000"
)
STRECHA = {"fountain": "fountain-P11", "herz-jesus": "Herz-Jesus-P8"}


def prior_5(truth: np.ndarray, seed: int) -> tuple[float, ...]:
    """Every parameter 5 % off, random signs."""
    signs = np.random.default_rng(seed + 99).choice([-1.0, 1.0], 4)
    return tuple(float(v) for v in truth * (1.0 + 0.05 * signs))


def strecha_database(out: Path, name: str, default: bool) -> tuple[Path, np.ndarray]:
    """A cached SIFT database of a shared Strecha scene and its true intrinsics."""
    folder = default_datasets_root(BENCHMARKS.parent) / "strecha" / STRECHA[name]
    path = out / f"{name}{'-default' if default else ''}.db"
    if not path.exists():
        with quiet_stderr():
            if default:
                build_database(
                    folder / "images",
                    path,
                    strecha_images(folder),
                    camera_model="SIMPLE_RADIAL",
                    single_camera=False,
                    camera_mode="auto",
                )
            else:
                build_database(folder / "images", path, strecha_images(folder))
    return path, ground_truth_intrinsics(folder)


def kitti_database(out: Path) -> tuple[Path, np.ndarray]:
    """A cached SIFT database of the shared KITTI drive (one PINHOLE camera)."""
    scene = read_scene("kitti", default_datasets_root(BENCHMARKS.parent) / "kitti/sequences/seq2")
    path = out / "kitti.db"
    if not path.exists():
        with quiet_stderr():
            build_database(scene.image_dir, path, [v.name for v in scene.views])
    return path, scene.mean_intrinsics()


def rendered_database(out: Path) -> tuple[Path, np.ndarray]:
    """A cached SIFT database of ``render_photos.py``'s 30 images and their true K."""
    folder = out / "rendered30"
    truth_file = folder / "ground_truth.json"
    if not truth_file.exists():
        subprocess.run(
            [sys.executable, str(BENCHMARKS / "render_photos.py"), str(folder), "--images", "30"],
            check=True,
            capture_output=True,
        )
    path = folder / "database.db"
    if not path.exists():
        with quiet_stderr():
            build_database(folder / "images", path)
    intrinsics = json.loads(truth_file.read_text())["intrinsics"]
    return path, np.array([intrinsics[name] for name in ("fx", "fy", "cx", "cy")])


def synthetic_database(out: Path, images: int) -> tuple[Path, np.ndarray]:
    """A cached ``scaling.py`` database (knn view graph, Strecha camera)."""
    from scaling import build_database as build_scaling

    path = out / f"synthetic{images}.db"
    if not path.exists():
        build_scaling(path, images, "knn", 0, 400, 2000, 0.5, 0.1, 20)
    info = json.loads(path.with_suffix(".json").read_text())
    return path, np.array(info["truth"])


def drone_database(out: Path, seed: int) -> tuple[Path, np.ndarray]:
    """A cached database of the drone survey (``lenses.py``'s ``drone-0.28``: a 65° VGA
    camera over ground of 5 % relief, k1 = −0.28) stored as COLMAP's default
    SIMPLE_RADIAL camera, and its true K."""
    scene = with_radial_distortion(drone_survey(seed=seed), -0.28)
    path = out / f"drone{seed}.db"
    if not path.exists():
        contents = scene_contents(scene)
        width, height = scene.width, scene.height
        default = [1.2 * max(width, height), width / 2, height / 2, 0.0]
        contents.cameras[CAMERA_ID] = CameraInfo(CAMERA_ID, "SIMPLE_RADIAL", width, height, default)
        write_database(contents, path)
    return path, scene.intrinsics


def mapping_seconds(database: Path, out: Path) -> float:
    """Wall seconds of ``pycolmap.incremental_mapping`` of a copy of the database."""
    work = out / "mapping"
    work.mkdir(parents=True, exist_ok=True)
    copy = work / "database.db"
    copy.write_bytes(database.read_bytes())
    clock = time.perf_counter()
    with quiet_stderr():
        pycolmap.incremental_mapping(str(copy), str(work), str(work))
    return time.perf_counter() - clock


def calibrate_case(name: str, out: Path, seed: int) -> tuple[object, np.ndarray, Path | None]:
    """(result, truth, database or None) of one input."""
    options = CalibrationOptions(seed=seed)
    if name == "demo":
        path = out / "demo.db"
        if not path.exists():
            make_demo_database(path, seed=0)
        truth = np.array([1400.0, 1420.0, 790.0, 612.0])
        return calibrate_database(path, options)[0], truth, path
    if name in STRECHA or name.removesuffix("-default") in STRECHA:
        default = name.endswith("-default")
        path, truth = strecha_database(out, name.removesuffix("-default"), default)
        options = replace(options, no_prior=not default)
        return calibrate_database(path, options)[0], truth, path
    if name == "kitti":
        path, truth = kitti_database(out)
        options = replace(options, no_prior=True)
        return calibrate_database(path, options)[0], truth, path
    if name == "rendered30":
        path, truth = rendered_database(out)
        options = replace(options, no_prior=True)
        return calibrate_database(path, options)[0], truth, path
    if name == "drone":
        path, truth = drone_database(out, seed)
        options = replace(options, no_prior=True)
        return calibrate_database(path, options)[0], truth, path
    if name.startswith("synthetic"):
        path, truth = synthetic_database(out, int(name.removeprefix("synthetic")))
        return calibrate_database(path, options)[0], truth, path
    scenes = {
        "facade": lambda: facade_scene(relief=0.01, seed=seed, noise_px=1.0, num_points=1000),
        "straight": lambda: forward_driving(seed=seed, yaw_deg=0.0),
        "telephoto": lambda: narrow_lens(seed=seed),
    }
    scene = scenes[name]()
    if name == "telephoto":
        options = replace(options, no_prior=True)
    else:
        options = replace(options, prior=prior_5(scene.intrinsics, seed))
    return calibrate_contents(scene_contents(scene), options)[0], scene.intrinsics, None


def row(name: str, out: Path, seed: int, mapping: bool) -> dict:
    """One input's figures."""
    clock = time.perf_counter()
    result, truth, database = calibrate_case(name, out, seed)
    wall = time.perf_counter() - clock
    estimate = np.array([result.fx, result.fy, result.cx, result.cy])
    std = np.array([np.nan if result.std[n] is None else result.std[n] for n in result.std])
    stages = getattr(result, "stage_seconds", None) or {}
    figures = {
        "input": name,
        "images": len({i for t in result.triplets for i in t.image_ids}),
        "stages": {s: stages.get(s) for s in STAGES},
        "calibrate": float(stages.get("total", result.seconds)),
        "wall": wall,
        "error": float(np.mean(np.abs(estimate / truth - 1.0)) * 100.0),
        "agree": f"{result.num_inlier_triplets}/{result.num_triplets}",
        "max_z": float(np.nanmax(np.abs(estimate - truth) / std)) if np.any(std > 0) else None,
    }
    if mapping and database is not None:
        figures["mapping"] = mapping_seconds(database, out)
    return figures


def child(name: str, out: Path, seed: int) -> None:
    """Run one input and print its figures with the peak RSS as JSON (subprocess mode)."""
    figures = row(name, out, seed, mapping=False)
    figures["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(json.dumps(figures))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--inputs", default=DEFAULT_INPUTS)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mapping", action="store_true", help="time pycolmap mapping too")
    parser.add_argument("--out", type=Path, default=Path("benchmark_output/cost"))
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.child:
        child(args.child, args.out, args.seed)
        return
    header = ["input", *STAGES, "calibrate", "error %", "agree", "max |z|", "mapping", "ratio"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for name in args.inputs.split(","):
        if name.startswith("synthetic"):
            if not (args.out / f"{name}.db").exists():
                synthetic_database(args.out, int(name.removeprefix("synthetic")))
            done = subprocess.run(
                [
                    sys.executable,
                    __file__,
                    "--child",
                    name,
                    "--out",
                    str(args.out),
                    "--seed",
                    str(args.seed),
                ],
                capture_output=True,
                text=True,
                check=True,
            )
            figures = json.loads(done.stdout.strip().splitlines()[-1])
            name = f"{name} ({figures['peak_mb']:.0f} MB)"
        else:
            figures = row(name, args.out, args.seed, args.mapping)
        stages = [
            "" if figures["stages"][s] is None else f"{figures['stages'][s]:.2f}" for s in STAGES
        ]
        mapping = figures.get("mapping")
        cells = [
            name,
            *stages,
            f"{figures['calibrate']:.2f}",
            f"{figures['error']:.3f}",
            figures["agree"],
            "" if figures["max_z"] is None else f"{figures['max_z']:.1f}",
            "" if mapping is None else f"{mapping:.1f}",
            "" if mapping is None else f"{mapping / figures['calibrate']:.0f}x",
        ]
        print("| " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
