"""Camera intrinsics as stored by COLMAP, and the pinhole view of them.

Conventions
-----------
* Pixel coordinates follow COLMAP: ``x`` to the right, ``y`` down, and the
  *centre* of the top-left pixel is at ``(0.5, 0.5)`` (so the image spans
  ``[0, width] x [0, height]``). The principal point ``(cx, cy)`` is given in the
  same convention; the image centre is ``(width / 2, height / 2)``.
* Focal lengths ``fx``, ``fy`` and the principal point are in pixels.
* ``params`` are COLMAP's parameter vectors exactly as stored, e.g.
  ``SIMPLE_RADIAL = (f, cx, cy, k)``, ``OPENCV = (fx, fy, cx, cy, k1, k2, p1, p2)``.
  The positions of focal lengths and principal point are taken from pycolmap
  (``focal_length_idxs()`` / ``principal_point_idxs()``), not hard-coded.
* "Normalised" coordinates are undistorted image-plane coordinates at depth 1
  (pycolmap's ``cam_from_img``), i.e. ``K^-1 [x, y, 1]^T`` for a pinhole camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
import pycolmap

from ..common.errors import CalibrationError

SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
SINGLE_FOCAL_MODELS = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


@dataclass(frozen=True)
class _Layout:
    """Where a camera model keeps its parameters (indices into ``params``)."""

    focal: tuple[int, ...]
    principal_point: tuple[int, ...]
    extra: tuple[int, ...]
    num_params: int
    names: tuple[str, ...]  # every parameter's name, as pycolmap's ``params_info``


@cache
def _layout(model: str) -> _Layout:
    """Parameter layout of a COLMAP camera model, queried from pycolmap."""
    if model not in pycolmap.CameraModelId.__members__ or model == "INVALID":
        raise ValueError(f"unknown COLMAP camera model: {model!r}")
    cam = pycolmap.Camera.create_from_model_name(0, model, 1.0, 2, 2)
    return _Layout(
        focal=tuple(cam.focal_length_idxs()),
        principal_point=tuple(cam.principal_point_idxs()),
        extra=tuple(cam.extra_params_idxs()),
        num_params=len(cam.params),
        names=tuple(name.strip() for name in cam.params_info.split(",")),
    )


@dataclass(frozen=True, eq=False)
class CameraInfo:
    """One COLMAP camera.

    Attributes:
        camera_id: COLMAP camera id.
        model: COLMAP model name, e.g. ``"SIMPLE_RADIAL"``.
        width, height: image size in pixels.
        params: COLMAP parameter vector exactly as stored (float64, read-only copy).
        has_prior_focal_length: COLMAP's ``prior_focal_length`` flag: the focal length
            came from the image's EXIF data (or the user), not from the size-based guess
            f = 1.2 · max(width, height).
    """

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray
    has_prior_focal_length: bool = False

    def __post_init__(self) -> None:
        layout = _layout(self.model)
        params = np.array(self.params, dtype=np.float64).reshape(-1)
        if params.size != layout.num_params:
            raise ValueError(
                f"camera {self.camera_id}: model {self.model} has {layout.num_params} params, "
                f"got {params.size}"
            )
        params.setflags(write=False)
        object.__setattr__(self, "params", params)
        object.__setattr__(self, "camera_id", int(self.camera_id))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "has_prior_focal_length", bool(self.has_prior_focal_length))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraInfo):
            return NotImplemented
        return (self.camera_id, self.model, self.width, self.height) == (
            other.camera_id,
            other.model,
            other.width,
            other.height,
        ) and np.array_equal(self.params, other.params)

    @property
    def single_focal(self) -> bool:
        """True if the model has one focal length ``f`` (``fx = fy = f``)."""
        return len(_layout(self.model).focal) == 1

    @property
    def intrinsics(self) -> np.ndarray:
        """``(fx, fy, cx, cy)`` in pixels, shape (4,); ``fx = fy = f`` for single-focal models."""
        layout = _layout(self.model)
        focal = self.params[list(layout.focal)]
        fx, fy = (focal[0], focal[0]) if focal.size == 1 else (focal[0], focal[1])
        cx, cy = self.params[list(layout.principal_point)]
        return np.array([fx, fy, cx, cy], dtype=np.float64)

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - standard name of the calibration matrix
        """Pinhole calibration matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (pixels)."""
        fx, fy, cx, cy = self.intrinsics
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> np.ndarray:
        """The model's extra (distortion) parameters, shape (k,); empty for pinhole models."""
        return self.params[list(_layout(self.model).extra)].copy()

    @property
    def distortion_names(self) -> tuple[str, ...]:
        """The distortion parameters' names in COLMAP's order, e.g. ``("k1", "k2")``."""
        layout = _layout(self.model)
        return tuple(layout.names[index] for index in layout.extra)

    @property
    def is_undistorted(self) -> bool:
        """True if the model has no distortion parameters or all of them are exactly 0."""
        return not np.any(self.distortion)

    def with_intrinsics(self, fx: float, fy: float, cx: float, cy: float) -> CameraInfo:
        """A copy with focal lengths and principal point replaced (pixels).

        Distortion parameters are kept. For single-focal models ``f = (fx + fy) / 2``.
        """
        layout = _layout(self.model)
        params = self.params.copy()
        if len(layout.focal) == 1:
            params[layout.focal[0]] = 0.5 * (float(fx) + float(fy))
        else:
            params[list(layout.focal)] = (fx, fy)
        params[list(layout.principal_point)] = (cx, cy)
        return CameraInfo(
            self.camera_id, self.model, self.width, self.height, params, self.has_prior_focal_length
        )

    @classmethod
    def blank(cls, model: str, camera_id: int = 1) -> CameraInfo:
        """A 1x1 camera of ``model`` with every parameter 0 (its layout, e.g. how many
        distortion parameters the model has)."""
        count = len(pycolmap.Camera.create_from_model_name(camera_id, model, 1.0, 1, 1).params)
        return cls(camera_id, model, 1, 1, np.zeros(count))

    @classmethod
    def of_model(
        cls,
        camera_id: int,
        model: str,
        width: int,
        height: int,
        intrinsics: Sequence[float] | np.ndarray,
        distortion: Sequence[float] | np.ndarray | None = None,
        *,
        has_prior_focal_length: bool = False,
    ) -> CameraInfo:
        """A ``width`` x ``height`` camera of ``model`` at ``intrinsics`` (fx, fy, cx, cy;
        pixels, :meth:`with_intrinsics`) with ``distortion`` (COLMAP's order; default 0)."""
        camera = cls(
            camera_id, model, width, height, cls.blank(model).params, has_prior_focal_length
        )
        if distortion is not None:
            camera = camera.with_distortion(distortion)
        fx, fy, cx, cy = map(float, intrinsics)
        return camera.with_intrinsics(fx, fy, cx, cy)

    def with_distortion(self, distortion: Sequence[float] | np.ndarray) -> CameraInfo:
        """A copy with the model's extra (distortion) parameters replaced, COLMAP's order."""
        params = self.params.copy()
        extra = list(_layout(self.model).extra)
        if len(extra) != len(distortion):
            raise ValueError(
                f"camera {self.camera_id}: model {self.model} has {len(extra)} distortion "
                f"parameter(s), got {len(distortion)}"
            )
        params[extra] = np.asarray(distortion, dtype=np.float64)
        return CameraInfo(
            self.camera_id, self.model, self.width, self.height, params, self.has_prior_focal_length
        )

    def to_pycolmap(self) -> pycolmap.Camera:
        """A new ``pycolmap.Camera`` with the same id, model, size, params and prior flag."""
        camera = pycolmap.Camera(
            camera_id=self.camera_id,
            model=self.model,
            width=self.width,
            height=self.height,
            params=self.params.tolist(),
        )
        camera.has_prior_focal_length = self.has_prior_focal_length
        return camera

    @classmethod
    def from_pycolmap(cls, cam: pycolmap.Camera) -> CameraInfo:
        """Build from a ``pycolmap.Camera`` (params copied as stored)."""
        return cls(
            camera_id=int(cam.camera_id),
            model=cam.model.name,
            width=int(cam.width),
            height=int(cam.height),
            params=np.asarray(cam.params, dtype=np.float64),
            has_prior_focal_length=bool(cam.has_prior_focal_length),
        )


