"""Lenses whose distortion the stored camera does not hold: accuracy, k and std coverage.

Issue 26's synthetic lens class, each calibrated from COLMAP's default camera (f = 1.2 ·
max(w, h), centred, distortion 0) of the model named, msac-opt, one seed per run:

* ``handheld-<k1>``: the 17-frame 63° handheld set (``handheld_indoor``), SIMPLE_RADIAL,
  k1 in {0, −0.01, −0.05, −0.1} and the pincushion +0.05;
* ``handheld-0.3``: the handheld set through a strong barrel lens, k1 = −0.3;
* ``wide-100``: an 8-view 100° ring (``wide_lens``), RADIAL, k1 = −0.25, k2 = +0.05;
* ``division-80``: an 8-view 80° ring through a lens that follows the division model
  (λ = −0.25 at the image corner, ``with_division_distortion``), which no COLMAP
  model holds exactly, as a RADIAL camera;
* ``drone-0.28``: a drone's 65° VGA camera over ground of 5 % relief (``drone_survey``),
  SIMPLE_RADIAL, k1 = −0.28: strong polynomial distortion where nearly every view pair
  is a homography;
* ``pinhole-0.05``: the handheld set at k1 = −0.05 through a PINHOLE camera (which
  stays pinhole: the std must cover the bias).

Per class: mean and worst |error| of f and of the principal point (% of f), k against
the truth, the share of |error| / std ≤ 2 over every reported std (coverage), how
often the distortion counted as present, and runs where a parameter reported
determined ended further from the truth than the start (must be 0).

With ``--floor``, each polynomial lens class's maximum-likelihood floor instead: pycolmap
bundle adjustment of every image and track, started at the ground truth (poses, points,
K and k), with the stored model's focal length, principal point and distortion free. Its
errors are what the images themselves determine; no estimator from the tracks alone is
expected below them.

    python benchmarks/lenses.py [--classes handheld-0,...] [--seeds 5] [--floor]
"""

from __future__ import annotations

import argparse

import numpy as np
import pycolmap
from tqdm import tqdm

from colmap_trifocal import CalibrationOptions, calibrate_contents
from colmap_trifocal.common.bundle_adjustment import bundle_adjustment_options
from colmap_trifocal.common.log import keep_colmap_quiet
from colmap_trifocal.database.cameras import CameraInfo
from colmap_trifocal.synthetic.database import CAMERA_ID, scene_contents
from colmap_trifocal.synthetic.lenses import (
    drone_survey,
    lens_scene,
    wide_lens,
    with_division_distortion,
    with_radial_distortion,
)
from colmap_trifocal.synthetic.motions import handheld_indoor

NAMES = ("fx", "fy", "cx", "cy")
CLASSES = {
    "handheld-0": (handheld_indoor, "SIMPLE_RADIAL", (0.0, 0.0)),
    "handheld-0.01": (handheld_indoor, "SIMPLE_RADIAL", (-0.01, 0.0)),
    "handheld-0.05": (handheld_indoor, "SIMPLE_RADIAL", (-0.05, 0.0)),
    "handheld-0.1": (handheld_indoor, "SIMPLE_RADIAL", (-0.1, 0.0)),
    "pincushion+0.05": (handheld_indoor, "SIMPLE_RADIAL", (0.05, 0.0)),
    "handheld-0.3": (handheld_indoor, "SIMPLE_RADIAL", (-0.3, 0.0)),
    "wide-100": (wide_lens, "RADIAL", (-0.25, 0.05)),
    "division-80": (lambda seed: lens_scene(80.0, seed=seed), "RADIAL", ("division", -0.25)),
    "drone-0.28": (drone_survey, "SIMPLE_RADIAL", (-0.28, 0.0)),
    "pinhole-0.05": (handheld_indoor, "PINHOLE", (-0.05, 0.0)),
}


def default_camera_contents(make, model: str, k: tuple, seed: int):
    """The scene through the lens, stored as COLMAP's default camera of ``model``."""
    if k[0] == "division":
        scene = with_division_distortion(make(seed=seed), k[1])
    else:
        scene = with_radial_distortion(make(seed=seed), *k)
    contents = scene_contents(scene)
    width, height = scene.width, scene.height
    f, cx, cy = 1.2 * max(width, height), width / 2, height / 2
    params = {
        "SIMPLE_RADIAL": [f, cx, cy, 0.0],
        "RADIAL": [f, cx, cy, 0.0, 0.0],
        "PINHOLE": [f, f, cx, cy],
    }[model]
    contents.cameras[CAMERA_ID] = CameraInfo(CAMERA_ID, model, width, height, params)
    return contents, scene.intrinsics, np.array([f, f, cx, cy])


