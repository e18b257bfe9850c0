"""The paper's Table I protocol on a dataset with ground truth.

For each scene: one COLMAP database of all its images (SIFT at
``max_image_size``, exhaustive matching, one PINHOLE camera), built once and
cached. For each image count N: a sequence of N images chosen by overlap,
greedily: it starts at the scene's first image and repeatedly adds the unused
image with the largest summed overlap with the images already chosen (overlap:
the dataset's own scores where it has them, e.g. BlendedMVS ``pair.txt``;
otherwise the number of verified matches). For each perturbation range
``[lo, hi]`` % and run r: a prior whose every parameter is the ground truth
times ``1 ± U(lo, hi) %`` with a random sign, and a seed; every method then
calibrates the sequence from that prior.

The ground truth of a sequence is the mean of its images' intrinsics (pixels,
COLMAP convention). Errors are the mean relative error of (fx, fy, cx, cy), in
percent. The trifocal variants of one run share their tensors (as the methods
would if run one after another with the same seed).
"""

from __future__ import annotations

import hashlib
import shutil
import sqlite3
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..common.log import keep_colmap_quiet, logger
from ..database.features import build_database
from ..database.snapshot import DatabaseContents, read_database
from ..datasets import read_scene
from ..datasets.base import DatasetScene
from ..intrinsics.api import CalibrationOptions, calibrate_contents_methods
from ..reconstruction.mapping import (
    Refinement,
    camera_intrinsics,
    incremental_mapping,
    refine_intrinsics,
)
from .records import RunRecord
from .runner import run_tasks

TRIFOCAL_METHODS = ("msac-opt", "msac", "direct")
EVALUATION_METHODS = (*TRIFOCAL_METHODS, "fundamental", "calibrate_view_graph", "mapping")
#: Methods run by default (the mapping baseline is slow: ask for it with --methods).
DEFAULT_METHODS = EVALUATION_METHODS[:-1]


@dataclass
class EvaluationOptions:
    """Settings of :func:`evaluate_scene` (the flags of ``colmap-trifocal evaluate``)."""

    image_counts: tuple[int, ...] = (8, 16, 32)
    #: Prior perturbation ranges, percent: each parameter is off by U(lo, hi) %, random sign.
    perturbations: tuple[tuple[float, float], ...] = ((0.0, 5.0), (5.0, 10.0))
    runs: int = 100
    #: Runs of the (slow) mapping baseline, the first ones of each configuration.
    mapping_runs: int = 3
    methods: tuple[str, ...] = DEFAULT_METHODS
    seed: int = 0
    max_image_size: int = 1600
    #: Folder of the per-scene databases (built once); None: a temporary folder.
    cache: Path | None = None
    workers: int | None = None
    dask_address: str | None = None
    progress: bool = False


@dataclass
class RunTask:
    """Everything one run needs (picklable, sent to a worker process or Dask)."""

    kind: str
    scene: str
    run: int
    seed: int
    perturbation: tuple[float, float]
    truth: np.ndarray
    prior: np.ndarray
    contents: DatabaseContents = field(repr=False)
    methods: tuple[str, ...]
    #: Database of the sequence (for the pycolmap baselines; copied, never changed).
    sequence_database: Path | None = None


def perturbation_label(perturbation: tuple[float, float]) -> str:
    low, high = perturbation
    return f"{low:g}-{high:g}"


def perturbed_prior(
    truth: np.ndarray, perturbation: tuple[float, float], rng: np.random.Generator
) -> np.ndarray:
    """Each parameter times ``1 ± U(lo, hi) / 100`` with an independent random sign."""
    low, high = perturbation
    signs = rng.choice([-1.0, 1.0], size=4)
    return np.asarray(truth, float) * (1.0 + signs * rng.uniform(low, high, size=4) / 100.0)


def select_sequence(
    names: list[str], overlap: dict[tuple[str, str], float], count: int
) -> list[str]:
    """Greedy sequence of ``count`` names (capped at len(names)) starting at names[0].

    ``overlap[(a, b)]`` (either order) scores how much two images overlap.
    """
    chosen = [names[0]]
    remaining = list(names[1:])
    while remaining and len(chosen) < count:
        totals = [
            sum(overlap.get((c, r), overlap.get((r, c), 0.0)) for c in chosen) for r in remaining
        ]
        chosen.append(remaining.pop(int(np.argmax(totals))))
    return chosen


def match_overlap(contents: DatabaseContents) -> dict[tuple[str, str], float]:
    """Overlap of image pairs as their number of verified matches (names as keys)."""
    names = contents.image_names
    return {(names[a], names[b]): float(len(m)) for (a, b), m in contents.matches.items()}


