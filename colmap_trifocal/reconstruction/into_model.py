"""Write estimated intrinsics into a copy of an existing COLMAP reconstruction, then refine.

``calibrate DB --model DIR --output OUT``: the model at ``DIR`` (built from the same
database, so its camera ids are the database's) is read with pycolmap, each camera
with an estimate gets it (distortion kept), the copy is optionally refined by
pycolmap bundle adjustment (focal lengths and principal points; distortion on
request) and written to ``OUT``. ``DIR`` is never changed. The mean reprojection
error (pixels, over all observations) is reported for the model as given, with the
estimate written in (poses and points unchanged), and after the refinement.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from ..common.errors import CalibrationError
from ..common.files import write_model_atomically
from ..common.log import logger
from ..database.cameras import CameraInfo
from ..intrinsics.results import apply_cameras
from .mapping import REFINE_CHOICES, refine_intrinsics


@dataclass
class ModelUpdate:
    """What :func:`calibrate_model` did; reprojection errors in pixels (mean over observations)."""

    output: Path
    camera_ids: list[int]
    error_given: float
    error_with_estimate: float
    error_refined: float | None

    def to_json(self) -> dict:
        """The JSON form (``calibrate --json`` has it under ``"model"``)."""
        return {
            "output": str(self.output),
            "camera_ids": self.camera_ids,
            "reprojection_error_px": {
                "given": self.error_given,
                "with_estimate": self.error_with_estimate,
                "refined": self.error_refined,
            },
        }

    def describe(self) -> str:
        """One line for the terminal."""
        refined = "" if self.error_refined is None else f", refined {self.error_refined:.3f} px"
        return (
            f"wrote {self.output}: {len(self.camera_ids)} camera(s) updated; mean reprojection "
            f"error: given model {self.error_given:.3f} px, with the estimate "
            f"{self.error_with_estimate:.3f} px{refined}"
        )


def reprojection_error(reconstruction: pycolmap.Reconstruction) -> float:
    """Mean reprojection error (pixels) with the current cameras, poses and points.

    ``compute_mean_reprojection_error`` averages errors cached in the points, which
    changing a camera or bundle adjustment leave stale; they are recomputed first.
    """
    reconstruction.update_point_3d_errors()
    return float(reconstruction.compute_mean_reprojection_error())


def read_model(path: Path) -> pycolmap.Reconstruction:
    """A COLMAP model folder (binary or text); CalibrationError when it cannot be read."""
    path = Path(path)
    if not path.is_dir():
        raise CalibrationError(f"model folder not found: {path}")
    if not any((path / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
        raise CalibrationError(f"not a COLMAP model (no cameras.bin or cameras.txt): {path}")
    try:
        return pycolmap.Reconstruction(path)
    except (RuntimeError, ValueError) as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[-1]
        raise CalibrationError(f"cannot read COLMAP model {path}: {first}") from None


def check_model_images(
    reconstruction: pycolmap.Reconstruction, image_names: Iterable[str], model: Path
) -> None:
    """Refuse a model whose images are not the database's (by name).

    Camera ids, models and image sizes alone accept a model of another database taken
    with the same camera: its poses and points then do not belong to the images the
    estimate comes from.

    Args:
        reconstruction: the model read from ``model``.
        image_names: the names of the database's images.
        model: the model folder (for the message).
    """
    known = set(image_names)
    foreign = sorted(
        image.name for image in reconstruction.images.values() if image.name not in known
    )
    if foreign:
        raise CalibrationError(
            f"{len(foreign)} of the model's {len(reconstruction.images)} images are not in the "
            f"database (e.g. {foreign[0]}): is the model from this database? {model}"
        )


def check_output_folder(output: Path, model: Path) -> None:
    """Refuse an output folder that is the model itself or already holds files."""
    output, model = Path(output), Path(model)
    if output.exists() and output.resolve() == model.resolve():
        raise CalibrationError(
            f"--output must differ from --model (the model is never changed): {output}"
        )
    if output.exists() and (not output.is_dir() or any(output.iterdir())):
        raise CalibrationError(f"--output must be a new or empty folder: {output}")


def set_intrinsics(
    reconstruction: pycolmap.Reconstruction, cameras: dict[int, CameraInfo]
) -> list[int]:
    """Write each camera's params into the reconstruction's camera of the same id.

    Camera ids the model lacks are skipped (:func:`..intrinsics.results.apply_cameras`).

    Returns:
        The ids written. Raises CalibrationError when no camera id matches, or when a
        matching camera differs in model or image size (a model of another database).
    """
    return apply_cameras(reconstruction, cameras, require_all=False)


def calibrate_model(
    model: Path,
    output: Path,
    cameras: dict[int, CameraInfo],
    refine: str = "ba",
    *,
    refine_distortion: bool = False,
    reconstruction: pycolmap.Reconstruction | None = None,
    tied: Collection[int] = (),
) -> ModelUpdate:
    """Copy the model at ``model`` to ``output`` with ``cameras``' params, refined on request.

    Args:
        model: existing COLMAP model folder (left unchanged).
        output: new or empty folder for the result.
        cameras: camera_id -> camera with the estimated intrinsics.
        refine: ``none`` or ``ba`` (see :func:`.mapping.refine_intrinsics`).
        refine_distortion: also refine the distortion parameters (with ``ba``).
        reconstruction: the model as :func:`read_model` read it (changed here); read
            from ``model`` when None.
        tied: cameras whose fy the adjustment keeps equal to fx (see
            :func:`.mapping.refine_intrinsics`).
    """
    if refine not in REFINE_CHOICES:
        raise CalibrationError(f"unknown --refine {refine!r} (choose from {REFINE_CHOICES})")
    check_output_folder(output, model)
    if reconstruction is None:
        reconstruction = read_model(model)
    if reconstruction.num_reg_images() == 0:
        raise CalibrationError(f"the model has no registered images: {model}")
    given = reprojection_error(reconstruction)
    written = set_intrinsics(reconstruction, cameras)
    with_estimate = reprojection_error(reconstruction)
    refined = None
    if refine == "ba":
        refine_intrinsics(reconstruction, distortion=refine_distortion, tied=tied)
        refined = reprojection_error(reconstruction)
    write_model_atomically(reconstruction, Path(output))
    logger.info("wrote the model with %d calibrated camera(s) to %s", len(written), output)
    return ModelUpdate(Path(output), written, given, with_estimate, refined)