def check_supported(camera: CameraInfo | pycolmap.Camera) -> None:
    """Raise :class:`CalibrationError` unless the camera model is in ``SUPPORTED_MODELS``."""
    if isinstance(camera, CameraInfo):
        model, camera_id = camera.model, camera.camera_id
    else:
        model, camera_id = camera.model.name, int(camera.camera_id)
    if model in SUPPORTED_MODELS:
        return
    kind = "fisheye camera model" if "FISHEYE" in model else "camera model"
    raise CalibrationError(
        f"camera {camera_id}: {kind} {model} is not supported "
        f"(supported models: {', '.join(SUPPORTED_MODELS)})"
    )


def undistort_to_pinhole(camera: CameraInfo, xy: np.ndarray) -> np.ndarray:
    """Map distorted pixel keypoints to where the camera's own pinhole ``K`` would see them.

    Args:
        camera: the camera; its distortion parameters are kept fixed at the stored values.
        xy: (n, 2) pixel coordinates (COLMAP convention, see module docstring).

    Returns:
        (n, 2) float64 pixel coordinates ``K * cam_from_img(xy)``. For pinhole models and
        cameras whose distortion parameters are all 0 this is a float64 copy of ``xy``.
        Points that pycolmap cannot undistort come back as NaN.

    Raises:
        CalibrationError: more than :data:`MAX_UNDONE_FRACTION` of the points cannot be
            undistorted: the stored distortion folds the image over (k1 = -3, -1000), and
            the keypoints left would fail deep in the tensor fit (SVD did not converge).
    """
    pts = np.array(xy, dtype=np.float64, copy=True).reshape(-1, 2)
    if camera.model in PINHOLE_MODELS or camera.is_undistorted or pts.shape[0] == 0:
        return pts
    pycolmap_camera = camera.to_pycolmap()
    with np.errstate(all="ignore"):
        normalised = np.asarray(pycolmap_camera.cam_from_img(np.ascontiguousarray(pts)))
        failed = int(np.count_nonzero(~_undone(pycolmap_camera, camera, pts, normalised)))
    if failed > MAX_UNDONE_FRACTION * len(pts):
        extra = np.asarray(pycolmap_camera.params)[list(pycolmap_camera.extra_params_idxs())]
        shown = ", ".join(f"{v:g}" for v in extra)
        raise CalibrationError(
            f"camera {camera.camera_id}: its stored distortion (k {shown}) cannot be undone at "
            f"{failed} of {len(pts)} keypoints of an image (the lens model folds over there); "
            "store a camera without that distortion, or give --prior"
        )
    fx, fy, cx, cy = camera.intrinsics
    return normalised * np.array([fx, fy]) + np.array([cx, cy])


