"""A ``run`` workspace's ``report.json`` read back for ``show``'s caption: untrusted input.

The file beside a model may be anything: a FIFO, a huge or sparse file, JSON nested a
hundred thousand levels deep, or a report whose values have the wrong types. It is read
only when it is a regular file of at most :data:`MAX_REPORT_BYTES` (never opened
otherwise, never read past that size), parsed, and checked field by field; a report that
fails any check is not used, and the reason is returned for a warning.
"""

from __future__ import annotations

import json
import math
import reprlib
from dataclasses import dataclass
from pathlib import Path

from ..common.streams import read_regular_file

#: A report larger than this is not read (a run's report holds a few kB per camera).
MAX_REPORT_BYTES = 16 * 1024 * 1024
#: COLMAP's camera ids are unsigned 32-bit integers.
MAX_CAMERA_ID = 2**32 - 1
PARAMETERS = ("fx", "fy", "cx", "cy")


class ReportProblem(ValueError):
    """Why a ``report.json`` is not used (one line)."""


@dataclass(frozen=True)
class ReportCamera:
    """One camera of a run's report: TrifocalCalib's estimate (pixels) and its std."""

    camera_id: int
    num_registered_images: int | None
    trifocal: tuple[float, float, float, float]
    std: dict[str, float | None]


@dataclass(frozen=True)
class RunReportFile:
    """What the caption uses of a run's report."""

    num_registered_images: int
    cameras: tuple[ReportCamera, ...]


def report_path(model: Path) -> Path:
    """The ``report.json`` of the ``run`` workspace that holds ``model`` (``sparse/0``)."""
    return Path(model).resolve().parent.parent / "report.json"


def read_run_report(model: Path) -> tuple[RunReportFile | None, str | None]:
    """The report beside ``model`` and None, or None and why it is not used (None as
    well where there is no report: a model that is not a ``run`` workspace's)."""
    path = report_path(model)
    if not path.exists() and not path.is_symlink():
        return None, None
    try:
        data = read_regular_file(path, MAX_REPORT_BYTES)
    except OSError as exc:
        return None, f"{path}: {exc.strerror or exc}"
    try:
        return parse_report(json.loads(data)), None
    except (ValueError, RecursionError, ReportProblem) as exc:
        reason = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        return None, f"{path}: not a report of colmap-trifocal run ({reason.splitlines()[0]})"


def parse_report(report: object) -> RunReportFile:
    """The checked fields of a parsed report.

    Raises:
        ReportProblem: a field is missing or of the wrong type or range.
    """
    if not isinstance(report, dict):
        raise ReportProblem(f"a JSON {type(report).__name__}, not an object")
    registered = _integer(report.get("num_registered_images"), "num_registered_images")
    cameras = report.get("cameras")
    if not isinstance(cameras, list):
        raise ReportProblem("cameras is not a list")
    return RunReportFile(
        registered, tuple(_camera(c, f"cameras[{i}]") for i, c in enumerate(cameras))
    )


def _camera(entry: object, where: str) -> ReportCamera:
    if not isinstance(entry, dict):
        raise ReportProblem(f"{where} is not an object")
    camera_id = _integer(entry.get("camera_id"), f"{where}.camera_id", MAX_CAMERA_ID)
    count = entry.get("num_registered_images")
    images = None if count is None else _integer(count, f"{where}.num_registered_images")
    trifocal = entry.get("trifocal")
    if not isinstance(trifocal, dict):
        raise ReportProblem(f"{where}.trifocal is not an object")
    values = [_number(trifocal.get(n), f"{where}.trifocal.{n}") for n in PARAMETERS]
    spread = entry.get("trifocal_std")
    if spread is not None and not isinstance(spread, dict):
        raise ReportProblem(f"{where}.trifocal_std is not an object")
    std = {
        name: None
        if spread is None or spread.get(name) is None
        else _number(spread.get(name), f"{where}.trifocal_std.{name}")
        for name in PARAMETERS
    }
    return ReportCamera(camera_id, images, (values[0], values[1], values[2], values[3]), std)


def _integer(value: object, where: str, largest: int = 2**63 - 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= largest:
        raise ReportProblem(f"{where} is {_shown(value)}, not an integer in [0, {largest}]")
    return value


def _number(value: object, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ReportProblem(f"{where} is {_shown(value)}, not a number")
    number = float(value) if abs(value) < 1e300 else math.inf
    if not math.isfinite(number):
        raise ReportProblem(f"{where} is {_shown(value)}, not a finite number")
    return number


def _shown(value: object) -> str:
    """A value for a message: short, one line (``reprlib`` never walks all of it)."""
    return reprlib.repr(value)
