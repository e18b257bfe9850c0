"""3D view of a COLMAP sparse model: coloured points and one camera frustum per image.

Conventions:

* poses are COLMAP's world-to-camera ``x_cam = R X + t``; the camera centre (the
  frustum apex) is ``C = −Rᵀ t`` in world units;
* COLMAP pixel convention: the centre of the top-left pixel is at (0.5, 0.5), so the
  image covers ``[0, w] × [0, h]`` and its corners are (0, 0), (w, 0), (w, h), (0, h);
* a frustum is an ``open3d.geometry.LineSet`` with 5 vertices — the apex, then the
  image corners in the order above, placed on the plane at depth ``frustum_scale``
  (world units, along the optical axis) — and 8 lines: 4 rays from the apex and the
  corner rectangle;
* colours are RGB in [0, 1].

The view frames the bulk of the points (per-axis percentiles :data:`FRAME_PERCENTILES`)
and every camera, so that a few far points (triangulated from nearly parallel rays) do
not shrink the model into a corner; frustums are drawn at a fraction of that framed
size. :func:`render_png` writes the caption (the calibrated K ± std and the registered
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
from ..common.extras import missing_extra
from ..common.log import logger
from ..database.cameras import CameraInfo
from ..database.from_reconstruction import grouping_cameras, read_reconstruction
from .report_reader import ReportProblem, RunReportFile, parse_report, read_run_report

if TYPE_CHECKING:
    import open3d

#: Debian packages open3d needs to import (libusb) and to render offscreen.
DEBIAN_PACKAGES = "libegl1 libgl1-mesa-dri libvulkan1 mesa-vulkan-drivers libusb-1.0-0"

#: Default frustum depth as a fraction of the framed scene's size (see :func:`scene_size`).
FRUSTUM_FRACTION = 0.03

#: Per-axis percentiles (%) of the points that the view frames and that set the scene size.
FRAME_PERCENTILES = (2.0, 98.0)

#: Rendered point diameter in pixels per pixel of image height (at least 3 px).
POINT_SIZE_PER_HEIGHT = 1.0 / 240.0

#: Caption text height in pixels per pixel of image width (OpenCV Hershey simplex).
CAPTION_SCALE_PER_WIDTH = 0.6 / 1280.0

#: Vertical field of view of the rendering camera, degrees.
VERTICAL_FOV_DEG = 50.0

#: Points farther from the scene centre than this quantile of the distances are dropped.
KEEP_QUANTILE = 0.99

#: Colormap anchors (blue → cyan → green → yellow → red) for registration order.
_COLORMAP = np.array(
    [[0.0, 0.0, 1.0], [0.0, 0.8, 1.0], [0.0, 0.8, 0.0], [1.0, 0.8, 0.0], [1.0, 0.0, 0.0]]
)

_PROBE = (
    "import open3d as o3d\n"
    "o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)\n"
    "o3d.visualization.rendering.OffscreenRenderer(16, 16).render_to_image()\n"
)


def _open3d():
    """The open3d module, or CalibrationError naming the extra (not installed) or the
    Debian packages it needs (installed, but it cannot load)."""
    try:
        import open3d
    except ModuleNotFoundError as exc:
        if exc.name != "open3d":
            raise CalibrationError(f"cannot import open3d ({exc})") from exc
        raise missing_extra("open3d", "drawing a model (show, run --png)") from exc
    except (ImportError, OSError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CalibrationError(
            f"cannot import open3d ({reason}); install the Debian packages {DEBIAN_PACKAGES}"
        ) from exc
    return open3d


def load_model(path: Path) -> pycolmap.Reconstruction:
    """Read a COLMAP sparse model folder (e.g. ``sparse/0``, ``.bin`` or ``.txt`` files).

    Raises:
        CalibrationError: the folder is missing, lacks cameras/images/points3D files,
            or they cannot be parsed (:func:`..database.from_reconstruction.read_reconstruction`).
    """
    return read_reconstruction(Path(path))


def registration_colors(count: int) -> np.ndarray:
    """(count, 3) RGB colours in [0, 1] from blue (first) through green to red (last)."""
    t = np.linspace(0.0, 1.0, count) if count > 1 else np.zeros(count)
    anchors = np.linspace(0.0, 1.0, len(_COLORMAP))
    return np.stack([np.interp(t, anchors, _COLORMAP[:, c]) for c in range(3)], axis=1)


#: The largest coordinate drawn (world units): points beyond are left out of the view,
#: a camera beyond is refused (1e300 overflowed the view's vectors).
MAX_COORDINATE = 1e12


def _points(reconstruction: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) point positions (world units) and (n, 3) uint8 RGB colours; points that are
    not finite or beyond :data:`MAX_COORDINATE` are left out."""
    points = list(reconstruction.points3D.values())
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    xyz = np.array([p.xyz for p in points], dtype=float)
    rgb = np.array([p.color for p in points], dtype=np.uint8)
    drawable = np.all(np.abs(xyz) <= MAX_COORDINATE, axis=1)  # NaN compares False
    return xyz[drawable], rgb[drawable]


