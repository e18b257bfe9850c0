"""Readers of datasets with ground-truth intrinsics.

:func:`read_scene` reads one scene of any kind in :data:`DATASET_KINDS` into a
:class:`DatasetScene` (intrinsics in COLMAP's pixel convention, poses
world-to-camera where the format has them). Every input problem is raised as a
one-line :class:`~colmap_trifocal.common.errors.CalibrationError`.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path

from ..common.errors import CalibrationError
from .base import DatasetScene, GroundTruthView, one_line
from .blendedmvs import read_blendedmvs_scene
from .colmap_model import read_colmap_scene
from .dtu import read_dtu_scene
from .euroc import read_euroc_scene
from .kitti import read_kitti_scene
from .middlebury import read_middlebury_scene
from .nerf import read_nerf_scene
from .strecha import default_datasets_root, read_strecha_scene
from .tum import read_tum_scene

DATASET_KINDS = (
    "strecha",
    "colmap",
    "blendedmvs",
    "kitti",
    "tum",
    "dtu",
    "middlebury",
    "euroc",
    "nerf",
)

READERS: dict[str, Callable[..., DatasetScene]] = {
    "strecha": read_strecha_scene,
    "colmap": read_colmap_scene,
    "blendedmvs": read_blendedmvs_scene,
    "kitti": read_kitti_scene,
    "tum": read_tum_scene,
    "dtu": read_dtu_scene,
    "middlebury": read_middlebury_scene,
    "euroc": read_euroc_scene,
    "nerf": read_nerf_scene,
}

__all__ = [
    "DATASET_KINDS",
    "DatasetScene",
    "GroundTruthView",
    "default_datasets_root",
    "read_scene",
]


def read_scene(kind: str, path: Path | str, **options) -> DatasetScene:
    """Read one scene of a dataset ``kind`` (see :data:`DATASET_KINDS`) at ``path``.

    ``options`` go to the reader (e.g. ``camera=0`` for ``kitti``, ``image_dir`` for
    ``colmap``, ``par_file`` for ``middlebury``).
    """
    reader = READERS.get(kind)
    if reader is None:
        raise CalibrationError(
            f"unknown dataset kind {kind!r} (expected one of: {', '.join(DATASET_KINDS)})"
        )
    path = Path(path)
    if not path.exists():
        raise CalibrationError(f"{kind} dataset path {path} does not exist")
    accepted = list(inspect.signature(reader).parameters)[1:]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise CalibrationError(
            f"unknown option(s) {', '.join(unknown)} for dataset kind {kind!r}"
            f" (accepted: {', '.join(accepted) or 'none'})"
        )
    try:
        return reader(path, **options)
    except CalibrationError:
        raise
    except (OSError, ValueError, IndexError, KeyError) as exc:
        raise CalibrationError(f"cannot read {kind} dataset {path}: {one_line(exc)}") from None
