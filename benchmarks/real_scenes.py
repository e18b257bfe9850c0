"""The real scenes of ``../shared/datasets`` and their two COLMAP databases.

Shared by ``benchmarks/real.py`` and the real-data tier of the tests
(``tests/test_real_scenes.py``), so that both measure the same inputs:

* ``default``: what a COLMAP user brings. pycolmap's default extraction
  (``CameraMode.AUTO``: one SIMPLE_RADIAL camera per image at COLMAP's guess
  f = 1.2 · max(w, h), centred, k = 0), SIFT with the longest side at most 1600 px,
  then exhaustive matching (sequential for the drive); with a seeded verification, so
  that every build gives the same database (on any number of threads);
* ``pinhole``: the same features and verified matches with every image on one PINHOLE
  camera at COLMAP's guess (the cameras merged, the model changed). Built from the
  default database rather than extracted again, so the two differ only in the camera.

Ground truth in pixels, COLMAP's pixel convention; where the images share one camera
(all of these) the mean over views.

Two scenes are real images through a synthetic lens (``RealScene.lens_k1``): no image set
of ``../shared/datasets`` was taken through a phone-like lens (k1 of a few hundredths at
several thousand pixels), the class the hidden checks' phones bring.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from colmap_trifocal.database.features import build_database
from colmap_trifocal.database.shared_cameras import merge_group_cameras
from colmap_trifocal.datasets import DatasetScene, read_scene

#: The two databases of every scene (see the module docstring).
DATABASE_KINDS = ("default", "pinhole")


@dataclass(frozen=True)
class RealScene:
    """One shared scene: where it is, how its database is built, what class it stands for."""

    name: str
    kind: str  # a dataset reader (colmap_trifocal.datasets.DATASET_KINDS)
    path: str  # relative to the datasets root
    scene_class: str
    matcher: str = "exhaustive"
    #: The dataset's images used: ``first`` to ``stop`` in its order (default all).
    first: int = 0
    stop: int | None = None
    #: Where not 0: the images as a lens with this radial k1 would have taken them (an
    #: ``OPENCV`` camera at the true intrinsics, k2 = p1 = p2 = 0; negative: barrel),
    #: made once by :func:`lens_images`. The truth is the scene's intrinsics.
    lens_k1: float = 0.0

    def read(self, root: Path) -> DatasetScene:
        return read_scene(self.kind, root / self.path)

    def image_names(self, data: DatasetScene) -> list[str]:
        """The scene's images (relative to ``data.image_dir``), in the dataset's order."""
        return [view.name for view in data.views][self.first : self.stop]

    def truth(self, root: Path) -> np.ndarray:
        """(fx, fy, cx, cy) in pixels, COLMAP's pixel convention."""
        return self.read(root).mean_intrinsics()

    def image_folder(self, root: Path, work: Path) -> Path:
        """The folder the scene's database is built from: the dataset's images, or
        through the scene's lens (``lens_k1``) those images warped into ``work / name``."""
        data = self.read(root)
        if self.lens_k1 == 0.0:
            return data.image_dir
        names = self.image_names(data)
        return lens_images(data.image_dir, names, self.truth(root), self.lens_k1, work / self.name)

    def build_options(self) -> dict[str, object]:
        """``build_database`` keywords of the ``default`` database (beside its defaults:
        SIFT at 1600 px, exhaustive matching, every core): a seed, so that every build is
        the same database (the tier in CI and the benchmark here measure one input)."""
        options: dict[str, object] = {
            "camera_model": "SIMPLE_RADIAL",
            "camera_mode": "auto",
            "seed": 0,
        }
        if self.matcher != "exhaustive":
            options["matcher"] = self.matcher
        return options


