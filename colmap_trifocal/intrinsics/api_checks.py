"""The public entry's checks of what a caller passes (:mod:`.api`): paths, contents,
options, methods and groupings, each refused with :class:`CalibrationError` where Python
would raise a TypeError or an AttributeError deep inside."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from ..common.errors import CalibrationError
from ..database.cameras import CameraInfo
from ..database.snapshot import DatabaseContents
from .options import METHODS, CalibrationOptions, check_options


def checked_options(options: CalibrationOptions | None) -> CalibrationOptions:
    """The options (defaults for None), checked; CalibrationError for another type."""
    return CalibrationOptions() if options is None else check_options(options)


def checked_path(value: object, what: str) -> Path:
    """``value`` as a path (str, bytes or os.PathLike); CalibrationError for anything else
    (None, a number, a list of paths), where ``Path()`` would raise TypeError."""
    if isinstance(value, bytes):
        value = os.fsdecode(value)
    if not isinstance(value, str | os.PathLike):
        raise CalibrationError(
            f"{what} must be a path (str or os.PathLike), got {type(value).__name__}"
        )
    try:
        path = Path(value)
    except TypeError as exc:  # an os.PathLike whose __fspath__ gives no str
        raise CalibrationError(f"{what} must be a path: {exc}") from exc
    if (isinstance(value, str) and not value) or "\0" in str(path):
        raise CalibrationError(f"{what} must be a path, got {str(value)!r}")
    return path


def checked_contents(contents: object) -> DatabaseContents:
    """``contents`` if it is database contents (:func:`read_contents`); CalibrationError
    otherwise (an attribute error deep in the grouping before)."""
    if not isinstance(contents, DatabaseContents):
        raise CalibrationError(
            f"contents must be DatabaseContents (see read_contents), got {type(contents).__name__}"
        )
    return contents


def checked_methods(methods: object) -> tuple[str, ...]:
    """At least one method name of :data:`METHODS`, as a tuple; CalibrationError for an
    empty or non-sequence value (a lone string is not split into letters)."""
    if isinstance(methods, str | bytes) or not isinstance(methods, Sequence):
        raise CalibrationError(f"methods must be a tuple of method names, got {methods!r}")
    if not methods:
        raise CalibrationError(f"methods: at least one of {METHODS}, got none")
    unknown = [m for m in methods if not isinstance(m, str) or m not in METHODS]
    if unknown:
        raise CalibrationError(f"unknown method {unknown[0]!r} (choose from {METHODS})")
    return tuple(methods)


def checked_grouping(
    grouping: object, contents: DatabaseContents
) -> Mapping[int, CameraInfo] | None:
    """None, or a mapping from every camera id of ``contents`` to its CameraInfo (what
    the grouping compares); CalibrationError otherwise."""
    if grouping is None:
        return None
    if not isinstance(grouping, Mapping):
        raise CalibrationError(
            f"grouping must map camera ids to CameraInfo, got {type(grouping).__name__}"
        )
    bad = [k for k, v in grouping.items() if not isinstance(v, CameraInfo) or k != v.camera_id]
    if bad:
        raise CalibrationError(f"grouping: camera id {bad[0]!r} does not map to its CameraInfo")
    missing = sorted(set(contents.cameras) - set(grouping))
    if missing:
        raise CalibrationError(f"grouping: camera id {missing[0]} of the contents is missing")
    return grouping