def dataset_overlap(scene: DatasetScene) -> dict[tuple[str, str], float] | None:
    """The dataset's own overlap scores (e.g. BlendedMVS pair.txt), if it has them."""
    if not scene.overlap:
        return None
    return {(a, b): float(score) for a, pairs in scene.overlap.items() for b, score in pairs}


def restrict_contents(contents: DatabaseContents, image_ids: list[int]) -> DatabaseContents:
    """The contents of a subset of images (matches and F's between them only)."""
    keep = set(image_ids)
    return replace(
        contents,
        image_names={i: n for i, n in contents.image_names.items() if i in keep},
        image_camera={i: c for i, c in contents.image_camera.items() if i in keep},
        keypoints={i: k for i, k in contents.keypoints.items() if i in keep},
        matches={p: m for p, m in contents.matches.items() if p[0] in keep and p[1] in keep},
        fundamentals={
            p: f for p, f in contents.fundamentals.items() if p[0] in keep and p[1] in keep
        },
    )


def scene_database_path(scene: DatasetScene, folder: Path, max_image_size: int) -> Path:
    """Where :func:`scene_database` caches the scene's database.

    The name carries a digest of the image names, so a scene cut to other views gets
    its own database instead of a stale one.
    """
    names = "\n".join(v.name for v in scene.views).encode()
    digest = hashlib.sha256(names).hexdigest()[:10]
    return folder / f"{scene.kind}-{scene.name}-{max_image_size}-{digest}.db"


def scene_database(scene: DatasetScene, folder: Path, max_image_size: int) -> Path:
    """The scene's database (all its images), built on first use and reused; its
    verification seeded, so that every build of it holds the same matches."""
    folder.mkdir(parents=True, exist_ok=True)
    path = scene_database_path(scene, folder, max_image_size)
    if path.exists():
        return path
    partial = path.with_suffix(".partial.db")
    partial.unlink(missing_ok=True)
    logger.info("building the database of %s (%d images)", scene.name, len(scene.views))
    build_database(
        scene.image_dir,
        partial,
        image_names=[v.name for v in scene.views],
        max_image_size=max_image_size,
        seed=0,
    )
    partial.rename(path)
    return path


def sequence_database(source: Path, image_names: list[str], target: Path) -> Path:
    """A copy of ``source`` with the matches and geometries of ``image_names`` only.

    The other images stay but are unmatched, so mapping and calibrate_view_graph
    see only the sequence. Descriptors are dropped (nothing downstream needs them),
    which keeps the per-run copies small.
    """
    shutil.copyfile(source, target)
    keep = set(image_names)
    with pycolmap.Database.open(str(target)) as db:
        ids = {image.image_id for image in db.read_all_images() if image.name in keep}
        pair_ids = set(db.read_two_view_geometries()[0]) | set(db.read_all_matches()[0])
        for pair_id in pair_ids:
            a, b = (int(v) for v in pycolmap.pair_id_to_image_pair(pair_id))
            if not (a in ids and b in ids):
                db.delete_matches(a, b)
                db.delete_two_view_geometry(a, b)
        db.clear_descriptors()
    with sqlite3.connect(target) as connection:
        connection.execute("VACUUM")
    return target


def run_task(task: RunTask) -> list[RunRecord]:
    """All methods of one run; a method that fails gives a record with its message."""
    common = dict(
        experiment=task.kind,
        scene=task.scene,
        run=task.run,
        seed=task.seed,
        num_images=len(task.contents.image_names),
        perturbation=perturbation_label(task.perturbation),
    )
    records: list[RunRecord] = []
    calibration_methods = tuple(m for m in task.methods if m in (*TRIFOCAL_METHODS, "fundamental"))
    if calibration_methods:
        options = CalibrationOptions(prior=tuple(task.prior), seed=task.seed, workers=1)
        try:
            results = calibrate_contents_methods(task.contents, options, calibration_methods)
        except CalibrationError as exc:
            records += [
                RunRecord.finished(
                    None, task.truth, task.prior, method=m, message=str(exc), **common
                )
                for m in calibration_methods
            ]
        else:
            for method, (result,) in results.items():
                std = [result.std[name] for name in ("fx", "fy", "cx", "cy")]
                records.append(
                    RunRecord.finished(
                        result.intrinsics,
                        task.truth,
                        task.prior,
                        method=method,
                        std=std,
                        seconds=result.seconds,
                        extra={"num_inlier_triplets": result.num_inlier_triplets},
                        **common,
                    )
                )
    for method in ("calibrate_view_graph", "mapping"):
        if method in task.methods:
            records.append(_pycolmap_baseline(task, method, common))
    return records


