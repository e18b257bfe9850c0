"""What a 3D view of a COLMAP sparse model shows: coloured points, one frustum per image,
and the virtual camera that frames them (open3d geometries; drawn by :mod:`.visualize`).

Conventions: poses are COLMAP's world-to-camera ``x_cam = R X + t`` (the camera centre,
the frustum apex, is ``C = −Rᵀ t``); the centre of the top-left pixel is at (0.5, 0.5),
so an image covers ``[0, w] × [0, h]``; a frustum is an ``open3d.geometry.LineSet`` of 5
vertices (the apex, then the corners (0, 0), (w, 0), (w, h), (0, h) at depth
``frustum_scale`` along the optical axis) and 8 lines; colours are RGB in [0, 1]. The
view frames the bulk of the points (per-axis percentiles :data:`FRAME_PERCENTILES`) and
every camera. open3d is imported lazily (:func:`_open3d`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..common.extras import missing_extra

if TYPE_CHECKING:
    import open3d

#: The largest coordinate drawn (world units): points beyond are left out of the view,
#: a camera beyond is refused (1e300 overflowed the view's vectors).
MAX_COORDINATE = 1e12


#: Debian packages open3d needs to import (libusb) and to render offscreen.
DEBIAN_PACKAGES = "libegl1 libgl1-mesa-dri libvulkan1 mesa-vulkan-drivers libusb-1.0-0"


#: Default frustum depth as a fraction of the framed scene's size (see :func:`scene_size`).
FRUSTUM_FRACTION = 0.03


#: Per-axis percentiles (%) of the points that the view frames and that set the scene size.
FRAME_PERCENTILES = (2.0, 98.0)


#: Vertical field of view of the rendering camera, degrees.
VERTICAL_FOV_DEG = 50.0


#: Points farther from the scene centre than this quantile of the distances are dropped.
KEEP_QUANTILE = 0.99


#: Colormap anchors (blue → cyan → green → yellow → red) for registration order.
_COLORMAP = np.array(
    [[0.0, 0.0, 1.0], [0.0, 0.8, 1.0], [0.0, 0.8, 0.0], [1.0, 0.8, 0.0], [1.0, 0.0, 0.0]]
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


def registration_colors(count: int) -> np.ndarray:
    """(count, 3) RGB colours in [0, 1] from blue (first) through green to red (last)."""
    t = np.linspace(0.0, 1.0, count) if count > 1 else np.zeros(count)
    anchors = np.linspace(0.0, 1.0, len(_COLORMAP))
    return np.stack([np.interp(t, anchors, _COLORMAP[:, c]) for c in range(3)], axis=1)


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
    forward, up = _view_direction(frustums, centre)

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


def _view_direction(frustums: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(forward, up) unit vectors of the view, before the elevation: the mean optical axis
    of the (n, 5, 3) ``frustums`` and their mean image "up" (from the mean camera centre
    towards ``centre`` where the axes cancel out); +z and −y without frustums."""
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
    assert up is not None  # forward is a unit vector: a perpendicular one exists
    return forward, up
