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
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..database.from_reconstruction import read_reconstruction

if TYPE_CHECKING:
    import open3d

#: Debian packages open3d needs to import (libusb) and to render offscreen.
DEBIAN_PACKAGES = "libegl1 libgl1-mesa-dri libvulkan1 mesa-vulkan-drivers libusb-1.0-0"

#: Default frustum depth as a fraction of the scene extent (see :func:`scene_extent`).
FRUSTUM_FRACTION = 0.05

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
    """The open3d module, or CalibrationError naming the Debian packages it needs."""
    try:
        import open3d
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


def _points(reconstruction: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) point positions (world units) and (n, 3) uint8 RGB colours."""
    points = list(reconstruction.points3D.values())
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    xyz = np.array([p.xyz for p in points], dtype=float)
    rgb = np.array([p.color for p in points], dtype=np.uint8)
    return xyz, rgb


def inlier_mask(xyz: np.ndarray, keep_quantile: float = KEEP_QUANTILE) -> np.ndarray:
    """(n,) bool: points within the ``keep_quantile`` distance from the per-axis median."""
    if len(xyz) == 0:
        return np.zeros(0, dtype=bool)
    distance = np.linalg.norm(xyz - np.median(xyz, axis=0), axis=1)
    return distance <= np.quantile(distance, keep_quantile)


def scene_extent(xyz: np.ndarray, centres: np.ndarray | None = None) -> float:
    """Robust scene size (world units): median distance of the points to their centroid.

    The centroid is the per-axis median, so a few far points move neither the centre
    nor the extent. With camera ``centres`` (m, 3) the extent is at least their median
    distance to that centroid, so frustums stay visible when the cameras are far from
    a compact scene. 0 without points and cameras.
    """
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    centres = np.zeros((0, 3)) if centres is None else np.asarray(centres, float).reshape(-1, 3)
    if len(xyz) == 0 and len(centres) == 0:
        return 0.0
    centroid = np.median(xyz if len(xyz) else centres, axis=0)
    extents = [np.median(np.linalg.norm(a - centroid, axis=1)) for a in (xyz, centres) if len(a)]
    return float(max(extents))


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
            (world units); None: :data:`FRUSTUM_FRACTION` of :func:`scene_extent` of
            the kept points and the camera centres.

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
    world_from_cam, centres = _poses(reconstruction, image_ids)
    if frustum_scale is None:
        extent = scene_extent(xyz[keep], centres)
        frustum_scale = FRUSTUM_FRACTION * extent if extent > 0 else 1.0
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
    """(n, 3) vertices of a point cloud / line set, else its bounding-box corners."""
    o3d = _open3d()
    if isinstance(geometry, o3d.geometry.PointCloud | o3d.geometry.LineSet):
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
    """(centre, eye, up) of a virtual camera seeing every vertex of ``geometries``.

    The camera looks at the bounding-box centre along the mean optical axis of the
    frustums (5-vertex LineSets, see the module docstring), i.e. from behind the
    cameras, raised by ``elevation_deg`` towards the mean image "up" direction. When
    the optical axes cancel out (cameras all around the scene), it looks from the
    mean camera centre towards the scene centre instead; without frustums along +z
    with −y up (a COLMAP camera at the origin). The distance is the smallest one
    that keeps every vertex inside the field of view, times ``margin``.
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


def _material(geometry: open3d.geometry.Geometry):
    """Unlit material: size-2 points for point clouds, 1.5 px lines for line sets."""
    o3d = _open3d()
    material = o3d.visualization.rendering.MaterialRecord()
    material.shader = "defaultUnlit"
    material.point_size = 2.0
    if isinstance(geometry, o3d.geometry.LineSet):
        material.shader = "unlitLine"
        material.line_width = 1.5
    elif isinstance(geometry, o3d.geometry.TriangleMesh):
        material.shader = "defaultLit"
    return material


def render_png(
    geometries: Sequence[open3d.geometry.Geometry],
    path: Path,
    width: int = 1280,
    height: int = 960,
) -> Path:
    """Render ``geometries`` offscreen (white background) to the PNG ``path``.

    The virtual camera is placed by :func:`view_for`. Takes about 1-2 s on a CPU
    (plus the one-off :func:`offscreen_problem` check).

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
    centre, eye, up = view_for(geometries, width, height)

    verbosity = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # GLFW fallback
    try:
        with _native_stdout_to_stderr():
            renderer = o3d.visualization.rendering.OffscreenRenderer(width, height)
    finally:
        o3d.utility.set_verbosity_level(verbosity)
    try:
        renderer.scene.set_background([1.0, 1.0, 1.0, 1.0])
        # No tone mapping / colour grading: exact white background and point colours.
        renderer.scene.view.set_post_processing(False)
        for k, geometry in enumerate(geometries):
            renderer.scene.add_geometry(f"geometry{k}", geometry, _material(geometry))
        renderer.setup_camera(VERTICAL_FOV_DEG, centre, eye, up)
        image = renderer.render_to_image()
    finally:
        del renderer
    if not o3d.io.write_image(str(path), image):
        raise CalibrationError(f"cannot write the image {path}")
    return path


def show(model: Path, png: Path | None = None) -> Path | None:
    """Show the model in ``model`` (a COLMAP sparse folder): to ``png`` or in a window.

    With ``png`` the view is rendered offscreen and its path returned. Without it an
    interactive open3d window opens when a display exists (``DISPLAY`` or
    ``WAYLAND_DISPLAY`` set) and None is returned after it is closed.

    Raises:
        CalibrationError: bad model folder, no display (and no ``png``), or offscreen
            rendering impossible.
    """
    geometries = scene_geometry(load_model(Path(model)))
    if png is not None:
        return render_png(geometries, Path(png))
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise CalibrationError("no display: use --png OUT")
    _open3d().visualization.draw_geometries(geometries, window_name=f"colmap-trifocal: {model}")
    return None
