"""Per-group results of ``calibrate``: the estimate with the camera ids it covers, or a skip.

A group (:mod:`..database.camera_groups`) is one physical camera that may span many
camera ids. Its JSON object keeps the keys of the DESIGN.md contract (``camera_id``
is the group's first id) and adds ``camera_ids`` and ``start_source``. A group that
could not be calibrated is reported as ``{"camera_id", "camera_ids", "num_images",
"skipped": reason}`` with no estimate.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from ..database.cameras import CameraInfo
from .results import CameraCalibration

#: ``start_source`` values: where the starting intrinsics came from.
START_SOURCES = ("--prior", "default guess", "EXIF focal length", "stored camera")


@dataclass
class GroupCalibration(CameraCalibration):
    """A :class:`CameraCalibration` for a group of camera ids with shared intrinsics.

    Attributes:
        camera_ids: every camera id the estimate is for (sorted; ``camera_id`` is the first).
        start_source: where the prior came from (one of ``START_SOURCES``); with
            ``EXIF focal length`` the focal search still checks it.
        group_cameras: the group's cameras as stored (distortion kept per camera on write).
    """

    camera_ids: list[int] = field(default_factory=list)
    start_source: str = "stored camera"
    group_cameras: list[CameraInfo] = field(default_factory=list, repr=False)

    @classmethod
    def of(
        cls,
        result: CameraCalibration,
        cameras: list[CameraInfo],
        start_source: str,
    ) -> GroupCalibration:
        """Wrap one camera's result as the result of the group ``cameras``."""
        values = {f.name: getattr(result, f.name) for f in fields(CameraCalibration)}
        return cls(
            **values,
            camera_ids=[c.camera_id for c in cameras],
            start_source=start_source,
            group_cameras=list(cameras),
        )

    def updated_cameras(self) -> dict[int, CameraInfo]:
        """camera_id -> the stored camera with the estimate (:meth:`written_camera`)."""
        cameras = self.group_cameras or ([self.stored_camera] if self.stored_camera else [])
        return {c.camera_id: self.written_camera(c) for c in cameras}

    def to_json(self) -> dict:
        """The contract's object plus ``camera_ids`` and ``start_source``."""
        data = super().to_json()
        data.pop("group_cameras")
        return data


@dataclass
class SkippedGroup:
    """A group that was not calibrated, and why (e.g. ``"2 images"``)."""

    camera_ids: list[int]
    num_images: int
    reason: str

    @property
    def camera_id(self) -> int:
        """The group's first camera id."""
        return self.camera_ids[0]

    def to_json(self) -> dict:
        """``{"camera_id", "camera_ids", "num_images", "skipped"}``."""
        return {
            "camera_id": self.camera_id,
            "camera_ids": list(self.camera_ids),
            "num_images": self.num_images,
            "skipped": self.reason,
        }

    def message(self) -> str:
        """One line for stderr."""
        ids = self.camera_ids
        who = f"camera {ids[0]}" if len(ids) == 1 else f"camera group {ids[0]} ({len(ids)} ids)"
        return f"{who} skipped: {self.reason}"