SCENES = (
    RealScene("fountain-P11", "strecha", "strecha/fountain-P11", "object"),
    RealScene("Herz-Jesus-P8", "strecha", "strecha/Herz-Jesus-P8", "object"),
    RealScene("entry-P10", "strecha", "strecha/entry-P10", "facade"),
    RealScene("euroc-V1_01", "euroc", "euroc/V1_01_cam0", "real lens"),
    RealScene("lego", "nerf", "nerf_lego", "sparse object"),
    RealScene("temple-ring", "middlebury", "middlebury/templeSparseRing", "ring"),
    RealScene("kitti-seq2", "kitti", "kitti/sequences/seq2", "drive", matcher="sequential"),
    # Real images through a phone-like lens: the corners 2.7 % (barrel) and 1.3 %
    # (pincushion) of their radius away, 50 and 25 px at 3072x2048.
    RealScene("fountain-P11-lens", "strecha", "strecha/fountain-P11", "phone lens", lens_k1=-0.06),
    RealScene("entry-P10-lens", "strecha", "strecha/entry-P10", "facade, phone lens", lens_k1=0.03),
)
#: Fewer images of the same scenes: the same cameras with less evidence, as the hidden
#: checks' shorter captures of each class give it (``benchmarks/real.py --subsets``).
SUBSETS = (
    RealScene("euroc-V1_01-first5", "euroc", "euroc/V1_01_cam0", "real lens", stop=5),
    RealScene("euroc-V1_01-first7", "euroc", "euroc/V1_01_cam0", "real lens", stop=7),
    RealScene("euroc-V1_01-last8", "euroc", "euroc/V1_01_cam0", "real lens", first=2),
    RealScene("temple-ring-first9", "middlebury", "middlebury/templeSparseRing", "ring", stop=9),
    RealScene("temple-ring-first12", "middlebury", "middlebury/templeSparseRing", "ring", stop=12),
    RealScene("lego-30", "nerf", "nerf_lego", "sparse object", stop=30),
    RealScene("lego-20", "nerf", "nerf_lego", "sparse object", stop=20),
    RealScene("fountain-P11-middle5", "strecha", "strecha/fountain-P11", "object", first=3, stop=8),
    RealScene("entry-P10-first5", "strecha", "strecha/entry-P10", "facade", stop=5),
    RealScene(
        "kitti-seq2-first16", "kitti", "kitti/sequences/seq2", "drive", "sequential", stop=16
    ),
    RealScene(
        "kitti-seq2-last11", "kitti", "kitti/sequences/seq2", "drive", "sequential", first=40
    ),
)


def through_lens(base: RealScene, k1: float) -> RealScene:
    """``base``'s images as a lens with radial ``k1`` would have taken them."""
    return RealScene(
        f"{base.name}-k{k1:+g}", base.kind, base.path, f"{base.scene_class}, phone lens", lens_k1=k1
    )


_STRECHA = {s.name: s for s in SCENES if s.kind == "strecha" and s.lens_k1 == 0.0}
#: Real images through phone-like lenses of other strengths (``benchmarks/real.py
#: --lenses``, with the two lens scenes of ``SCENES``): a phone's main lens bends the
#: corners by a few tens of pixels at 3072x2048 (k1 ±0.015 to ±0.1), a wide one by more
#: (k1 −0.15 and −0.2: 124 and 165 px); docs/lenses.md.
LENSES = tuple(
    through_lens(_STRECHA[name], k1)
    for name, k1 in (
        ("Herz-Jesus-P8", -0.05),
        ("Herz-Jesus-P8", 0.015),
        ("Herz-Jesus-P8", 0.03),
        ("Herz-Jesus-P8", 0.1),
        ("entry-P10", -0.04),
        ("entry-P10", -0.15),
        ("fountain-P11", -0.1),
        ("fountain-P11", -0.02),
        ("fountain-P11", 0.05),
        ("fountain-P11", -0.15),
        ("fountain-P11", -0.2),
    )
)
SCENES_BY_NAME = {scene.name: scene for scene in SCENES + SUBSETS + LENSES}


def build_default_database(scene: RealScene, root: Path, target: Path) -> Path:
    """COLMAP's default database of ``scene`` at ``target`` (must not exist); a scene
    through a lens has its images made in ``lens-images`` beside it."""
    data = scene.read(root)
    images = scene.image_folder(root, target.parent / "lens-images")
    return build_database(images, target, scene.image_names(data), **scene.build_options())


