"""Drawing a COLMAP sparse model: offscreen to a PNG with a caption, or in a window.

What the view shows (points, frustums, the framing camera) is :mod:`.scene_view`.
:func:`render_png` writes the caption (the calibrated K ± std and the registered
images, :func:`model_caption`) in a white band above the view with OpenCV.

open3d is imported lazily, so this module (and :func:`load_model`) imports even where
open3d cannot (without ``libusb-1.0-0`` its import fails). Offscreen rendering uses
Filament; on a CPU-only Linux machine it runs on Mesa's llvmpipe Vulkan driver, and
no environment variable is needed. A missing driver makes Filament *abort* the
process instead of raising, so :func:`render_png` first checks, once per process and
in a child process, that a renderer can be created (:func:`offscreen_problem`).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import subprocess
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..common.log import logger
from ..database.cameras import CameraInfo
from ..database.from_reconstruction import grouping_cameras, read_reconstruction
from .report_reader import ReportProblem, RunReportFile, parse_report, read_run_report
from .scene_view import (
    DEBIAN_PACKAGES,
    VERTICAL_FOV_DEG,
    _open3d,
    scene_geometry,
    view_for,
)

if TYPE_CHECKING:
    import open3d


#: Rendered point diameter in pixels per pixel of image height (at least 3 px).
POINT_SIZE_PER_HEIGHT = 1.0 / 240.0

#: Caption text height in pixels per pixel of image width (OpenCV Hershey simplex).
CAPTION_SCALE_PER_WIDTH = 0.6 / 1280.0


_PROBE = (
    "import open3d as o3d\n"
    "o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)\n"
    "o3d.visualization.rendering.OffscreenRenderer(16, 16).render_to_image()\n"
)


def load_model(path: Path) -> pycolmap.Reconstruction:
    """Read a COLMAP sparse model folder (e.g. ``sparse/0``, ``.bin`` or ``.txt`` files).

    Raises:
        CalibrationError: the folder is missing, lacks cameras/images/points3D files,
            or they cannot be parsed (:func:`..database.from_reconstruction.read_reconstruction`).
    """
    return read_reconstruction(Path(path))


def _flush_c_stdio() -> None:
    """Flush C stdio buffers (Filament logs through them)."""
    with contextlib.suppress(OSError, AttributeError, TypeError):
        ctypes.CDLL(None).fflush(None)


@contextlib.contextmanager
def _native_stdout_to_stderr() -> Iterator[None]:
    """Send what native code writes to file descriptor 1 to 2 (Filament's start-up log)."""
    try:
        sys.stdout.flush()
        saved = os.dup(1)
        os.dup2(2, 1)
    except (OSError, ValueError, AttributeError):
        yield
        return
    try:
        yield
    finally:
        _flush_c_stdio()
        os.dup2(saved, 1)
        os.close(saved)


@functools.cache
def offscreen_problem() -> str | None:
    """None when open3d can render offscreen here, else a one-line reason.

    Creating a renderer without a working (Vulkan/EGL) driver aborts the process, so
    the check runs in a child Python process (about 1-2 s, once per process).
    """
    try:
        _open3d()
    except CalibrationError as exc:
        return str(exc)
    try:
        result = subprocess.run(
            [sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"open3d offscreen renderer check failed ({type(exc).__name__})"
    if result.returncode != 0:
        status = result.returncode
        how = f"killed by signal {-status}" if status < 0 else f"exit status {status}"
        return (
            f"open3d cannot create an offscreen renderer ({how}); "
            f"install the Debian packages {DEBIAN_PACKAGES}"
        )
    return None


def _material(geometry: open3d.geometry.Geometry, point_size: float = 3.0):
    """Unlit material: ``point_size`` px points for point clouds, 2 px lines for line sets."""
    o3d = _open3d()
    material = o3d.visualization.rendering.MaterialRecord()
    material.shader = "defaultUnlit"
    material.point_size = float(point_size)
    if isinstance(geometry, o3d.geometry.LineSet):
        material.shader = "unlitLine"
        material.line_width = 2.0
    elif isinstance(geometry, o3d.geometry.TriangleMesh):
        material.shader = "defaultLit"
    return material


def _caption_layout(lines: Sequence[str], width: int) -> tuple[float, int]:
    """(font scale, line height in px) for ``lines`` across an image ``width`` px wide.

    The scale is :data:`CAPTION_SCALE_PER_WIDTH` of the width, smaller where the
    longest line would not fit.
    """
    scale = CAPTION_SCALE_PER_WIDTH * width
    widest = max(
        (cv2.getTextSize(t, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] for t in lines), default=0
    )
    if widest > 0.96 * width:
        scale *= 0.96 * width / widest
    return scale, int(np.ceil(32 * scale / 0.6))


def caption_band(lines: Sequence[str], width: int) -> np.ndarray:
    """A white (h, width, 3) uint8 RGB band with ``lines`` in dark grey, one per row."""
    if not lines:
        return np.zeros((0, width, 3), np.uint8)
    scale, line_height = _caption_layout(lines, width)
    band = np.full((line_height * len(lines) + line_height // 2, width, 3), 255, np.uint8)
    thickness = max(1, round(2 * scale))
    for k, text in enumerate(lines):
        origin = (int(0.02 * width), line_height * (k + 1))
        cv2.putText(
            band,
            text,
            origin,
            cv2.FONT_HERSHEY_SIMPLEX,
            scale,
            (40, 40, 40),
            thickness,
            cv2.LINE_AA,
        )
    return band


def render_png(
    geometries: Sequence[open3d.geometry.Geometry],
    path: Path,
    width: int = 1280,
    height: int = 960,
    caption: Sequence[str] = (),
) -> Path:
    """Render ``geometries`` offscreen (white background) to the PNG ``path``.

    The virtual camera is placed by :func:`view_for`; points are drawn
    :data:`POINT_SIZE_PER_HEIGHT` of the height wide (at least 3 px). ``caption`` lines
    go in a white band at the top (:func:`caption_band`); the view fills the rest of
    the ``width`` x ``height`` image. Takes about 1-2 s on a CPU (plus the one-off
    :func:`offscreen_problem` check).

    Raises:
        CalibrationError: offscreen rendering is impossible here (the message names
            the Debian packages to install) or the image cannot be written.
    """
    problem = offscreen_problem()
    if problem is not None:
        raise CalibrationError(problem)
    o3d = _open3d()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    band = caption_band(list(caption), width)
    view_height = max(height - band.shape[0], height // 2)
    band = band[: height - view_height]
    centre, eye, up = view_for(geometries, width, view_height)
    point_size = max(3.0, POINT_SIZE_PER_HEIGHT * height)

    verbosity = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # GLFW fallback
    try:
        with _native_stdout_to_stderr():
            renderer = o3d.visualization.rendering.OffscreenRenderer(width, view_height)
    finally:
        o3d.utility.set_verbosity_level(verbosity)
    try:
        renderer.scene.set_background([1.0, 1.0, 1.0, 1.0])
        # No tone mapping / colour grading: exact white background and point colours.
        renderer.scene.view.set_post_processing(False)
        for k, geometry in enumerate(geometries):
            renderer.scene.add_geometry(f"geometry{k}", geometry, _material(geometry, point_size))
        renderer.setup_camera(VERTICAL_FOV_DEG, centre, eye, up)
        view = np.asarray(renderer.render_to_image())[..., :3]
    finally:
        del renderer
    image = np.vstack([band, view])
    _write_png(path, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return path


def _write_png(path: Path, image: np.ndarray) -> None:
    """``image`` (BGR) as a PNG at ``path``; a FIFO, pipe or device is written without
    blocking for good (:func:`..common.streams.write_special`; OpenCV's own open of a
    FIFO without a reader waited forever)."""
    from ..common.streams import descriptor_of, is_stream, write_special

    if descriptor_of(path) is not None or is_stream(path):
        ok, encoded = cv2.imencode(".png", image)
        if not ok:
            raise CalibrationError(f"cannot encode the image {path}")
        try:
            write_special(path, encoded.tobytes())
        except OSError as exc:
            raise CalibrationError(
                f"cannot write the image {path}: {exc.strerror or exc}"
            ) from None
        return
    try:
        written = cv2.imwrite(str(path), image)
    except cv2.error:
        written = False
    if not written:
        raise CalibrationError(f"cannot write the image {path}")


def run_report(model: Path) -> RunReportFile | None:
    """The checked ``report.json`` of the ``run`` whose workspace holds ``model``
    (``sparse/0``), or None (none there, or not usable: see
    :func:`.report_reader.read_run_report` for why)."""
    return read_run_report(Path(model))[0]


def _intrinsics_text(values: Sequence[float], std: dict | None = None) -> str:
    """``fx 2759.4 ± 1.8, fy …, cx …, cy … px`` (no ``±`` where the std is unknown)."""
    parts = []
    for name, value in zip(("fx", "fy", "cx", "cy"), values, strict=True):
        spread = None if std is None else std.get(name)
        parts.append(f"{name} {value:.1f}" + ("" if spread is None else f" \u00b1 {spread:.1f}"))
    return ", ".join(parts) + " px"


def model_caption(
    reconstruction: pycolmap.Reconstruction,
    report: RunReportFile | dict | None = None,
    max_cameras: int = 3,
) -> list[str]:
    """Caption lines: the registered images and points, then each camera's K.

    With a ``run`` report that matches the model (same number of registered images and
    its cameras in the model) each camera's line is TrifocalCalib's estimate ± std;
    otherwise the model's own K per physical camera (ids grouped as
    :func:`..database.from_reconstruction.grouping_cameras` does, mean K), without std.
    ``report`` is a checked report (:func:`.report_reader.read_run_report`) or a parsed
    ``report.json`` (checked here; one that fails a check is not used). At most
    ``max_cameras`` camera lines, then how many more there are.
    """
    if isinstance(report, dict):
        try:
            report = parse_report(report)
        except ReportProblem:
            report = None
    registered = reconstruction.num_reg_images()
    lines = [
        f"{registered} of {reconstruction.num_images()} images registered, "
        f"{reconstruction.num_points3D()} points"
    ]
    cameras: list[str] = []
    usable = (
        report is not None
        and report.num_registered_images == registered
        and all(reconstruction.exists_camera(c.camera_id) for c in report.cameras)
    )
    if usable and report is not None:
        for camera in report.cameras:
            images = "?" if camera.num_registered_images is None else camera.num_registered_images
            cameras.append(
                f"camera {camera.camera_id} ({images} images), "
                f"TrifocalCalib: {_intrinsics_text(camera.trifocal, camera.std)}"
            )
    else:
        image_count: dict[int, int] = {}
        for image_id in reconstruction.reg_image_ids():
            camera_id = int(reconstruction.image(image_id).camera_id)
            image_count[camera_id] = image_count.get(camera_id, 0) + 1
        infos = {c: CameraInfo.from_pycolmap(reconstruction.camera(c)) for c in image_count}
        groups: dict[bytes, list[int]] = {}
        for camera_id, info in sorted(grouping_cameras(infos).items()):
            groups.setdefault(info.params.tobytes(), []).append(camera_id)
        for ids in groups.values():
            first = infos[ids[0]]
            mean = np.mean([infos[c].intrinsics for c in ids], axis=0)
            who = f"camera {ids[0]}" if len(ids) == 1 else f"cameras {ids[0]}.. ({len(ids)} ids)"
            cameras.append(
                f"{who} {first.model} {first.width}x{first.height} "
                f"({sum(image_count[c] for c in ids)} images), model: {_intrinsics_text(mean)}"
            )
    if len(cameras) > max_cameras:
        cameras = [*cameras[:max_cameras], f"... and {len(cameras) - max_cameras} more cameras"]
    return lines + cameras


def show(
    model: pycolmap.Reconstruction | Path | str,
    png: Path | str | None = None,
    *,
    width: int = 1280,
    height: int = 960,
    warn: Callable[[str], None] | None = None,
) -> Path | None:
    """Show a COLMAP model: rendered to ``png``, or in a window.

    Args:
        model: a ``pycolmap.Reconstruction`` in memory, or a COLMAP sparse folder
            (``sparse/0``, binary or text).
        png: render offscreen (with its caption, :func:`model_caption`: for a folder of a
            ``run`` workspace TrifocalCalib's estimate from its ``report.json``, else the
            model's own K) to this PNG and return its path. None: an interactive Open3D
            window where a display exists (``DISPLAY`` or ``WAYLAND_DISPLAY`` set),
            returning None once it is closed.
        width, height: size of the PNG in pixels.
        warn: told why a ``report.json`` beside the model is not used (a FIFO, too
            large, not JSON, a field of the wrong type); default: the log.

    Raises:
        CalibrationError: bad model folder, Open3D not installed (the extra ``viz``) or
            unable to render here, no display (and no ``png``).
    """
    if isinstance(model, pycolmap.Reconstruction):
        reconstruction, report, title = model, None, "reconstruction"
    elif not isinstance(model, (str, Path)):
        raise CalibrationError(
            f"show takes a pycolmap.Reconstruction or a model folder, not {type(model).__name__}"
        )
    else:
        reconstruction = load_model(Path(model))
        title = str(model)
        report, problem = read_run_report(Path(model))
        if problem is not None:
            (warn or logger.warning)(f"{problem}; the caption shows the model's own intrinsics")
    geometries = scene_geometry(reconstruction)
    if png is not None:
        caption = model_caption(reconstruction, report)
        return render_png(geometries, Path(png), width=width, height=height, caption=caption)
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise CalibrationError("no display: use --png OUT")
    from .viewer import display_problem

    problem = display_problem()  # a display nobody serves: Open3D would run for ever
    if problem is not None:
        raise CalibrationError(f"{problem}: use --png OUT")
    _open3d().visualization.draw_geometries(geometries, window_name=f"colmap-trifocal: {title}")
    return None
