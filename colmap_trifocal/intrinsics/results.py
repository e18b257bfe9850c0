"""What ``calibrate`` returns per camera, and its JSON form (DESIGN.md contract).

A camera is a physical camera: the camera ids of one group
(:mod:`..database.camera_groups`; COLMAP's default gives one id per image) share its
intrinsics. :class:`CameraCalibration` is its estimate, for every one of those ids;
:class:`SkippedGroup` a camera that was not calibrated, and why. Both have a
``to_json()``: the objects of the list ``calibrate --json`` writes.

Units: intrinsics and their standard deviations in pixels (COLMAP's pixel
convention, the centre of the top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..database.camera_targets import (
    group_ids_held,
    write_to_database_file,
    write_to_open_database,
)
from ..database.cameras import PINHOLE_MODELS, CameraInfo
from ..geometry.tensor_estimation import TripletTensor
from .camera_writing import apply_cameras
from .result_parts import (
    JSON_KEYS,
    NO_CAUSE,
    START_SOURCES,
    Diagnostics,
    Provenance,
    Timing,
    TripletReport,
    finite_or_none,
)
from .solve.parametrization import PARAMETER_NAMES

__all__ = [
    "PARAMETER_NAMES",
    "START_SOURCES",
    "JSON_KEYS",
    "CameraCalibration",
    "Diagnostics",
    "GroupCalibration",
    "Provenance",
    "SkippedGroup",
    "Timing",
    "TripletReport",
    "apply_cameras",
    "finite_or_none",
]


@dataclass(frozen=True)
class CameraCalibration:
    """The estimate for one camera, for every camera id of its group, as written by
    ``calibrate --json``: the camera's final result, after the constraint solve
    (:class:`intrinsics.solve.constraints.FallbackSolution`), the polish and the assessment.

    ``camera_id`` is the group's first id and ``camera_ids`` all of them (sorted);
    ``model`` is the COLMAP camera model. ``observable`` is True where the std is
    below 1 % of the parameter's scale (the focal length; half the image size for the
    principal point, see :mod:`intrinsics.solve.observability`). Other parameters are either
    still estimated (weakly determined, std up to 3 tolerances), tied (``std`` None) or held
    at the best evidence, the start or a decisive focal search, with that evidence's std
    (``source``, ``assumptions``). ``unconstrained_std`` is each parameter's std when all of
    the camera model's parameters are estimated (None where undetermined); for a value the
    lens route holds at the start, its estimate's through the lens.
    """

    camera_id: int
    model: str
    method: str
    fx: float
    fy: float
    cx: float
    cy: float
    std: dict[str, float | None]
    observable: dict[str, bool]
    num_triplets: int
    num_inlier_triplets: int
    prior: tuple[float, float, float, float]
    #: (fx, fy, cx, cy) the tensors were normalised with: the prior after the focal
    #: search (and after the re-estimation when the estimate moved far from it).
    start: tuple[float, float, float, float]
    #: What was assumed instead of estimated, e.g. ``["fy = fx"]``; empty normally.
    assumptions: list[str] = field(default_factory=list)
    #: Per parameter: estimated from the images (False: tied or held at the prior).
    estimated: dict[str, bool] = field(default_factory=lambda: dict.fromkeys(PARAMETER_NAMES, True))
    unconstrained_std: dict[str, float | None] = field(default_factory=dict)
    #: Per parameter, where its value comes from: ``trifocal`` (the constraints),
    #: ``tied`` (fy = fx), ``focal-search`` or ``prior`` (held at that estimate).
    source: dict[str, str] = field(default_factory=dict)
    #: The distortion parameters to store with the estimate (COLMAP's order), None to
    #: keep the stored ones.
    distortion: list[float] | None = None
    #: Every camera id the estimate is for (sorted; ``camera_id`` is the first);
    #: ``[camera_id]`` unless given.
    camera_ids: list[int] = field(default_factory=list)
    timing: Timing = field(default_factory=Timing)
    diagnostics: Diagnostics = field(default_factory=Diagnostics)
    provenance: Provenance = field(default_factory=Provenance)

    def __post_init__(self) -> None:
        if not self.camera_ids:
            object.__setattr__(self, "camera_ids", [self.camera_id])
        provenance = self.provenance
        if not provenance.group_cameras and provenance.stored_camera is not None:
            object.__setattr__(
                self, "provenance", replace(provenance, group_cameras=[provenance.stored_camera])
            )

    # The parts' values by their flat names, as the JSON and scripts know them.
    @property
    def seconds(self) -> float:
        return self.timing.seconds

    @property
    def stage_seconds(self) -> dict[str, float]:
        return self.timing.stage_seconds

    @property
    def tensor_starts(self) -> int:
        return self.timing.tensor_starts

    @property
    def focal_search(self) -> dict[str, Any] | None:
        return self.diagnostics.focal_search

    @property
    def diagnosis(self) -> str | None:
        return self.diagnostics.diagnosis

    @property
    def triplet_bundle(self) -> dict[str, Any] | None:
        return self.diagnostics.triplet_bundle

    @property
    def lens_distortion(self) -> dict[str, Any] | None:
        return self.diagnostics.lens_distortion

    @property
    def triplets(self) -> list[TripletReport]:
        return self.diagnostics.triplets

    @property
    def tensors(self) -> list[TripletTensor]:
        return self.diagnostics.tensors

    @property
    def stored_camera(self) -> CameraInfo | None:
        return self.provenance.stored_camera

    @property
    def group_cameras(self) -> list[CameraInfo]:
        return self.provenance.group_cameras

    @property
    def start_source(self) -> str:
        return self.provenance.start_source

    @property
    def reference(self) -> tuple[float, float, float, float] | None:
        return self.provenance.reference

    @property
    def intrinsics(self) -> np.ndarray:
        """(fx, fy, cx, cy) in pixels."""
        return np.array([self.fx, self.fy, self.cx, self.cy])

    @property
    def determined_anything(self) -> bool:
        """Whether the images determined at least one parameter (else: the prior)."""
        return any(self.estimated.values())

    @property
    def undetermined(self) -> list[str]:
        """Names of the parameters the images do not determine."""
        return [name for name in PARAMETER_NAMES if not self.observable[name]]

    def written_camera(self, stored: CameraInfo) -> CameraInfo:
        """``stored`` with the estimate (pixels) and, where the tracks showed distortion
        the stored camera did not hold (all its distortion parameters 0, the same
        model), the estimated distortion; otherwise its distortion kept."""
        camera = stored.with_intrinsics(self.fx, self.fy, self.cx, self.cy)
        same_model = self.stored_camera is not None and stored.model == self.stored_camera.model
        if self.distortion is not None and same_model and stored.is_undistorted:
            camera = camera.with_distortion(self.distortion)
        return camera

    def to_json(self) -> dict[str, Any]:
        """The JSON object of DESIGN.md (plus prior, start, assumptions, triplets): the
        keys of :data:`JSON_KEYS`, the parts' values flat."""
        data = {key: copy.deepcopy(getattr(self, key)) for key in JSON_KEYS}
        data["triplets"] = [asdict(report) for report in self.triplets]
        data["prior"] = dict(zip(PARAMETER_NAMES, self.prior, strict=True))
        data["start"] = dict(zip(PARAMETER_NAMES, self.start, strict=True))
        if self.reference is not None:
            data["reference"] = dict(zip(PARAMETER_NAMES, self.reference, strict=True))
        return data

    def updated_cameras(self) -> dict[int, CameraInfo]:
        """camera_id -> the stored camera with the estimate (:meth:`written_camera`), for
        every camera of the group.

        The one place where (fx, fy, cx, cy) become a camera model's params is
        :meth:`.CameraInfo.with_intrinsics` (single-focal models: f = (fx + fy) / 2).
        """
        if not self.group_cameras:
            raise CalibrationError(f"camera {self.camera_id}: the result has no stored camera")
        return {c.camera_id: self.written_camera(c) for c in self.group_cameras}

    def mapping_cameras(self) -> dict[int, CameraInfo]:
        """camera_id -> the camera to map the group with: :meth:`updated_cameras`, except
        on a camera that holds no distortion where the tracks determine a lens its model
        cannot hold: a model with one more radial term than the stored one
        (``lens_distortion["richer_model"]``, e.g. RADIAL behind COLMAP's default
        SIMPLE_RADIAL), or a lens behind a model without distortion parameters
        (``PINHOLE``: the lens stage's own fit, ``OPENCV``). That model, with the estimate
        and its fitted distortion.

        A mapper refining a one-term model on such a lens trades the focal length
        against k (docs/lenses.md), and a pinhole model cannot bend its tracks at all; in
        the lens's model it refines the lens it sees.
        """
        cameras = self.updated_cameras()
        lens = self.lens_distortion or {}
        model, params = lens.get("richer_model"), lens.get("richer_params")
        if model is None and _lens_behind_pinhole(self.model, lens):
            model, params = lens["camera_model"], lens["params"]
        # One group, one model (merged cameras share it): all undistorted, or none changes.
        if model is None or params is None or not all(c.is_undistorted for c in self.group_cameras):
            return cameras
        return {
            camera_id: CameraInfo.of_model(
                camera_id,
                model,
                camera.width,
                camera.height,
                self.intrinsics,
                params,
                has_prior_focal_length=camera.has_prior_focal_length,
            )
            for camera_id, camera in cameras.items()
        }

    @property
    def camera(self) -> pycolmap.Camera:
        """The estimate as a new ``pycolmap.Camera``.

        Model, image size and id are the stored camera's (the database's, or the
        reconstruction's it was calibrated from); focal length and principal point are
        the estimate (pixels); distortion params the stored ones, or the estimated ones
        where the stored camera held none and the tracks showed some
        (:attr:`distortion`).
        """
        cameras = self.updated_cameras()
        return cameras.get(self.camera_id, next(iter(cameras.values()))).to_pycolmap()

    @property
    def cameras(self) -> dict[int, pycolmap.Camera]:
        """camera_id -> a new ``pycolmap.Camera`` with the estimate, for every camera id of
        the group (each with its stored model, size and distortion, as :attr:`camera`)."""
        return {c: camera.to_pycolmap() for c, camera in self.updated_cameras().items()}

    def apply(self, target: pycolmap.Reconstruction | pycolmap.Database | Path | str) -> list[int]:
        """Write the estimate into the group's cameras of ``target``.

        ``target`` is a ``pycolmap.Reconstruction`` (changed in memory; poses and points
        are not touched: bundle-adjust or re-triangulate afterwards), an open
        ``pycolmap.Database`` (one transaction), or the path of a database file (a backup
        ``<name>.bak`` first, one transaction, read back, as ``calibrate --write``). It
        must hold every camera id of the group, or only the first (the group merged into
        one camera: :func:`colmap_trifocal.merge_cameras`, ``reconstruct``). Each camera
        keeps its own distortion unless it is 0 and the tracks showed some
        (:meth:`written_camera`); a reconstruction's camera of the model ``reconstruct``
        mapped the lens in (:meth:`mapping_cameras`) takes that camera.

        Returns:
            The camera ids written (sorted).

        Raises:
            CalibrationError: another kind of target (None, a ``pycolmap.Camera``, a
                folder, ...), a closed database, a camera id missing, or one of another
                model or image size (nothing is written then).
        """
        cameras, group = self.updated_cameras(), list(self.camera_ids)
        if isinstance(target, pycolmap.Reconstruction):
            ids = group_ids_held(group, set(target.cameras), "the reconstruction")
            mapped = self.mapping_cameras()
            return apply_cameras(
                target,
                {
                    c: mapped[c] if target.camera(c).model.name == mapped[c].model else cameras[c]
                    for c in ids
                },
            )
        if isinstance(target, pycolmap.Database):
            return write_to_open_database(target, cameras, group)
        if isinstance(target, (str, Path)):
            return write_to_database_file(Path(target), cameras, group)
        raise CalibrationError(
            "apply takes a pycolmap.Reconstruction, a pycolmap.Database or a database "
            f"path, not {type(target).__name__}"
        )

    def compare_with_model(self) -> str:
        """A table of the estimate (± std) beside the reconstruction's own intrinsics.

        Rows fx, fy, cx, cy in pixels and their difference in % of the model's value.

        Raises:
            CalibrationError: the result is not of a reconstruction (no ``reference``).
        """
        if self.reference is None:
            raise CalibrationError(
                f"camera {self.camera_id}: not calibrated from a reconstruction (no reference)"
            )
        lines = [f"{'':>4} {'estimate':>10} {'± std':>8} {'model':>10} {'diff %':>8}"]
        for name, value, model in zip(
            PARAMETER_NAMES, self.intrinsics, self.reference, strict=True
        ):
            std = self.std.get(name)
            shown = "-" if std is None else f"{std:.2f}"
            lines.append(
                f"{name:>4} {value:>10.2f} {shown:>8} {model:>10.2f} "
                f"{100.0 * (value / model - 1.0):>+8.3f}"
            )
        return "\n".join(lines)

    def warning(self) -> str | None:
        """One line naming the parameters that are not observable and what was done, or None.

        Tied or held parameters are named with their unconstrained std and the
        assumption made; weakly determined ones (estimated, std above tolerance)
        with their std.
        """
        fixed = [name for name in self.undetermined if not self.estimated[name]]
        weak = [name for name in self.undetermined if self.estimated[name]]
        if not fixed and not weak:
            return None
        parts = []
        if fixed:
            reasons = []
            for name in fixed:
                std = self.unconstrained_std.get(name)
                if std is None or not math.isfinite(std) or std > 1e6:
                    reasons.append(f"{name} (no information)")
                else:
                    reasons.append(f"{name} (std {std:.0f} px)")
            hint = _motion_hint(fixed)
            if self.diagnosis and self.diagnosis != NO_CAUSE:
                hint = f" ({self.diagnosis})"
            elif self.diagnosis:
                hint = f" ({NO_CAUSE} in the tracks; {hint[2:]}"
            parts.append(
                f"{', '.join(reasons)} not determined by these images"
                f"{hint}; {'; '.join(self.assumptions)}"
            )
        if weak:
            stds = ", ".join(
                name if self.std[name] is None else f"{name} (std {self.std[name]:.0f} px)"
                for name in weak
            )
            parts.append(f"{stds} only weakly determined, kept as estimated")
            if not fixed and self.diagnosis and self.diagnosis != NO_CAUSE:
                parts[-1] += f" ({self.diagnosis})"
        return f"camera {self.camera_id}: " + "; ".join(parts)