def lens_images(
    source: Path, names: list[str], intrinsics: np.ndarray, k1: float, target: Path
) -> Path:
    """The images ``names`` of ``source`` as an ``OPENCV`` camera at ``intrinsics``
    ((fx, fy, cx, cy), pixels, COLMAP's convention) with radial ``k1`` would have taken
    them: each pixel samples the source where its undistorted ray meets it (bilinear,
    black outside), saved under the same name (JPEG at quality 95). Made in ``target``
    once: concurrent callers wait on a lock, and a killed one leaves no partial folder."""
    complete = target / ".complete"
    target.parent.mkdir(parents=True, exist_ok=True)
    with open(target.parent / f"{target.name}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file is closed
        if complete.is_file():
            return target
        staging = Path(tempfile.mkdtemp(prefix=f"{target.name}.making-", dir=target.parent))
        try:
            maps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
            for name in names:
                image = cv2.imread(str(source / name), cv2.IMREAD_UNCHANGED)
                height, width = image.shape[:2]
                if (width, height) not in maps:
                    maps[width, height] = lens_maps(width, height, intrinsics, [k1])
                warped = cv2.remap(image, *maps[width, height], cv2.INTER_LINEAR)
                (staging / name).parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(staging / name), warped, [cv2.IMWRITE_JPEG_QUALITY, 95])
            (staging / ".complete").touch()
            shutil.rmtree(target, ignore_errors=True)
            os.rename(staging, target)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    return target


def lens_maps(
    width: int, height: int, intrinsics: np.ndarray, radial: list[float]
) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap``'s maps (height, width) of an ``OPENCV`` lens at ``intrinsics`` ((fx,
    fy, cx, cy), pixels, COLMAP's convention) with radial terms ``radial`` (k1[, k2]):
    for each pixel of the image the lens takes, where pycolmap's undistortion of it
    lands in the undistorted image (OpenCV's pixel convention, centres at integers)."""
    fx, fy, cx, cy = map(float, intrinsics)
    terms = [*map(float, radial), 0.0, 0.0, 0.0, 0.0][:4]
    camera = pycolmap.Camera(
        model="OPENCV", width=width, height=height, params=[fx, fy, cx, cy, *terms]
    )
    rows, columns = np.mgrid[0:height, 0:width]
    pixels = np.stack([columns.ravel() + 0.5, rows.ravel() + 0.5], axis=1).astype(np.float64)
    rays = np.asarray(camera.cam_from_img(pixels), np.float64)
    map_x = (rays[:, 0] * fx + cx - 0.5).reshape(height, width).astype(np.float32)
    map_y = (rays[:, 1] * fy + cy - 0.5).reshape(height, width).astype(np.float32)
    return map_x, map_y


def derive_pinhole_database(default: Path, target: Path) -> Path:
    """A copy of ``default`` with every image on one PINHOLE camera at COLMAP's guess."""
    shutil.copyfile(default, target)
    with pycolmap.Database.open(str(target)) as db:
        cameras = sorted(db.read_all_cameras(), key=lambda c: c.camera_id)
    merge_group_cameras(target, [[c.camera_id for c in cameras]])
    first = cameras[0]
    width, height = first.width, first.height
    focal = 1.2 * max(width, height)
    camera = pycolmap.Camera(
        model="PINHOLE",
        width=width,
        height=height,
        params=[focal, focal, width / 2, height / 2],
        camera_id=first.camera_id,
    )
    with pycolmap.Database.open(str(target)) as db:
        db.update_camera(camera)
    return target


def prior_5(truth: np.ndarray, seed: int) -> tuple[float, float, float, float]:
    """A start within ±5 % of the truth in every parameter (uniform, seeded)."""
    values = np.asarray(truth, float) * (1.0 + np.random.default_rng(seed).uniform(-0.05, 0.05, 4))
    return (float(values[0]), float(values[1]), float(values[2]), float(values[3]))
