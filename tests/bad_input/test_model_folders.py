"""COLMAP model folders: truncated, huge or sparse files, FIFOs, cameras and poses that are
not finite.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import CliResult

from bad_input.builders import (
    copy_good,
    make_model,
    model_of_other_images,
    models_with,
    only_cameras_bin,
    run_database,
    two_image_model,
)
from bad_input.table import (
    Case,
    check_case,
)

CASES: dict[str, Case] = {
    "show: missing model": Case(
        copy_good, "model folder not found", argv=lambda f, p, w: ("show", f / "nope")
    ),
    "show: truncated images.bin": Case(
        models_with({"images": 3000}),
        "truncated COLMAP model file",
        argv=lambda f, p, w: ("show", p, "--png", f / "x.png"),
    ),
    "show: empty points3D.bin": Case(
        models_with({"points3D": 0}),
        "(0 bytes)",
        argv=lambda f, p, w: ("show", p, "--png", f / "x.png"),
    ),
    "show: truncated points3D.bin": Case(
        models_with({"points3D": 20000}),
        "need 39608 bytes, the file has 20000",
        argv=lambda f, p, w: ("show", p, "--png", f / "x.png"),
    ),
    "show: points3D.bin with its count only": Case(
        models_with({"points3D": 8}),
        "the file has 8",
        argv=lambda f, p, w: ("show", p, "--png", f / "x.png"),
    ),
    "evaluate colmap: garbage points3D.bin": Case(
        models_with({"points3D": None}),
        "points3D.bin",
        argv=lambda f, p, w: ("evaluate", "colmap", p, "--runs", "1"),
    ),
    "evaluate colmap: no ../../images": Case(
        models_with(images=False),
        ": image folder",
        argv=lambda f, p, w: ("evaluate", "colmap", p, "--runs", "1"),
    ),
    "model folder with only cameras.bin": Case(
        only_cameras_bin, "not a COLMAP model (no images, points3D .bin/.txt)"
    ),
    "model folder: truncated images.bin": Case(
        models_with({"images": 3000}), "truncated COLMAP model file"
    ),
    "model folder: garbage points3D.bin": Case(models_with({"points3D": None}), "points3D.bin"),
    "model of 2 registered images": Case(
        two_image_model, "the reconstruction has 2 registered image(s), at least 3"
    ),
    "run --model missing": Case(
        copy_good, "model folder not found", argv=run_database("--model", "{folder}/nope")
    ),
    "run --model is a file": Case(
        copy_good, "model folder not found", argv=run_database("--model", "{path}")
    ),
    "run --model garbage": Case(
        lambda f, g: copy_good(make_model(f, {"points3D": None}).parent.parent, g),
        "COLMAP model file",
        argv=run_database("--model", "{folder}/sparse/0"),
    ),
    "calibrate --model of another database": Case(
        model_of_other_images,
        "6 of the model's 6 images are not in the database (e.g. other_camera000001_frame",
        argv=lambda f, p, w: ("calibrate", p, "--model", f / "sparse" / "0", "--output", w),
    ),
}


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input(
    name: str,
    good_database: Path,
    tmp_path: Path,
    run_main: Callable[..., CliResult],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    check_case(CASES[name], good_database, tmp_path, run_main, monkeypatch)