def run_class(name: str, seeds: int) -> dict:
    make, model, k = CLASSES[name]
    rows = []
    for seed in tqdm(range(seeds), desc=name, leave=False):
        contents, truth, start = default_camera_contents(make, model, k, seed)
        (result,) = calibrate_contents(contents, CalibrationOptions(no_prior=True, seed=seed))
        error = result.intrinsics - truth
        z = [
            abs(error[i]) / result.std[n]
            for i, n in enumerate(NAMES)
            if result.std[n] is not None and result.std[n] > 0
        ]
        worse = [
            n
            for i, n in enumerate(NAMES)
            if result.observable[n] and abs(error[i]) > abs(start[i] - truth[i])
        ]
        lens = result.lens_distortion or {}
        rows.append(
            {
                "f": 100 * abs(error[0]) / truth[0],
                "c": 100 * np.max(np.abs(error[2:])) / truth[0],
                "k1": (lens.get("params") or [np.nan])[0] if lens.get("present") else 0.0,
                "z": z,
                "present": bool(lens.get("present")),
                "worse": worse,
                "determined": sum(result.observable.values()),
            }
        )
    z = np.concatenate([r["z"] for r in rows]) if rows else np.zeros(0)
    k1 = np.array([r["k1"] for r in rows])
    f = np.array([r["f"] for r in rows])
    return {
        "class": name,
        "f mean/worst %": f"{f.mean():.2f} / {f.max():.2f}",
        "c worst %": f"{max(r['c'] for r in rows):.2f}",
        "k1 (truth)": f"{np.mean(k1):+.4f} ± {np.std(k1):.4f} ({_truth(k)})",
        "coverage ±2σ": f"{100 * np.mean(z <= 2):.0f} % of {len(z)}",
        "present": f"{sum(r['present'] for r in rows)}/{len(rows)}",
        "determined": f"{np.mean([r['determined'] for r in rows]):.1f}/4",
        "worse than start": sum(bool(r["worse"]) for r in rows),
    }


def floor_class(name: str, seeds: int) -> dict | None:
    """The class's maximum-likelihood floor (the module's ``--floor``); None for the
    lenses no COLMAP model holds (division) and for the pinhole camera."""
    make, model, k = CLASSES[name]
    if k[0] == "division" or model == "PINHOLE":
        return None
    f_errors, c_errors, k1 = [], [], []
    for seed in range(seeds):
        scene = with_radial_distortion(make(seed=seed), *k)
        f, cx, cy = scene.intrinsics[0], scene.intrinsics[2], scene.intrinsics[3]
        params = [f, cx, cy, *k[: 1 if model == "SIMPLE_RADIAL" else 2]]
        reconstruction = truth_reconstruction(scene, model, params)
        options = bundle_adjustment_options(
            refine_extra_params=True, function_tolerance=1e-12, gradient_tolerance=1e-12
        )
        with keep_colmap_quiet():
            pycolmap.bundle_adjustment(reconstruction, options)
        adjusted = np.asarray(reconstruction.cameras[CAMERA_ID].params, dtype=float)
        f_errors.append(100 * abs(adjusted[0] / f - 1))
        c_errors.append(100 * max(abs(adjusted[1] - cx), abs(adjusted[2] - cy)) / f)
        k1.append(adjusted[3])
    return {
        "class": name,
        "floor: f mean/worst %": f"{np.mean(f_errors):.2f} / {np.max(f_errors):.2f}",
        "c worst %": f"{np.max(c_errors):.2f}",
        "k1 (truth)": f"{np.mean(k1):+.4f} ± {np.std(k1):.4f} ({_truth(k)})",
    }


def truth_reconstruction(scene, model: str, params: list[float]) -> pycolmap.Reconstruction:
    """Every image at its true pose and every track at its true point (two views or
    more), on the scene's noisy observations, one camera of ``model`` at ``params``."""
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(
        pycolmap.Camera(
            camera_id=CAMERA_ID, model=model, width=scene.width, height=scene.height, params=params
        )
    )
    for view in range(scene.num_cameras):
        image = pycolmap.Image(
            name=f"{view}.png",
            keypoints=np.ascontiguousarray(scene.observations[view], dtype=np.float64),
            camera_id=CAMERA_ID,
            image_id=view + 1,
        )
        pose = pycolmap.Rigid3d(
            pycolmap.Rotation3d(scene.rotations[view]), scene.translations[view].astype(float)
        )
        reconstruction.add_image_with_trivial_frame(image, pose)
    visible = (
        np.ones(scene.observations.shape[:2], bool) if scene.visible is None else scene.visible
    )
    for point, (X, seen) in enumerate(zip(scene.points, visible.T, strict=True)):
        views = np.flatnonzero(seen)
        if len(views) >= 2 and not scene.outliers[point]:
            track = pycolmap.Track([pycolmap.TrackElement(int(v) + 1, point) for v in views])
            reconstruction.add_point3D(X, track)
    return reconstruction


def _truth(k: tuple) -> str:
    """The lens's distortion as the table shows it."""
    if k[0] == "division":
        return f"division λ = {k[1]:+.2f}"
    return f"{k[0]:+.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--classes", default=",".join(CLASSES))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--floor", action="store_true", help="the BA-from-truth floor instead")
    args = parser.parse_args()
    names = args.classes.split(",")
    if args.floor:
        pycolmap.logging.minloglevel = 2  # keep_colmap_quiet keeps this level
        table = [row for n in names if (row := floor_class(n, args.seeds)) is not None]
    else:
        table = [run_class(name, args.seeds) for name in names]
    header = list(table[0])
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in table:
        print("| " + " | ".join(str(row[h]) for h in header) + " |")


if __name__ == "__main__":
    main()
