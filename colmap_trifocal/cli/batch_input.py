"""One input of a batch (a database or a COLMAP model folder) calibrated into JSON-able lines.

``calibrate DB [DB ...]`` runs :func:`calibrate_input` once per input, in this process or
on a Dask worker. It reads the input itself and returns plain dicts, one per camera group
(the group's JSON object with the input's path as ``database``), or one
``{"database", "error"}`` when the input cannot be calibrated: no pycolmap object crosses
a process boundary, and a failing input does not stop the others.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..common.errors import CalibrationError
from ..database.from_reconstruction import MODEL_FILES
from ..database.snapshot import DatabaseContents
from ..database.writing import check_writable
from ..intrinsics.api import (
    add_read_seconds,
    calibrate_groups,
    read_contents,
    reconstruction_groups,
    write_calibrations,
)
from ..intrinsics.options import CalibrationOptions
from ..intrinsics.results import CameraCalibration, SkippedGroup


def is_model_folder(path: Path) -> bool:
    """``path`` is a folder holding at least one of a COLMAP model's files
    (``cameras``, ``images``, ``points3D`` as ``.bin`` or ``.txt``)."""
    return path.is_dir() and any(
        (path / f"{name}{ext}").is_file() for name in MODEL_FILES for ext in (".bin", ".txt")
    )


def check_input_path(path: Path) -> None:
    """Refuse a folder that holds no COLMAP model file (neither a database nor a model).

    Raises:
        CalibrationError: ``path`` is such a folder.
    """
    if path.is_dir() and not is_model_folder(path):
        raise CalibrationError(
            f"database path is a directory: {path}; not a COLMAP model folder either "
            f"(no {', '.join(MODEL_FILES)} .bin/.txt)"
        )


def calibrate_path(
    path: Path,
    options: CalibrationOptions,
    check_contents: Callable[[DatabaseContents], None] | None = None,
) -> tuple[list[CameraCalibration], list[SkippedGroup]]:
    """Calibrate a database, or a model folder from its tracks (never written here).

    ``check_contents`` sees a database's contents before the calibration (it raises
    :class:`CalibrationError` to refuse them, e.g. a ``--model`` of other images).

    Returns:
        The calibrated groups (of a model: each with ``reference``, the model's own
        intrinsics) and the skipped ones.

    Raises:
        CalibrationError: the input cannot be read or calibrated.
    """
    check_input_path(path)
    if is_model_folder(path):
        return reconstruction_groups(path, options)
    contents, read_seconds = read_contents(path)
    if check_contents is not None:
        check_contents(contents)
    by_method, skipped = calibrate_groups(contents, options, (options.method,))
    results = by_method[options.method]
    results = add_read_seconds(results, read_seconds)
    return results, skipped


@dataclass(frozen=True)
class InputTask:
    """One input of a batch: its path, the calibration's options and whether to store
    the estimate in the database (``--write``: backup first, one transaction)."""

    path: str
    options: CalibrationOptions = field(default_factory=CalibrationOptions)
    write: bool = False


def calibrate_input(task: InputTask) -> list[dict[str, Any]]:
    """The JSON lines of one input: one dict per group, or one error.

    A group's line is its ``to_json()`` object with ``database`` (the input's path)
    first, ``warning`` (the one-line warning of :meth:`.CameraCalibration.warning` or a
    skipped group's message; None) and, with ``write``, ``written`` (its cameras were
    stored: the images determined at least one value). An input that cannot be read,
    calibrated or written gives ``[{"database": path, "error": message}]``; a model
    folder with ``write`` is such an error (the estimate is written into databases only).
    """
    path = Path(task.path)
    try:
        if task.write:
            if is_model_folder(path):
                raise CalibrationError(
                    "--write stores the estimate in a database: this is a COLMAP model folder"
                )
            check_writable(path)
        results, skipped = calibrate_path(path, task.options)
        if task.write:
            write_calibrations(path, results)
    except CalibrationError as exc:
        return [{"database": task.path, "error": str(exc)}]
    except OSError as exc:
        where = f": {exc.filename}" if exc.filename is not None else ""
        return [{"database": task.path, "error": f"{exc.strerror or exc}{where}"}]
    lines = []
    for result in results:
        line = {"database": task.path, **result.to_json(), "warning": result.warning()}
        if task.write:
            line["written"] = result.determined_anything
        lines.append(line)
    for group in skipped:
        lines.append({"database": task.path, **group.to_json(), "warning": group.message()})
    return lines
