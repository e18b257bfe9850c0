"""``colmap-trifocal run IMAGES WORKSPACE``: features, calibration, mapping, bundle adjustment.

Before any work: the flags, the workspace and ``--png`` paths, and the rule that no output (the
workspace's ``database.db``, ``sparse/``, ``report.json``, the PNG) is or holds an
input (the images, ``--database``, ``--model``). Then the pipeline runs
(:func:`colmap_trifocal.reconstruction.workflow.run_pipeline`), announcing its stages on
stderr when stderr is a terminal, and the report is printed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..common.arguments import integer_in, seed
from ..common.files import Output, refuse_outputs_over_inputs
from .output import check_output_file, check_output_folder, native_output_silenced, warn


def add_parser(commands: argparse._SubParsersAction) -> None:
    """``run IMAGES WORKSPACE``: features, calibration, mapping, bundle adjustment."""
    from ..database.camera_groups import GROUPINGS
    from ..database.cameras import SUPPORTED_MODELS
    from ..database.features import MATCHERS, MAX_IMAGE_SIZE_RANGE
    from ..reconstruction.workflow import RunOptions

    run = commands.add_parser(
        "run", help="images -> features -> TrifocalCalib -> mapping -> bundle adjustment"
    )
    run.add_argument(
        "images", type=Path, help="folder of images (with --database: optional, for colours)"
    )
    run.add_argument(
        "workspace", type=Path, help="output folder: database.db, sparse/0, report.json"
    )
    run.add_argument(
        "--max-image-size",
        type=integer_in(*MAX_IMAGE_SIZE_RANGE),
        default=RunOptions.max_image_size,
        help="longest image side for SIFT, in pixels",
    )
    run.add_argument(
        "--matcher",
        choices=MATCHERS,
        default=RunOptions.matcher,
        help="pycolmap feature matching: every pair (exhaustive, default) or neighbours in "
        "name order (sequential: video)",
    )
    run.add_argument(
        "--camera-model",
        default=RunOptions.camera_model,
        choices=SUPPORTED_MODELS,
        help="COLMAP model of the new cameras (default SIMPLE_RADIAL, COLMAP's; one camera "
        "per image, as COLMAP's default, grouped into physical cameras by --group)",
    )
    run.add_argument(
        "--group",
        choices=GROUPINGS,
        default=RunOptions.group,
        help="camera ids sharing intrinsics: auto (same model, size and stored parameters; "
        "default), camera (each camera id alone), all (every image one camera)",
    )
    _add_stage_arguments(run)


def _add_stage_arguments(run: argparse.ArgumentParser) -> None:
    """The mapping, calibration and refinement settings, the inputs to start from, the
    outputs."""
    from ..intrinsics.api import METHODS
    from ..reconstruction.mapping import MAPPERS, REFINE_CHOICES
    from ..reconstruction.workflow import RunOptions

    run.add_argument(
        "--mapper",
        choices=MAPPERS,
        default=RunOptions.mapper,
        help="pycolmap incremental mapping or the global mapper (GLOMAP), both started "
        "from the TrifocalCalib estimate",
    )
    run.add_argument(
        "--method",
        choices=METHODS,
        default=RunOptions.method,
        help="TrifocalCalib variant (default msac-opt) or the Mendonça-Cipolla baseline",
    )
    run.add_argument(
        "--refine",
        choices=REFINE_CHOICES,
        default=RunOptions.refine,
        help="after mapping: bundle adjustment of focal lengths and principal points (ba, "
        "default) or none (the estimate kept where the images determined it)",
    )
    run.add_argument(
        "--seed",
        type=seed,
        default=0,
        help="random seed of the matches' verification, calibration and mapping (default 0)",
    )
    run.add_argument("--database", type=Path, help="start from this database (it is copied)")
    run.add_argument(
        "--model",
        type=Path,
        help="existing COLMAP model (with --database): write the estimate, refine",
    )
    run.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the results of an earlier run in WORKSPACE",
    )
    run.add_argument(
        "--png", type=Path, metavar="OUT", help="render the model offscreen to this PNG (Open3D)"
    )


def run(args: argparse.Namespace) -> int:
    """Check, run the pipeline, print the report (and render the PNG); exit status 0."""
    from ..intrinsics.results import SkippedGroup
    from ..reconstruction.workflow import RunOptions, run_inputs, run_pipeline, workspace_outputs
    from ..reconstruction.workspace import refuse_workspace_over_images

    if args.png is not None:
        from ..common.extras import require_extra

        require_extra("open3d", "run --png")
    progress = sys.stderr.isatty()
    options = RunOptions(
        max_image_size=args.max_image_size,
        matcher=args.matcher,
        camera_model=args.camera_model,
        group=args.group,
        mapper=args.mapper,
        method=args.method,
        refine=args.refine,
        seed=args.seed,
        database=args.database,
        model=args.model,
        overwrite=args.overwrite,
        progress=progress,
    )
    # With --database, IMAGES is optional (only used to colour the points).
    images = args.images if args.database is None or args.images.is_dir() else None
    refuse_workspace_over_images(images, args.workspace)
    if args.workspace.is_dir() or not args.workspace.exists():  # a file: the workflow says so
        check_output_folder(args.workspace, "WORKSPACE")
    outputs = workspace_outputs(args.workspace)
    if args.png is not None:
        check_output_file(args.png, "--png")
        outputs.append(Output("--png", args.png))
    refuse_outputs_over_inputs(outputs, run_inputs(images, options))
    report = run_pipeline(
        images, args.workspace, options, _announce if progress else None
    ).to_json()
    note = report["mapping"].get("note")  # the mapping's retries
    if note is not None:
        print(note, file=sys.stderr)
    print(format_report(report))
    for camera in report["cameras"]:
        if camera["warning"] is not None:
            warn(camera["warning"])
    for group in report["skipped_cameras"]:
        skipped = SkippedGroup(group["camera_ids"], group["num_images"], group["skipped"])
        warn(f"{skipped.message()}; mapped from its stored values")
    for skipped in report["skipped_images"]:  # as COLMAP skips what it cannot read
        warn(f"skipped {skipped['name']}: {skipped['reason']}")
    if args.png is not None:
        from ..reconstruction.visualize import show

        with native_output_silenced(args.verbosity):
            written = show(args.workspace / "sparse" / "0", args.png)
        print(f"wrote {written}")
    return 0


def _announce(stage: str) -> None:
    """A stage of the run starts: one line on stderr (a terminal)."""
    print(f"{stage} ...", file=sys.stderr, flush=True)


def format_report(report: dict) -> str:
    """Human-readable summary of a run's report: per camera the TrifocalCalib estimate,
    the refined intrinsics and their difference (pixels), per skipped camera group its
    stored and refined intrinsics, then the seconds per stage."""
    from ..intrinsics.results import PARAMETER_NAMES

    lines = [
        f"registered {report['num_registered_images']}/{report['num_images']} images, "
        f"{report['num_points3D']} points, mean reprojection error "
        f"{report['mean_reprojection_error_px']:.3f} px",
        f"{'camera':>6} {'':>9} {'fx':>10} {'fy':>10} {'cx':>10} {'cy':>10}",
    ]
    for camera in report["cameras"]:
        for label in ("trifocal", "refined", "difference"):
            values = " ".join(f"{camera[label][name]:>10.2f}" for name in PARAMETER_NAMES)
            lines.append(f"{camera['camera_id']:>6} {label:>9} {values}")
    for group in report["skipped_cameras"]:  # mapped from their stored values
        for label in ("stored", "refined"):
            if group[label] is not None:
                values = " ".join(f"{group[label][name]:>10.2f}" for name in PARAMETER_NAMES)
                lines.append(f"{group['camera_id']:>6} {label:>9} {values}")
    for camera in report["cameras"]:
        if camera.get("mapped_model", camera["model"]) != camera["model"]:
            params = ", ".join(f"{v:+.4f}" for v in camera["distortion"])
            lines.append(
                f"camera {camera['camera_id']} mapped as {camera['mapped_model']} (distortion "
                f"{params}): the tracks determine a lens {camera['model']} cannot hold"
            )
    lines.append(
        "seconds: " + ", ".join(f"{stage} {t:.1f}" for stage, t in report["seconds"].items())
    )
    return "\n".join(lines)