def _check_drawable(
    reconstruction: pycolmap.Reconstruction, image_ids: Sequence[int], centres: np.ndarray
) -> None:
    """Refuse what no view can frame: a registered image's camera whose params are not
    finite, or a pose whose centre is not finite or beyond :data:`MAX_COORDINATE` (the
    view's vectors overflowed to NaN and failed with a TypeError)."""
    for k, image_id in enumerate(image_ids):
        camera_id = reconstruction.image(image_id).camera_id
        params = np.asarray(reconstruction.cameras[camera_id].params, dtype=float)
        if not np.all(np.isfinite(params)):
            shown = ", ".join(f"{p:g}" for p in params)
            raise CalibrationError(
                f"cannot draw camera {camera_id} of the model: its params ({shown}) are not finite"
            )
        if not np.all(np.abs(centres[k]) <= MAX_COORDINATE):
            raise CalibrationError(
                f"cannot draw image {image_id} of the model: its pose is not finite or lies "
                f"beyond {MAX_COORDINATE:g}"
            )


def inlier_mask(xyz: np.ndarray, keep_quantile: float = KEEP_QUANTILE) -> np.ndarray:
    """(n,) bool: points within the ``keep_quantile`` distance from the per-axis median."""
    if len(xyz) == 0:
        return np.zeros(0, dtype=bool)
    distance = np.linalg.norm(xyz - np.median(xyz, axis=0), axis=1)
    return distance <= np.quantile(distance, keep_quantile)


def robust_bounds(
    xyz: np.ndarray, percentiles: tuple[float, float] = FRAME_PERCENTILES
) -> tuple[np.ndarray, np.ndarray]:
    """(3,) lower and (3,) upper per-axis percentiles of the points (world units).

    Raises ValueError without points.
    """
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    if len(xyz) == 0:
        raise ValueError("no points")
    low, high = np.percentile(xyz, percentiles, axis=0)
    return low, high


def framed(xyz: np.ndarray, percentiles: tuple[float, float] = FRAME_PERCENTILES) -> np.ndarray:
    """(n,) bool: the points inside their per-axis percentile box (the bulk of the scene)."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    if len(xyz) == 0:
        return np.zeros(0, dtype=bool)
    low, high = robust_bounds(xyz, percentiles)
    return np.all((xyz >= low) & (xyz <= high), axis=1)


def scene_size(xyz: np.ndarray, centres: np.ndarray | None = None) -> float:
    """Robust scene size (world units): the diagonal of the box that holds the bulk of the
    points (:func:`robust_bounds`) and every camera centre (m, 3); 0 without either."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    centres = np.zeros((0, 3)) if centres is None else np.asarray(centres, float).reshape(-1, 3)
    corners = [centres]
    if len(xyz):
        corners.extend(robust_bounds(xyz))
    stacked = np.vstack([c.reshape(-1, 3) for c in corners])
    if len(stacked) == 0:
        return 0.0
    return float(np.linalg.norm(stacked.max(axis=0) - stacked.min(axis=0)))


