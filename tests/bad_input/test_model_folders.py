"""COLMAP model folders: truncated, huge or sparse files, FIFOs, cameras and poses that are
not finite.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
from conftest import CliResult, require_rendering

from bad_input.builders import (
    copy_good,
    edited_model,
    far_points,
    far_pose,
    make_model,
    model_of_other_images,
    models_with,
    nan_camera,
    only_cameras_bin,
    run_database,
    show_png,
    sparse_model_file,
    special_model_file,
    two_image_model,
)
from bad_input.table import (
    Case,
    table_test,
)


def make_model_folder(folder: Path, _good: Path) -> Path:
    """A good model in ``folder/sparse/0``."""
    return make_model(folder)


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
    # ----- issue 37: huge (sparse) files are never read whole; FIFOs never opened;
    # cameras and poses that are not finite are refused where they are drawn
    "calibrate: 60 GB sparse cameras.bin": Case(
        sparse_model_file("cameras.bin"), "bytes after the last record): "
    ),
    "calibrate: 60 GB sparse images.bin": Case(
        sparse_model_file("images.bin"), "bytes after the last record): "
    ),
    "show: 60 GB sparse cameras.bin": Case(
        sparse_model_file("cameras.bin"), "corrupt COLMAP model file (", argv=show_png
    ),
    "show: 60 GB sparse images.bin": Case(
        sparse_model_file("images.bin"), "corrupt COLMAP model file (", argv=show_png
    ),
    "calibrate: points3D.bin is a FIFO": Case(
        special_model_file("points3D.bin"), "points3D.bin is not a regular file (a FIFO)"
    ),
    "show: frames.bin is a FIFO": Case(
        special_model_file("frames.bin"), "frames.bin is not a regular file (a FIFO)", argv=show_png
    ),
    "show: a camera's params NaN": Case(
        edited_model(nan_camera),
        "cannot draw camera 1 of the model: its params (nan,",
        argv=show_png,
    ),
    "show (window): a camera's params NaN": Case(
        edited_model(nan_camera),
        "cannot draw camera 1 of the model",
        argv=lambda f, p, w: ("show", p),
    ),
    "show (window) on a display nobody serves": Case(
        make_model_folder,
        "cannot open the display (DISPLAY=':99')",
        argv=lambda f, p, w: ("show", p),
        env={"DISPLAY": ":99", "WAYLAND_DISPLAY": None},
    ),
    "calibrate: a camera's params NaN": Case(edited_model(nan_camera), "the stored params (nan,"),
    "show: an image's pose at 1e300": Case(
        edited_model(far_pose), "its pose is not finite or lies beyond 1e+12", argv=show_png
    ),
}


test_bad_input = table_test(CASES)


def test_show_draws_a_model_whose_points_are_all_at_1e300(
    good_database: Path, tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """Points at 1e300 (all of them) are left out of the view, and the cameras drawn: a
    PNG, exit 0 (a TypeError before: the view's vectors overflowed to NaN)."""
    require_rendering()
    model = edited_model(far_points)(tmp_path, good_database)
    result = run_main("show", model, "--png", tmp_path / "view.png")
    assert (result.returncode, result.stderr) == (0, ""), result.stderr
    assert cv2.imread(str(tmp_path / "view.png")).shape == (960, 1280, 3)