def _undone(
    pycolmap_camera: pycolmap.Camera, camera: CameraInfo, pts: np.ndarray, normalised: np.ndarray
) -> np.ndarray:
    """(n,) bool: ``normalised`` really undoes the distortion at ``pts``: finite, mapped
    back to the pixel, on the pixel's side of the principal point, and on the rising
    branch of the lens model (a point a little further out maps further out). A lens
    model that folds over has other solutions that map back exactly (k1 = -1000)."""
    fx, fy, cx, cy = camera.intrinsics
    pinhole = (pts - np.array([cx, cy])) / np.array([fx, fy])
    rays = np.hstack([normalised, np.ones((len(pts), 1))])
    again = np.asarray(pycolmap_camera.img_from_cam(rays, check_cheirality=False))
    further = np.hstack([normalised * 1.001, np.ones((len(pts), 1))])
    beyond = np.asarray(pycolmap_camera.img_from_cam(further, check_cheirality=False))
    centre = np.array([cx, cy])
    back = np.linalg.norm(again - pts, axis=1) <= 1.0
    near_centre = np.linalg.norm(pinhole, axis=1) < 1e-3
    same_side = np.sum(normalised * pinhole, axis=1) > 0
    rising = np.linalg.norm(beyond - centre, axis=1) >= np.linalg.norm(again - centre, axis=1)
    return back & (near_centre | (same_side & rising))


#: The largest share of an image's keypoints the stored distortion may fail to undo (the
#: rest are NaN and dropped); beyond it the camera is refused.
MAX_UNDONE_FRACTION = 0.1