def _poses(
    reconstruction: pycolmap.Reconstruction, image_ids: Sequence[int]
) -> tuple[np.ndarray, np.ndarray]:
    """(m, 3, 3) world-from-camera rotations Rᵀ and (m, 3) camera centres −Rᵀt."""
    rotations = np.zeros((len(image_ids), 3, 3))
    centres = np.zeros((len(image_ids), 3))
    for k, image_id in enumerate(image_ids):
        cam_from_world = reconstruction.image(image_id).cam_from_world()  # a method in 4.2.1
        rotation = np.asarray(cam_from_world.rotation.matrix())
        rotations[k] = rotation.T
        centres[k] = -rotation.T @ np.asarray(cam_from_world.translation)
    return rotations, centres


def image_corner_rays(camera: pycolmap.Camera) -> np.ndarray:
    """(4, 3) camera-frame rays (z = 1) through the corners (0,0), (w,0), (w,h), (0,h).

    Unprojected with the camera model (distortion included); where that fails (NaN,
    e.g. strong barrel distortion beyond its invertible range) the pinhole part
    ``K⁻¹`` is used instead.
    """
    w, h = float(camera.width), float(camera.height)
    corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    normalized = np.asarray(camera.cam_from_img(corners), dtype=float)
    if not np.all(np.isfinite(normalized)):
        k_inv = np.linalg.inv(np.asarray(camera.calibration_matrix()))
        normalized = (np.c_[corners, np.ones(4)] @ k_inv.T)[:, :2]
    return np.c_[normalized, np.ones(4)]


def frustum(
    centre: np.ndarray,
    world_from_cam: np.ndarray,
    rays: np.ndarray,
    scale: float,
    color: np.ndarray,
) -> open3d.geometry.LineSet:
    """A camera frustum LineSet: apex ``centre``, corners ``centre + Rᵀ (scale · ray)``.

    Args:
        centre: (3,) camera centre, world units.
        world_from_cam: (3, 3) rotation Rᵀ taking camera-frame directions to world.
        rays: (4, 3) camera-frame corner rays with z = 1 (see :func:`image_corner_rays`).
        scale: depth of the drawn image plane along the optical axis, world units.
        color: (3,) RGB in [0, 1] of every line.
    """
    o3d = _open3d()
    vertices = np.vstack([centre, centre + (scale * rays) @ world_from_cam.T])
    lines = np.array([[0, 1], [0, 2], [0, 3], [0, 4], [1, 2], [2, 3], [3, 4], [4, 1]])
    line_set = o3d.geometry.LineSet(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector2iVector(lines)
    )
    line_set.colors = o3d.utility.Vector3dVector(np.tile(np.asarray(color, float), (8, 1)))
    return line_set


def scene_geometry(
    reconstruction: pycolmap.Reconstruction, frustum_scale: float | None = None
) -> list[open3d.geometry.Geometry]:
    """The model as open3d geometry: ``[PointCloud, LineSet per registered image...]``.

    Args:
        reconstruction: a pycolmap reconstruction.
        frustum_scale: depth of each frustum's image plane along its optical axis
            (world units); None: :data:`FRUSTUM_FRACTION` of :func:`scene_size` of the
            points and the camera centres.

    Returns:
        The sparse points (far outliers beyond the :data:`KEEP_QUANTILE` distance
        from the centre dropped) with their RGB colours (0-255 mapped to 0-1), then
        one frustum per registered image in increasing image-id order, coloured by
        that order from blue to red (:func:`registration_colors`).
    """
    o3d = _open3d()
    xyz, rgb = _points(reconstruction)
    keep = inlier_mask(xyz)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz[keep]))
    cloud.colors = o3d.utility.Vector3dVector(rgb[keep].astype(float) / 255.0)

    image_ids = sorted(reconstruction.reg_image_ids())
    with np.errstate(all="ignore"):  # a pose at 1e300 is refused below, not warned about
        world_from_cam, centres = _poses(reconstruction, image_ids)
    _check_drawable(reconstruction, image_ids, centres)
    if frustum_scale is None:
        size = scene_size(xyz[keep], centres)
        frustum_scale = FRUSTUM_FRACTION * size if size > 0 else 1.0
    colors = registration_colors(len(image_ids))
    frustums = [
        frustum(
            centres[k],
            world_from_cam[k],
            image_corner_rays(reconstruction.cameras[reconstruction.image(image_id).camera_id]),
            frustum_scale,
            colors[k],
        )
        for k, image_id in enumerate(image_ids)
    ]
    return [cloud, *frustums]


