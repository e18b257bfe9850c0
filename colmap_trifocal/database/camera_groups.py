"""Group a database's camera ids into physical cameras (pure; no database access).

COLMAP's default feature extraction (``colmap feature_extractor``, the GUI, and
``pycolmap.extract_features`` with ``CameraMode.AUTO``) creates one camera per
image, every one with the same parameters when the images share a size and EXIF
data. Calibrating per camera id then has one image per camera and nothing to
calibrate from. A *group* is a set of camera ids calibrated with shared
intrinsics from the triplets among all their images.

Groupings (``--group``):

* ``camera``: one group per camera id (the database's own cameras).
* ``auto`` (default): camera ids with the same model, image size, stored parameters
  (bit for bit, distortion included) and prior-focal-length flag form one group.
  What COLMAP's database keeps of the EXIF data is the focal length: a camera with
  ``prior_focal_length`` set has its focal length from the EXIF focal length (mm)
  and the sensor width of the EXIF make/model, so equal parameters with the flag
  set mean the same lens setting on the same camera model. The make and model
  themselves are not in the database (nor is any other EXIF field), so two
  different camera bodies with equal sizes and parameters are grouped; use
  ``--group camera`` for such sets. A camera that is one of several sensors of a
  rig (COLMAP 3.12+ ``rigs`` table) is a physical camera of its own and is never
  merged with another camera id.
* ``all``: every image treated as one camera; the cameras must share model and
  image size (their parameters, e.g. distortion, may differ).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from ..common.errors import CalibrationError
from .cameras import CameraInfo

GROUPINGS = ("auto", "camera", "all")


@dataclass(frozen=True)
class CameraGroup:
    """Camera ids sharing one set of intrinsics, and their images.

    Attributes:
        camera_ids: sorted camera ids; the first one names the group (``camera_id``
            in the JSON report).
        image_ids: sorted ids of the images taken with these cameras.
    """

    camera_ids: tuple[int, ...]
    image_ids: tuple[int, ...]

    @property
    def camera_id(self) -> int:
        """The group's first (smallest) camera id."""
        return self.camera_ids[0]

    def describe(self) -> str:
        """``camera 3`` or ``cameras 1-11 (11 ids)``-style name for messages."""
        if len(self.camera_ids) == 1:
            return f"camera {self.camera_id}"
        return f"camera {self.camera_id} (group of cameras {format_ids(self.camera_ids)})"


def format_ids(ids: tuple[int, ...] | list[int]) -> str:
    """``1-3, 7`` for (1, 2, 3, 7) (sorted ids)."""
    parts: list[str] = []
    start = previous = ids[0]
    for i in (*ids[1:], None):
        if i is not None and i == previous + 1:
            previous = i
            continue
        parts.append(str(start) if start == previous else f"{start}-{previous}")
        if i is not None:
            start = previous = i
    return ", ".join(parts)


def _auto_key(camera: CameraInfo, *, rig_sensor: bool) -> tuple:
    """What two camera ids must share to be one physical camera under ``auto``."""
    own = camera.camera_id if rig_sensor else None
    return (
        camera.model,
        camera.width,
        camera.height,
        camera.params.tobytes(),
        camera.has_prior_focal_length,
        own,
    )


def group_cameras(
    cameras: Mapping[int, CameraInfo],
    image_camera: Mapping[int, int],
    grouping: str = "auto",
    rig_sensor_cameras: frozenset[int] | set[int] = frozenset(),
) -> list[CameraGroup]:
    """Group the camera ids that have images into physical cameras.

    Args:
        cameras: camera_id -> camera as stored.
        image_camera: image_id -> camera_id.
        grouping: ``auto``, ``camera`` or ``all`` (see the module docstring).
        rig_sensor_cameras: camera ids that are one of several sensors of a rig
            (never merged under ``auto``).

    Returns:
        The groups ordered by their first camera id. Cameras without images are left out.

    Raises:
        CalibrationError: unknown grouping, or ``all`` over different models or sizes.
    """
    if grouping not in GROUPINGS:
        raise CalibrationError(f"unknown grouping {grouping!r} (choose from {GROUPINGS})")
    images_of: dict[int, list[int]] = {}
    for image_id, camera_id in image_camera.items():
        images_of.setdefault(camera_id, []).append(image_id)
    used = sorted(c for c in images_of if c in cameras)
    if grouping == "camera":
        members = [[c] for c in used]
    elif grouping == "all":
        shapes = {(cameras[c].model, cameras[c].width, cameras[c].height) for c in used}
        if len(shapes) > 1:
            listed = ", ".join(f"{m} {w}x{h}" for m, w, h in sorted(shapes))
            raise CalibrationError(
                f"--group all needs one camera model and image size, the database has {listed}"
            )
        members = [used] if used else []
    else:
        by_key: dict[tuple, list[int]] = {}
        for c in used:
            by_key.setdefault(_auto_key(cameras[c], rig_sensor=c in rig_sensor_cameras), []).append(
                c
            )
        members = sorted(by_key.values())
    return [
        CameraGroup(
            camera_ids=tuple(ids),
            image_ids=tuple(sorted(i for c in ids for i in images_of[c])),
        )
        for ids in members
    ]
