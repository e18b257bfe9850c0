"""``colmap-trifocal demo``: the whole pipeline on a synthetic scene with a known camera.

No download: pycolmap synthesises a scene (random points, a ring of cameras),
writes its keypoints and matches to a database, adds Gaussian keypoint noise
and a share of wrong matches, and stores a deliberately wrong camera. The demo
then runs ``colmap-trifocal run`` on that database (TrifocalCalib, incremental
mapping, bundle adjustment) and prints estimated against true intrinsics.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..common.files import missing_folders, remove_database_files, remove_if_empty
from ..common.pycolmap_child import call_in_child
from ..intrinsics.options import Method
from ..intrinsics.results import PARAMETER_NAMES
from ..reconstruction.report import RunReport
from ..reconstruction.workflow import RunOptions, run_pipeline
from .database import corrupt_verified_matches

#: The demo camera (PINHOLE, 1600x1200): fx, fy, cx, cy in pixels.
DEMO_INTRINSICS = (1400.0, 1420.0, 790.0, 612.0)
DEMO_SIZE = (1600, 1200)


@dataclass
class DemoResult:
    """The demo's camera (pixels) and what the run made of it."""

    truth: np.ndarray  # (4,) fx, fy, cx, cy
    prior: np.ndarray  # (4,) stored wrong camera
    report: RunReport

    def estimate(self, stage: str) -> np.ndarray:
        """(fx, fy, cx, cy) after ``trifocal`` or ``refined`` (bundle adjustment)."""
        values = self.report.cameras[0][stage]
        return np.array([values[name] for name in PARAMETER_NAMES])

    def error(self, stage: str) -> float:
        """Mean relative error of (fx, fy, cx, cy) of a stage (fraction)."""
        return float(np.mean(np.abs(self.estimate(stage) / self.truth - 1.0)))


def demo_dataset_options(num_images: int, num_points: int) -> pycolmap.SyntheticDatasetOptions:
    """pycolmap's synthetic scene with the demo camera: one PINHOLE camera, one rig."""
    return pycolmap.SyntheticDatasetOptions(
        num_rigs=1,
        num_cameras_per_rig=1,
        num_frames_per_rig=num_images,
        num_points3D=num_points,
        camera_model_id=pycolmap.CameraModelId.PINHOLE,
        camera_params=list(DEMO_INTRINSICS),
        camera_width=DEMO_SIZE[0],
        camera_height=DEMO_SIZE[1],
    )


def make_demo_database(
    path: Path,
    seed: int = 0,
    num_images: int = 10,
    num_points: int = 1500,
    noise_px: float = 0.5,
    inlier_ratio: float = 0.8,
    prior_error: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Write the demo database; returns (true intrinsics, stored wrong intrinsics).

    The stored camera has every parameter off by ``±prior_error`` (random sign);
    a share ``1 − inlier_ratio`` of every pair's verified matches is wrong.
    """
    pycolmap.set_random_seed(seed)
    options = demo_dataset_options(num_images, num_points)
    truth = np.array(DEMO_INTRINSICS)
    rng = np.random.default_rng(seed)
    prior = truth * (1.0 + prior_error * rng.choice([-1.0, 1.0], size=4))
    with pycolmap.Database.open(str(path)) as db:
        reconstruction = pycolmap.synthesize_dataset(options, db)
        noise = pycolmap.SyntheticNoiseOptions(point2D_stddev=noise_px)
        pycolmap.synthesize_noise(noise, reconstruction, db)
        corrupt_verified_matches(db, 1.0 - inlier_ratio, rng)
        camera = db.read_all_cameras()[0]
        camera.params = prior.tolist()
        db.update_camera(camera)
    return truth, prior


def demo_database_values(path: str, seed: int) -> tuple[list[float], list[float]]:
    """:func:`make_demo_database` at ``path`` with ``seed``; (truth, prior) as lists (the
    child process of :func:`_made_or_removed` returns them through JSON)."""
    truth, prior = make_demo_database(Path(path), seed=seed)
    return truth.tolist(), prior.tolist()


def _made_or_removed(
    database: Path, seed: int, created: list[Path]
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`make_demo_database` in a child process (:mod:`..common.pycolmap_child`: on a
    full disk pycolmap raises, then aborts the process when the database closes); where
    it fails one CalibrationError, with the partial database and the folders this run
    made (``created``, deepest first) removed."""
    try:
        truth, prior = call_in_child(
            "colmap_trifocal.synthetic.demo.demo_database_values",
            {"path": str(database), "seed": seed},
            output=database,
            failure=f"cannot write the demo database {database}",
            progress=False,
        )
    except BaseException:
        remove_database_files(database)
        remove_if_empty(created)
        raise
    return np.array(truth), np.array(prior)


def run_demo(seed: int = 0, workdir: Path | None = None, method: Method = "msac-opt") -> DemoResult:
    """Build the demo database and run the whole pipeline on it.

    Outputs go to ``workdir`` (``demo.db`` and the workspace ``demo/``), or to a
    temporary folder that is removed afterwards.
    """
    if workdir is not None:
        refuse_existing_demo(Path(workdir))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(workdir) if workdir is not None else Path(tmp)
        created = missing_folders(folder)
        folder.mkdir(parents=True, exist_ok=True)
        database = folder / "demo.db"
        truth, prior = _made_or_removed(database, seed, created)
        options = RunOptions(method=method, seed=seed, database=database, overwrite=True)
        report = run_pipeline(None, folder / "demo", options)
        return DemoResult(truth=truth, prior=prior, report=report)


#: What the demo writes into a ``workdir``.
DEMO_OUTPUTS = ("demo.db", "demo")


def refuse_existing_demo(workdir: Path) -> None:
    """CalibrationError where ``workdir`` already holds a demo's outputs (``demo.db``, the
    workspace ``demo/``): the demo never replaces files it did not make in this run."""
    for name in DEMO_OUTPUTS:
        path = workdir / name
        if path.exists() or path.is_symlink():
            raise CalibrationError(
                f"{path} already exists: refusing to replace it (remove it or keep the demo "
                "in another folder)"
            )


def format_demo(result: DemoResult) -> str:
    """A small table: true, prior, TrifocalCalib estimate (± std), BA-refined, and errors."""
    camera = result.report.cameras[0]
    trifocal, refined = result.estimate("trifocal"), result.estimate("refined")
    seconds = result.report.seconds
    lines = [
        f"synthetic PINHOLE camera {DEMO_SIZE[0]}x{DEMO_SIZE[1]}, "
        f"{result.report.num_images} images, 0.5 px keypoint noise, 20 % wrong matches",
        f"registered {result.report.num_registered_images} images; seconds: "
        + ", ".join(f"{stage} {t:.1f}" for stage, t in seconds.items()),
        f"{'':>4} {'true':>9} {'prior':>9} {'trifocal':>9} {'± std':>7} {'BA':>9}",
    ]
    for i, name in enumerate(PARAMETER_NAMES):
        std = camera["trifocal_std"][name]
        lines.append(
            f"{name:>4} {result.truth[i]:>9.2f} {result.prior[i]:>9.2f} {trifocal[i]:>9.2f} "
            f"{std if std is not None else float('nan'):>7.2f} {refined[i]:>9.2f}"
        )
    prior_error = np.mean(np.abs(result.prior / result.truth - 1)) * 100
    lines.append(
        f"mean relative error: prior {prior_error:.2f} %, "
        f"BA-refined {100 * result.error('refined'):.3f} %"
    )
    lines.append(f"mean relative error: {100 * result.error('trifocal'):.3f} % (TrifocalCalib)")
    return "\n".join(lines)