def _pycolmap_baseline(task: RunTask, method: str, common: dict) -> RunRecord:
    """calibrate_view_graph or incremental mapping (refining f and pp) from the prior."""
    if task.sequence_database is None:
        raise ValueError("the pycolmap baselines need the sequence database")
    began = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        database = Path(folder) / "database.db"
        shutil.copyfile(task.sequence_database, database)
        with pycolmap.Database.open(str(database)) as db:
            (camera,) = db.read_all_cameras()
            camera.params = np.asarray(task.prior, float).tolist()
            db.update_camera(camera)
        try:
            if method == "calibrate_view_graph":
                options = pycolmap.ViewGraphCalibrationOptions()
                options.random_seed = task.seed % 2**31
                # The focal estimate is made before the optional re-estimation of the
                # relative poses, which leaves it as it is and costs far more time.
                options.reestimate_relative_pose = False
                with keep_colmap_quiet():
                    ok = pycolmap.calibrate_view_graph(str(database), options)
                if not ok:
                    raise CalibrationError("calibrate_view_graph failed")
                with pycolmap.Database.open(str(database)) as db:
                    (camera,) = db.read_all_cameras()
                estimate = np.asarray(camera.params, float)
            else:
                model = incremental_mapping(
                    database,
                    None,
                    Path(folder) / "sparse",
                    refine=Refinement(focal_length=True, principal_point=True),
                    seed=task.seed % 2**31,
                )
                refine_intrinsics(model)
                (camera,) = model.cameras.values()
                estimate = camera_intrinsics(camera)
        except CalibrationError as exc:
            return RunRecord.finished(
                None, task.truth, task.prior, method=method, message=str(exc), **common
            )
    return RunRecord.finished(
        estimate,
        task.truth,
        task.prior,
        method=method,
        seconds=time.perf_counter() - began,
        **common,
    )


def evaluation_tasks(scene: DatasetScene, options: EvaluationOptions, work: Path) -> list[RunTask]:
    """One task per (image count, perturbation range, run)."""
    unknown = [m for m in options.methods if m not in EVALUATION_METHODS]
    if unknown:
        raise CalibrationError(f"unknown method {unknown[0]!r} (choose from {EVALUATION_METHODS})")
    database = scene_database(scene, options.cache or work, options.max_image_size)
    contents = read_database(database)
    ids_by_name = {name: i for i, name in contents.image_names.items()}
    names = [v.name for v in scene.views if v.name in ids_by_name]
    if len(names) < 3:
        raise CalibrationError(f"{scene.name}: fewer than 3 images have features in the database")
    overlap = dataset_overlap(scene) or match_overlap(contents)
    needs_database = {"calibrate_view_graph", "mapping"} & set(options.methods)
    tasks = []
    for count in sorted({min(c, len(names)) for c in options.image_counts}):
        sequence = select_sequence(names, overlap, count)
        truth = np.mean([scene.view(n).intrinsics for n in sequence], axis=0)
        subset = restrict_contents(contents, [ids_by_name[n] for n in sequence])
        sequence_db = None
        if needs_database:
            sequence_db = sequence_database(database, sequence, work / f"sequence-{count}.db")
        for p_index, perturbation in enumerate(options.perturbations):
            for run in range(options.runs):
                seed = int(
                    np.random.SeedSequence([options.seed, count, p_index, run]).generate_state(1)[0]
                )
                rng = np.random.default_rng(seed)
                methods = tuple(
                    m for m in options.methods if m != "mapping" or run < options.mapping_runs
                )
                tasks.append(
                    RunTask(
                        kind=scene.kind,
                        scene=scene.name,
                        run=run,
                        seed=seed,
                        perturbation=perturbation,
                        truth=truth,
                        prior=perturbed_prior(truth, perturbation, rng),
                        contents=subset,
                        methods=methods,
                        sequence_database=sequence_db,
                    )
                )
    return tasks


def evaluate_scene(scene: DatasetScene, options: EvaluationOptions) -> list[RunRecord]:
    """Run the protocol on one scene; returns one record per (run, method)."""
    with tempfile.TemporaryDirectory(prefix="colmap-trifocal-evaluate-") as folder:
        tasks = evaluation_tasks(scene, options, Path(folder))
        results = run_tasks(
            run_task,
            tasks,
            options.workers,
            options.dask_address,
            f"{scene.name}: runs",
            progress=options.progress,
        )
    return [record for records in results for record in records]


def scenes_at(kind: str, path: Path) -> list[DatasetScene]:
    """The scene at ``path``, or every scene in its sub-folders (CalibrationError if none)."""
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
