"""``colmap-trifocal calibrate DATABASE``: the intrinsics of a database's cameras.

Prints a table (one line per camera group), then writes the outputs in this order: the
model copy (``--model``/``--output``), the JSON (``--json``), the database (``--write``,
last, so a failing output never leaves a changed database behind). Every argument and
output path is checked before the database is read.

A COLMAP model folder instead of a database is calibrated from its tracks
(:mod:`.calibrate_model`); several inputs, a quoted glob pattern or ``--dask`` give one
JSON line per camera group as each input finishes (:mod:`.batch`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..common.arguments import MAX_WORKERS_FLAG, integer_in, seed
from ..common.errors import CalibrationError
from ..common.files import Input, Output, refuse_outputs_over_inputs
from .output import check_output_file, check_output_folder, is_stdout, write_text_output
from .tables import print_table

if TYPE_CHECKING:
    from collections.abc import Callable

    import pycolmap

    from ..database.snapshot import DatabaseContents
    from ..intrinsics.api import CalibrationOptions, CameraCalibration


def add_parser(commands: argparse._SubParsersAction) -> None:
    """``calibrate DATABASE [DATABASE ...]``: the contract in DESIGN.md."""
    from ..database.camera_groups import GROUPINGS
    from ..intrinsics.api import METHODS

    calibrate = commands.add_parser(
        "calibrate", help="estimate the intrinsics of the cameras of COLMAP databases or models"
    )
    calibrate.add_argument(
        "database",
        type=Path,
        nargs="+",
        metavar="DATABASE",
        help="COLMAP database with verified matches, or a COLMAP model folder (sparse/0: "
        "calibrated from its tracks); several, or a quoted glob pattern: one JSON line per "
        "camera group as each input finishes",
    )
    calibrate.add_argument(
        "--method",
        choices=METHODS,
        default="msac-opt",
        help="TrifocalCalib variant (default msac-opt) or the Mendonça-Cipolla baseline "
        "(fundamental)",
    )
    calibrate.add_argument(
        "--prior",
        metavar="FX,FY,CX,CY",
        help="starting intrinsics in pixels (default: the camera stored in the database)",
    )
    calibrate.add_argument(
        "--camera-id",
        type=int,
        action="append",
        dest="camera_ids",
        metavar="ID",
        help="calibrate only the group of this camera (repeatable)",
    )
    calibrate.add_argument(
        "--group",
        choices=GROUPINGS,
        default="auto",
        help="camera ids sharing intrinsics: auto (same model, size and stored parameters; "
        "default), camera (each camera id alone), all (every image one camera)",
    )
    calibrate.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    _add_output_arguments(calibrate)
    _add_model_arguments(calibrate)


def _add_output_arguments(calibrate: argparse.ArgumentParser) -> None:
    """Where the estimate goes (JSON, cameras.txt, the database), and how the run works."""
    from ..common.parallel import MAX_WORKERS
    from ..intrinsics.api import CalibrationOptions

    calibrate.add_argument(
        "--json",
        type=Path,
        metavar="OUT",
        help="write the results as JSON (-: to stdout, the table then goes to stderr); "
        "with several inputs as JSON lines (default: stdout)",
    )
    calibrate.add_argument(
        "--cameras-txt",
        type=Path,
        metavar="OUT",
        help="write the estimate as COLMAP's cameras.txt (-: to stdout, the table then goes "
        "to stderr): every camera id of each calibrated group",
    )
    calibrate.add_argument(
        "--write",
        action="store_true",
        help="store the estimate in the database (a backup <name>.bak is made first)",
    )
    calibrate.add_argument(
        "--max-triplets",
        type=int,
        default=CalibrationOptions.max_triplets,
        metavar="N",
        help=f"image triplets per camera (default {CalibrationOptions.max_triplets}; more: "
        "slower, a little more accurate)",
    )
    calibrate.add_argument(
        "--no-prior",
        action="store_true",
        help="ignore the stored camera: start from f = 1.2 · max(width, height), centred",
    )
    calibrate.add_argument(
        "--no-focal-search",
        action="store_true",
        help="start the tensors from the prior's focal length instead of searching it",
    )
    calibrate.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    calibrate.add_argument(
        "--workers",
        type=integer_in(1, MAX_WORKERS_FLAG),
        metavar="N",
        help="worker processes and threads (default: one per core, at most "
        f"{MAX_WORKERS}; 1: all the work in this process). The result is the same",
    )


def _add_model_arguments(calibrate: argparse.ArgumentParser) -> None:
    """``--model``: the estimate into a copy of an existing model; and ``--dask``."""
    from ..reconstruction.mapping import REFINE_CHOICES

    calibrate.add_argument(
        "--model",
        type=Path,
        metavar="DIR",
        help="existing COLMAP model of this database: write the estimate into a copy (--output)",
    )
    calibrate.add_argument(
        "--output", type=Path, metavar="DIR", help="new folder for the model written with --model"
    )
    calibrate.add_argument(
        "--refine",
        choices=REFINE_CHOICES,
        help="with --model: bundle adjustment of focal lengths and principal points (default ba)",
    )
    calibrate.add_argument(
        "--refine-distortion",
        action="store_true",
        help="with --model --refine ba: also refine the distortion parameters",
    )
    calibrate.add_argument(
        "--dask",
        metavar="ADDRESS",
        help="calibrate the inputs on this Dask scheduler (tcp://host:8786); its workers "
        "need this package and the inputs' paths",
    )


def run(args: argparse.Namespace) -> int:
    """One database, one model folder, or many inputs (:mod:`.batch`); the exit status."""
    from ..intrinsics.api import check_options
    from .batch import expand_inputs, run_batch
    from .batch_input import check_input_path, is_model_folder

    if args.dask is not None:
        from .experiments import check_dask_flag

        check_dask_flag(args.dask)
    options = _options(args)
    if args.max_triplets < 1:
        raise CalibrationError("--max-triplets must be at least 1")
    check_options(options)
    paths, several = expand_inputs(args.database)
    if several or args.dask is not None:
        return run_batch(args, paths, options)
    (path,) = paths
    check_input_path(path)
    if is_model_folder(path):
        from .calibrate_model import run_model

        return run_model(args, path, options)
    return _run_database(args, path, options)


def _run_database(args: argparse.Namespace, database: Path, options: CalibrationOptions) -> int:
    """Check everything, calibrate, print the table, write the outputs; exit status 0."""
    from ..intrinsics.api import tied_focal_cameras, updated_cameras, write_calibrations
    from .batch_input import calibrate_path

    model = _check_arguments(args, database)
    results, skipped = calibrate_path(database, options, _model_check(args, model))
    # With the JSON or cameras.txt on stdout, the table and messages go to stderr.
    out = sys.stderr if outputs_to_stdout(args) else sys.stdout
    print_table(results, skipped, out)
    update = None
    if args.model is not None:
        from ..reconstruction.into_model import calibrate_model

        update = calibrate_model(
            args.model,
            args.output,
            updated_cameras(results),
            args.refine or "ba",
            refine_distortion=args.refine_distortion,
            reconstruction=model,
            tied=tied_focal_cameras(results),
        )
        print(update.describe(), file=out)
    entries = [r.to_json() for r in results] + [g.to_json() for g in skipped]
    if update is not None:
        for entry in entries:
            entry["model"] = update.to_json()
    write_text_outputs(args, entries, results)
    if args.write:
        written = write_calibrations(database, results)
        if written:
            print(f"wrote {written} camera(s) to {database}", file=out)
        for r in results:
            if not r.determined_anything:
                print(
                    f"camera {r.camera_id} not written: the images determine none of its values",
                    file=out,
                )
    return 0


def outputs_to_stdout(args: argparse.Namespace) -> bool:
    """Whether ``--json`` or ``--cameras-txt`` goes to standard output."""
    return any(path is not None and is_stdout(path) for path in (args.json, args.cameras_txt))


def write_text_outputs(
    args: argparse.Namespace, entries: list[dict], results: list[CameraCalibration]
) -> None:
    """``--json`` (the entries) and ``--cameras-txt`` (COLMAP's cameras.txt of the results),
    each to its file or to standard output."""
    from ..reconstruction.cameras_txt import cameras_txt

    if args.json is not None:
        text = json.dumps(entries, indent=2) + "\n"
        write_text_output(args.json, text, to_stdout=is_stdout(args.json))
    if args.cameras_txt is not None:
        write_text_output(
            args.cameras_txt, cameras_txt(results), to_stdout=is_stdout(args.cameras_txt)
        )


def check_text_outputs(args: argparse.Namespace) -> list[Output]:
    """Check ``--json`` and ``--cameras-txt`` (writable, at most one on standard output);
    the file outputs among them, to check against the inputs."""
    given = [
        (flag, path)
        for flag, path in (("--json", args.json), ("--cameras-txt", args.cameras_txt))
        if path is not None
    ]
    on_stdout = [flag for flag, path in given if is_stdout(path)]
    if len(on_stdout) > 1:
        raise CalibrationError("--json and --cameras-txt cannot both go to standard output")
    for flag, path in given:
        check_output_file(path, flag)
    return [Output(flag, path) for flag, path in given if not is_stdout(path)]


def _options(args: argparse.Namespace) -> CalibrationOptions:
    """The calibration's options from the flags (CalibrationError on a bad value)."""
    from ..intrinsics.api import CalibrationOptions, parse_prior

    return CalibrationOptions(
        method=args.method,
        prior=parse_prior(args.prior) if args.prior is not None else None,
        camera_ids=args.camera_ids,
        seed=args.seed,
        max_triplets=args.max_triplets,
        focal_search=not args.no_focal_search,
        no_prior=args.no_prior,
        progress=not args.no_progress and sys.stderr.isatty(),
        group=args.group,
        workers=args.workers,
    )


def _model_check(
    args: argparse.Namespace, model: pycolmap.Reconstruction | None
) -> Callable[[DatabaseContents], None] | None:
    """With ``--model`` (read as ``model``): refuse a model whose images are not the
    database's."""
    if model is None:
        return None
    from ..reconstruction import into_model

    def check(contents: DatabaseContents) -> None:
        into_model.check_model_images(model, contents.image_names.values(), args.model)

    return check


def _check_arguments(args: argparse.Namespace, database: Path) -> pycolmap.Reconstruction | None:
    """The flags that go together, and every output: writable, and no input overwritten
    (the database itself is the one output of ``--write``). Returns the ``--model``,
    read now (a one-line error before the calibration), or None."""
    from ..database.writing import check_writable

    if (args.model is None) != (args.output is None):
        raise CalibrationError("--model and --output go together")
    if args.model is None and (args.refine is not None or args.refine_distortion):
        raise CalibrationError("--refine and --refine-distortion need --model and --output")
    if args.refine_distortion and args.refine == "none":
        raise CalibrationError("--refine-distortion needs --refine ba")
    inputs = [Input.database(database)]
    outputs = []
    model = None
    if args.model is not None:
        from ..reconstruction import into_model

        into_model.check_output_folder(args.output, args.model)
        check_output_folder(args.output, "--output")
        model = into_model.read_model(args.model)
        inputs.append(Input.folder(args.model, "--model"))
        outputs.append(Output("--output", args.output, folder=True))
    outputs += check_text_outputs(args)
    refuse_outputs_over_inputs(outputs, inputs)
    if args.write:  # refuse a read-only database now, not after the calibration
        check_writable(database)
    return model
