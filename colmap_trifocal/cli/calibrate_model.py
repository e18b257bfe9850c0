"""``colmap-trifocal calibrate MODEL_DIR``: a COLMAP model's cameras from its tracks.

The model's 2D–3D tracks are the three-view tracks (its 3D points and poses are not
used), so the estimate is an independent check of the model's own, bundle-adjusted
intrinsics: the table of ``calibrate``, then each group's estimate beside the model's
values (:meth:`.CameraCalibration.compare_with_model`); ``--json`` adds ``reference``
(the model's fx, fy, cx, cy) to each group's object. The estimate goes nowhere else:
options that write a database or a model copy are refused.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..common.errors import CalibrationError
from ..common.files import Input, refuse_outputs_over_inputs
from .tables import print_comparisons, print_table

if TYPE_CHECKING:
    from ..intrinsics.api import CalibrationOptions


def run_model(args: argparse.Namespace, model: Path, options: CalibrationOptions) -> int:
    """Check, calibrate the model folder, print both tables, write the JSON; exit status 0."""
    from ..intrinsics.api import reconstruction_groups
    from .calibrate import outputs_to_stdout, write_text_outputs

    check_model_arguments(args, model)
    results, skipped = reconstruction_groups(model, options)
    out = sys.stderr if outputs_to_stdout(args) else sys.stdout  # stdout stays JSON
    print_table(results, skipped, out)
    print_comparisons(results, out)
    entries = [r.to_json() for r in results] + [g.to_json() for g in skipped]
    write_text_outputs(args, entries, results)
    return 0


def check_model_arguments(args: argparse.Namespace, model: Path) -> None:
    """Refuse the flags that need a database, and a ``--json`` or ``--cameras-txt`` that
    cannot be written or is a file of the model."""
    from .calibrate import check_text_outputs

    if args.write:
        raise CalibrationError(
            f"--write stores the estimate in a database: {model} is a COLMAP model folder "
            "(result.apply(reconstruction) writes it into a reconstruction)"
        )
    given = model_copy_flags(args)
    if given:
        raise CalibrationError(f"{given[0]} goes with a database: {model} is a COLMAP model folder")
    refuse_outputs_over_inputs(check_text_outputs(args), [Input.folder(model, "MODEL")])


def model_copy_flags(args: argparse.Namespace) -> list[str]:
    """The given flags of ``--model``'s copy (each takes one database)."""
    flags = (
        ("--model", args.model),
        ("--output", args.output),
        ("--refine", args.refine),
        ("--refine-distortion", args.refine_distortion or None),
    )
    return [flag for flag, value in flags if value is not None]
