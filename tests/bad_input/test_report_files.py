"""Files read back beside a model: a ``run`` workspace's ``report.json``, whatever it holds.

``show`` captions a model with the report of the ``run`` that made it. A report that cannot
be used (not a regular file, too large, not JSON, nested too deeply, or a field of the wrong
type or range) is ignored: the model is drawn with its own intrinsics in the caption and
one ``warning:`` line says why; nothing blocks, nothing is read whole.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

from conftest import CliResult

from bad_input.builders import make_model, show_png
from bad_input.table import Case, table_test

#: A report that the caption uses (the model of ``make_model`` has 6 images, camera 1).
GOOD_REPORT = {
    "num_registered_images": 6,
    "cameras": [
        {
            "camera_id": 1,
            "num_registered_images": 6,
            "trifocal": {"fx": 1100.0, "fy": 1250.0, "cx": 530.0, "cy": 370.0},
            "trifocal_std": {"fx": 1.0, "fy": 1.0, "cx": 1.0, "cy": None},
        }
    ],
}


def workspace_with_report(write: Callable[[Path], object]) -> Callable[[Path, Path], Path]:
    """A ``run`` workspace in the row's folder: the model in ``sparse/0`` and the report
    ``write`` puts at ``report.json``; returns the model."""

    def make(folder: Path, _good: Path) -> Path:
        model = make_model(folder, images=False)
        write(folder / "report.json")
        return model

    return make


def report_text(text: str) -> Callable[[Path, Path], Path]:
    return workspace_with_report(lambda path: path.write_text(text))


def report_with(**camera: object) -> Callable[[Path, Path], Path]:
    """The good report with camera 1's fields replaced (None: removed)."""
    entry = {**GOOD_REPORT["cameras"][0], **camera}  # type: ignore[index]
    entry = {key: value for key, value in entry.items() if value is not None}
    return report_text(json.dumps({**GOOD_REPORT, "cameras": [entry]}))


def _row(make: Callable[[Path, Path], Path], fragment: str) -> Case:
    return Case(make, fragment, argv=show_png, warning=True, rendering=True)


CASES: dict[str, Case] = {
    'report: camera_id "abc"': _row(report_with(camera_id="abc"), "camera_id is 'abc', not an"),
    "report: camera_id 1e400": _row(
        report_text(json.dumps(GOOD_REPORT).replace('"camera_id": 1', '"camera_id": 1e400')),
        "camera_id is inf, not an integer",
    ),
    "report: camera_id 2**70": _row(
        report_with(camera_id=2**70), "not an integer in [0, 4294967295]"
    ),
    "report: no trifocal": _row(report_with(trifocal=None), "trifocal is not an object"),
    "report: no cameras": _row(
        report_text('{"num_registered_images": 6}'), "cameras is not a list"
    ),
    "report: fx a string": _row(
        report_with(trifocal={"fx": "a", "fy": 1.0, "cx": 1.0, "cy": 1.0}),
        "trifocal.fx is 'a', not a number",
    ),
    "report: cy a list": _row(
        report_with(trifocal={"fx": 1.0, "fy": 1.0, "cx": 1.0, "cy": [1]}),
        "trifocal.cy is [1], not a number",
    ),
    "report: fx NaN": _row(
        report_text(json.dumps(GOOD_REPORT).replace('"fx": 1100.0', '"fx": NaN')),
        "trifocal.fx is nan, not a finite number",
    ),
    "report: std a string": _row(
        report_with(trifocal_std={"fx": "wide"}), "trifocal_std.fx is 'wide', not a number"
    ),
    "report: a list": _row(report_text("[1, 2]"), "a JSON list, not an object"),
    "report: not JSON": _row(report_text("{not json"), "not a report of colmap-trifocal run"),
    "report: 100k nested brackets": _row(
        report_text("[" * 100_000 + "]" * 100_000), "(nested too deeply)"
    ),
    "report: 60 GB sparse file": _row(
        workspace_with_report(lambda path: (path.touch(), os.truncate(path, 60 << 30))),
        "64424509440 bytes, more than the 16777216 expected",
    ),
    "report: a FIFO": _row(workspace_with_report(os.mkfifo), "not a regular file (a FIFO)"),
    "report: a folder": _row(
        workspace_with_report(lambda path: path.mkdir()), "not a regular file (a folder)"
    ),
}


def _wrote_the_png(_case: Case, result: CliResult, tmp_path: Path) -> None:
    """The model is drawn all the same (with its own intrinsics in the caption)."""
    assert result.stdout == f"wrote {tmp_path / 'view.png'}\n"
    assert (tmp_path / "view.png").stat().st_size > 0


test_bad_input = table_test(CASES, check=_wrote_the_png)


def test_a_good_report_is_the_caption(good_database: Path, tmp_path: Path) -> None:
    """The good report above is used (the warning rows fail for what they change alone)."""
    from colmap_trifocal.reconstruction.report_reader import read_run_report
    from colmap_trifocal.reconstruction.visualize import load_model, model_caption

    model = report_text(json.dumps(GOOD_REPORT))(tmp_path, good_database)
    report, problem = read_run_report(model)
    assert problem is None and report is not None
    caption = model_caption(load_model(model), report)
    assert caption[1] == (
        "camera 1 (6 images), TrifocalCalib: fx 1100.0 \u00b1 1.0, fy 1250.0 \u00b1 1.0, "
        "cx 530.0 \u00b1 1.0, cy 370.0 px"
    )
