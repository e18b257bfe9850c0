"""``colmap-trifocal run``: images (or a database) in, calibrated reconstruction out.

Stages, each timed in ``report.json`` (2-4 are :mod:`.pipeline`'s, which
:func:`.pipeline.reconstruct` runs on a database the caller has):

1. features: pycolmap SIFT extraction and matching into ``WORKSPACE/database.db``,
   cameras created as COLMAP's default does (one per image; skipped when an
   existing database is given: it is copied, never modified);
2. calibrate: the camera ids grouped into physical cameras, TrifocalCalib per
   group, the estimate written as the cameras' starting intrinsics; in the
   workspace copy the images of a group then share its first camera;
3. mapping: pycolmap incremental or global (GLOMAP) mapping, the determined
   intrinsics held fixed and the others refined while mapping; incremental
   mapping is retried with relaxed initialisation when it finds no initial pair
   or registers few images, seeded with the widest pair of the calibration's best
   triplets and COLMAP's forward-motion limit lifted (report.json ``mapping`` and
   its ``note`` say what was done, including the seeded pair); the largest
   model written to ``WORKSPACE/sparse/0`` (or an existing model given with
   ``model``: the estimate is written into it instead);
4. refine (``ba``, the default): global bundle adjustment of focal lengths and
   principal points with poses and points; ``none`` skips it.

Nothing is printed: each stage is logged (package logger) and announced to an optional
``on_stage`` callback; the command line shows them.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import pycolmap

from ..common.errors import CalibrationError
from ..common.files import (
    Input,
    Output,
    refuse_outputs_over_inputs,
    remove_database_files,
    write_model_atomically,
    write_text_atomically,
)
from ..common.log import logger
from ..common.pycolmap_child import call_in_child
from ..database.features import check_max_image_size
from ..database.snapshot import DatabaseContents, read_database
from ..database.sqlite_files import copy_database
from ..intrinsics.api import CalibrationOptions, updated_cameras
from ..intrinsics.options import Method
from ..intrinsics.results import apply_cameras
from .images import IMAGE_SUFFIXES, ImageListing, list_images
from .mapping import MAPPERS, REFINE_CHOICES
from .pipeline import (
    ReconstructOptions,
    announce,
    calibrate_for_mapping,
    map_calibrated,
    refine_calibrated,
)
from .report import RunReport, build_report
from .visualize import load_model
from .workspace import WORKSPACE_OUTPUTS, open_workspace, refuse_workspace_over_images


@dataclass
class RunOptions:
    """Settings of :func:`run_pipeline` (the flags of ``colmap-trifocal run``)."""

    max_image_size: int = 1600
    matcher: str = "exhaustive"
    #: COLMAP's default model (``colmap feature_extractor``).
    camera_model: str = "SIMPLE_RADIAL"
    #: pycolmap camera mode of the extraction (``auto``: COLMAP's default, one camera
    #: per image, grouped by the calibration).
    camera_mode: str = "auto"
    #: Grouping of camera ids into physical cameras (see ``calibrate --group``).
    group: str = "auto"
    mapper: str = "incremental"
    method: Method = "msac-opt"
    refine: str = "ba"
    seed: int = 0
    #: Start from this COLMAP database (copied into the workspace) instead of images.
    database: Path | None = None
    #: Start from this COLMAP model: write the estimate into it and refine.
    model: Path | None = None
    overwrite: bool = False
    progress: bool = False

    def __post_init__(self) -> None:
        check_max_image_size(self.max_image_size)

    def reconstruct_options(self) -> ReconstructOptions:
        """The calibration, mapping and refinement settings, as :func:`.pipeline.reconstruct`
        takes them (the stages after the features are the same)."""
        calibration = CalibrationOptions(
            method=self.method, seed=self.seed, progress=self.progress, group=self.group
        )
        return ReconstructOptions(
            calibration=calibration,
            mapper=self.mapper,
            refine=self.refine,
            progress=self.progress,
        )


def run_inputs(images: Path | None, options: RunOptions) -> list[Input]:
    """What a run reads: the images (those directly in the folder), ``--database`` with
    its SQLite companions, the files of ``--model``."""
    inputs = []
    if images is not None:
        inputs.append(Input.folder(Path(images), "IMAGES", IMAGE_SUFFIXES))
    if options.database is not None:
        inputs.append(Input.database(Path(options.database), "--database", "the --database input"))
    if options.model is not None:
        inputs.append(Input.folder(Path(options.model), "--model"))
    return inputs


def workspace_outputs(workspace: Path) -> list[Output]:
    """The workspace's outputs (``database.db``, ``sparse/``, ``report.json``): written,
    and with ``--overwrite`` removed first."""
    return [
        Output(
            "the workspace output", workspace / name, " (use another WORKSPACE)", name == "sparse"
        )
        for name in WORKSPACE_OUTPUTS
    ]


def check_inputs_survive(images: Path | None, workspace: Path, options: RunOptions) -> None:
    """Refuse a run that would overwrite or delete one of its inputs.

    The workspace may not be, hold or lie inside the image folder
    (:func:`.workspace.refuse_workspace_over_images`); no workspace output may be an input
    file (also not through a symlink or a hard link), and no input may lie inside one
    (``sparse/`` is removed with ``--overwrite``): see
    :func:`~colmap_trifocal.common.files.refuse_outputs_over_inputs`.
    """
    refuse_workspace_over_images(images, workspace)
    refuse_outputs_over_inputs(workspace_outputs(workspace), run_inputs(images, options))


def run_pipeline(
    images: Path | None,
    workspace: Path,
    options: RunOptions,
    on_stage: Callable[[str], None] | None = None,
) -> RunReport:
    """Run all stages; returns the report (also written to ``WORKSPACE/report.json``).

    ``on_stage`` receives one line as each long stage starts (features, mapping, bundle
    adjustment); the mapping's retries, if any, are described in ``report.mapping["note"]``.
    """
    if options.refine not in REFINE_CHOICES:
        raise CalibrationError(
            f"unknown --refine {options.refine!r} (choose from {REFINE_CHOICES})"
        )
    if options.mapper not in MAPPERS:
        raise CalibrationError(f"unknown --mapper {options.mapper!r} (choose from {MAPPERS})")
    if options.model is not None and options.database is None:
        raise CalibrationError("--model needs the --database its images were matched in")
    check_inputs_survive(images, workspace, options)
    given_model = load_model(options.model) if options.model is not None else None
    listing = None
    if images is not None and options.database is None:
        listing = list_images(images, options.max_image_size)
    with open_workspace(workspace, overwrite=options.overwrite):
        return _run_stages(images, listing, workspace, options, given_model, on_stage)


def _run_stages(
    images: Path | None,
    listing: ImageListing | None,
    workspace: Path,
    options: RunOptions,
    given_model: pycolmap.Reconstruction | None,
    on_stage: Callable[[str], None] | None,
) -> RunReport:
    """The stages of :func:`run_pipeline` in the prepared, locked workspace; the report."""
    database = workspace / "database.db"
    seconds: dict[str, float] = {}

    began = time.perf_counter()
    contents = _features(images, listing, database, options, on_stage)
    seconds["features"] = time.perf_counter() - began

    began = time.perf_counter()
    stages = options.reconstruct_options()
    # One camera per group while mapping (the workspace copy only); a given model keeps
    # its camera ids.
    calibrated = calibrate_for_mapping(
        contents, database, stages.calibration, merge=options.model is None
    )
    calibrations = calibrated.calibrations
    seconds["calibrate"] = time.perf_counter() - began

    began = time.perf_counter()
    mapping: dict[str, Any] = {}
    if given_model is not None:
        reconstruction = given_model
        updated = updated_cameras(calibrations, determined_only=False)
        apply_cameras(reconstruction, updated, require_all=False)
    else:
        with tempfile.TemporaryDirectory(dir=workspace) as tmp:
            mapped = map_calibrated(database, images, Path(tmp), calibrated, stages, on_stage)
        reconstruction, mapping = mapped.reconstruction, mapped.mapping
    seconds["mapping"] = time.perf_counter() - began

    began = time.perf_counter()
    if options.refine == "ba":
        refine_calibrated(reconstruction, calibrated, on_stage)
    seconds["refine"] = time.perf_counter() - began

    write_model_atomically(reconstruction, workspace / "sparse" / "0")
    report = build_report(
        reconstruction,
        calibrations,
        num_images=len(contents.image_camera),
        method=options.method,
        mapper=options.mapper,
        refine=options.refine,
        seconds=seconds,
        mapping=mapping,
        skipped_cameras=calibrated.skipped_with_cameras(),
        # Files with an image suffix that the extraction did not get (COLMAP skips them too).
        skipped_images=[asdict(s) for s in listing.skipped] if listing else [],
    )
    write_text_atomically(workspace / "report.json", json.dumps(report.to_json(), indent=2) + "\n")
    logger.info("wrote %s", workspace / "report.json")
    return report


def _features(
    images: Path | None,
    listing: ImageListing | None,
    database: Path,
    options: RunOptions,
    on_stage: Callable[[str], None] | None,
) -> DatabaseContents:
    """The workspace's ``database.db``: a copy of ``--database`` (with what is still in its
    ``-wal``), or SIFT features and matches of the listed images; its snapshot."""
    try:
        if options.database is not None:
            contents = read_database(options.database)  # validated (one-line errors)
            copy_database(options.database, database)
            return contents
        assert images is not None and listing is not None
        names = listing.names
        announce(f"features and matching for {len(names)} images (pycolmap SIFT)", on_stage)
        call_in_child(
            "colmap_trifocal.database.features.build_database",
            {
                "image_dir": str(images),
                "database": str(database),
                "image_names": names,
                "max_image_size": options.max_image_size,
                "camera_model": options.camera_model,
                "matcher": options.matcher,
                "camera_mode": options.camera_mode,
                "seed": options.seed,
                "progress": options.progress,
            },
            output=database,
            failure=f"cannot build the database {database}",
            progress=options.progress,
        )
    except BaseException:  # a failed or interrupted copy or build (its child has ended)
        remove_database_files(database)
        raise
    return read_database(database)
