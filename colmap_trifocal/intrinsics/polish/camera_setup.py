"""The shared camera's setup: the COLMAP model that expresses what the solve estimates,
what an adjustment refines, and the directions those parameters span in (fx, fy, cx, cy).

The camera is a PINHOLE (``fx, fy, cx, cy``) or, for a tied focal length, a
SIMPLE_PINHOLE camera; holding one principal-point coordinate but not the other is not
expressible with pycolmap's cameras.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..solve.parametrization import FreeParameters


@dataclass(frozen=True)
class Refined:
    """What an adjustment of the shared camera refines besides poses and points."""

    focal: bool = False
    principal_point: bool = False
    distortion: bool = False


#: Poses and points only: the camera held.
NOTHING = Refined()


@dataclass(frozen=True)
class CameraSetup:
    """The shared camera's COLMAP model (PINHOLE, or SIMPLE_PINHOLE for a tied focal
    length) and what its adjustment refines."""

    model: str
    refined: Refined

    @property
    def tied(self) -> bool:
        """One focal length for both axes."""
        return self.model == "SIMPLE_PINHOLE"


def pycolmap_camera_setup(free_parameters: FreeParameters) -> CameraSetup | None:
    """The shared camera that estimates ``free_parameters``.

    None when pycolmap cannot express it (one principal-point coordinate held) or
    nothing is estimated.
    """
    if free_parameters.cx != free_parameters.cy or free_parameters.dimension == 0:
        return None
    camera_model = "SIMPLE_PINHOLE" if free_parameters.focal == "tied" else "PINHOLE"
    return CameraSetup(camera_model, Refined(free_parameters.focal != "held", free_parameters.cx))


def camera_start(
    free_parameters: FreeParameters, estimate: np.ndarray
) -> tuple[CameraSetup, np.ndarray] | None:
    """The shared camera's setup (:func:`pycolmap_camera_setup`) and its starting
    (fx, fy, cx, cy) in pixels (fy = fx for a single focal length); None where
    pycolmap cannot express ``free_parameters``."""
    setup = pycolmap_camera_setup(free_parameters)
    if setup is None:
        return None
    intrinsics = np.asarray(estimate, dtype=float).copy()
    if setup.tied:
        intrinsics[1] = intrinsics[0]
    return setup, intrinsics


def refined_directions(refined: Refined, *, tied: bool, extra: int = 0) -> np.ndarray:
    """A (4 + extra, k): (fx, fy, cx, cy, extra parameters) = A p for the k parameters an
    adjustment refines: one focal length (``tied``) or two, the principal point, and
    each of the ``extra`` (distortion) parameters."""
    q = 4 + extra
    unit = np.eye(q)
    columns = []
    if refined.focal:
        columns += [unit[0] + unit[1]] if tied else [unit[0], unit[1]]
    if refined.principal_point:
        columns += [unit[2], unit[3]]
    columns += [unit[4 + i] for i in range(extra)]
    return np.array(columns).reshape(-1, q).T