#: The name of :class:`CameraCalibration` where it is a group's result (the same type).
GroupCalibration = CameraCalibration


@dataclass
class SkippedGroup:
    """A camera (a group of camera ids) that was not calibrated, and why (e.g. ``"2 images"``)."""

    camera_ids: list[int]
    num_images: int
    reason: str

    @property
    def camera_id(self) -> int:
        """The group's first camera id."""
        return self.camera_ids[0]

    def to_json(self) -> dict[str, Any]:
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


def _lens_behind_pinhole(stored_model: str, lens: dict[str, Any]) -> bool:
    """Whether the lens stage found a lens (present, not a misfit) on a camera model
    without distortion parameters, in a model that has them."""
    return (
        stored_model in PINHOLE_MODELS
        and bool(lens.get("present"))
        and not lens.get("misfit")
        and lens.get("camera_model") not in (None, *PINHOLE_MODELS)
        and lens.get("params") is not None
    )


def _motion_hint(undetermined: list[str]) -> str:
    """A likely cause for a set of undetermined parameters."""
    if len(undetermined) == 4:
        return " (pure translation, or too few / too similar images?)"
    if undetermined in (["fy"], ["fx"]):
        return " (planar motion: all rotations about one axis?)"
    return " (forward motion with little rotation, or planar motion?)"