def _unit(vector: np.ndarray) -> np.ndarray | None:
    """``vector`` normalised, or None when its norm is (close to) zero."""
    norm = float(np.linalg.norm(vector))
    return vector / norm if norm > 1e-9 else None


def _vertices(geometry: open3d.geometry.Geometry) -> np.ndarray:
    """(n, 3) vertices to frame: a point cloud's bulk (:func:`framed`), a line set's
    vertices, a mesh's vertices, else the bounding-box corners."""
    o3d = _open3d()
    if isinstance(geometry, o3d.geometry.PointCloud):
        points = np.asarray(geometry.points)
        return points[framed(points)]
    if isinstance(geometry, o3d.geometry.LineSet):
        return np.asarray(geometry.points)
    if isinstance(geometry, o3d.geometry.TriangleMesh):
        return np.asarray(geometry.vertices)
    box = geometry.get_axis_aligned_bounding_box()  # type: ignore[attr-defined]
    return np.asarray(box.get_box_points())


def view_for(
    geometries: Sequence[open3d.geometry.Geometry],
    width: int,
    height: int,
    vertical_fov_deg: float = VERTICAL_FOV_DEG,
    elevation_deg: float = 25.0,
    margin: float = 1.08,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centre, eye, up) of a virtual camera seeing ``geometries``: every frustum and line
    vertex, and the bulk of each point cloud (:func:`framed`; far points may fall outside).

    The camera looks at the bounding-box centre along the mean optical axis of the
    frustums (5-vertex LineSets, see the module docstring), i.e. from behind the
    cameras, raised by ``elevation_deg`` towards the mean image "up" direction. When
    the optical axes cancel out (cameras all around the scene), it looks from the
    mean camera centre towards the scene centre instead; without frustums along +z
    with −y up (a COLMAP camera at the origin). The distance is the smallest one
    that keeps those vertices inside the field of view, times ``margin``.
    """
    vertices = [_vertices(g) for g in geometries]
    points = np.vstack([v for v in vertices if len(v)] or [np.zeros((1, 3))])
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))

    o3d = _open3d()
    frustums = np.array(
        [
            np.asarray(g.points)
            for g in geometries
            if isinstance(g, o3d.geometry.LineSet) and len(g.points) == 5
        ]
    ).reshape(-1, 5, 3)
    forward = up = None
    if len(frustums):
        axes = frustums[:, 1:].mean(axis=1) - frustums[:, 0]  # optical axes
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        image_up = 0.5 * (frustums[:, 1] + frustums[:, 2] - frustums[:, 3] - frustums[:, 4])
        up = _unit(image_up.sum(axis=0))
        mean_axis = axes.mean(axis=0)
        if np.linalg.norm(mean_axis) > 0.3:
            forward = _unit(mean_axis)
        else:
            forward = _unit(centre - frustums[:, 0].mean(axis=0))
        forward = forward if forward is not None else axes[0]
    if forward is None:
        forward = np.array([0.0, 0.0, 1.0])
    if up is None:
        up = np.array([0.0, -1.0, 0.0])
    up = _unit(up - (up @ forward) * forward)
    if up is None:  # image up parallel to the view direction: any perpendicular
        up = _unit(np.cross(forward, np.eye(3)[np.argmin(np.abs(forward))]))

    elevation = np.radians(elevation_deg)
    forward, up = (
        np.cos(elevation) * forward - np.sin(elevation) * up,
        np.sin(elevation) * forward + np.cos(elevation) * up,
    )
    right = np.cross(forward, up)

    # Smallest distance D with |a·up| ≤ tan(fov_v/2)(D + a·f) (and the same for right).
    offsets = points - centre
    depth = offsets @ forward
    tan_v = np.tan(np.radians(vertical_fov_deg) / 2)
    tan_h = tan_v * width / height
    needed = np.maximum(np.abs(offsets @ up) / tan_v, np.abs(offsets @ right) / tan_h) - depth
    radius = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) / 2
    distance = max(margin * float(needed.max()), 1e-3 * max(radius, 1e-6))
    return centre, centre - distance * forward, up


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
