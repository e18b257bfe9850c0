"""Middlebury multi-view stereo sets (Seitz et al., CVPR 2006: temple, dino, ...).

Kind ``middlebury``; ``path`` is a folder holding ``<name>_par.txt`` and the images
it lists (or an ``images/`` folder holding them). The par file's first line is the
number of images, then one line per image:
``imgname.png k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 ... r33 t1 t2 t3`` with
``x ~ K [R | t] X`` (R, t world-to-camera). If several ``*_par.txt`` exist, option
``par_file`` picks one (a name in the folder or a path), else the first sorted. Views
keep the par file's order; width and height come from the first image. The matrices
are taken to be in the OpenCV pixel convention: cx, cy + 0.5.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..common.errors import CalibrationError
from .base import (
    DatasetScene,
    GroundTruthView,
    from_opencv,
    image_size,
    parsing,
    require_dir,
    require_file,
    text_rows,
)

PAR_SUFFIX = "_par.txt"


def read_middlebury_scene(path: Path | str, par_file: Path | str | None = None) -> DatasetScene:
    """A Middlebury folder with a ``*_par.txt`` as a :class:`DatasetScene`."""
    folder = require_dir(path, "Middlebury folder")
    if par_file is None:
        candidates = sorted(folder.glob(f"*{PAR_SUFFIX}"))
        if not candidates:
            raise CalibrationError(f"no *{PAR_SUFFIX} file in {folder}")
        par = candidates[0]
    else:
        par = Path(par_file) if Path(par_file).is_absolute() else folder / par_file
    require_file(par, "Middlebury parameter file")
    names, K, R, t = read_par_file(par)
    image_dir = folder
    if not (folder / names[0]).is_file() and (folder / "images" / names[0]).is_file():
        image_dir = folder / "images"
    width, height = image_size(image_dir / names[0]) or (None, None)
    views = [
        GroundTruthView(
            name=name,
            intrinsics=from_opencv(K_i),
            width=width,
            height=height,
            rotation=R_i,
            translation=t_i,
        )
        for name, K_i, R_i, t_i in zip(names, K, R, t, strict=True)
    ]
    scene_name = par.name[: -len(PAR_SUFFIX)] if par.name.endswith(PAR_SUFFIX) else par.stem
    return DatasetScene(kind="middlebury", name=scene_name, image_dir=image_dir, views=views)


def read_par_file(path: Path) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """Image names, K (N, 3, 3), R (N, 3, 3) and t (N, 3) of a Middlebury ``_par.txt``."""
    with parsing(path, "Middlebury parameter file"):
        rows = text_rows(path)
        count = int(rows[0][0])
        lines = rows[1:]
        if count < 1 or len(lines) != count:
            raise ValueError(f"{count} images announced, {len(lines)} lines found")
        if any(len(r) != 22 for r in lines):
            raise ValueError("expected an image name and 21 numbers per line")
        numbers = np.array([r[1:] for r in lines], dtype=float)
    K = numbers[:, :9].reshape(-1, 3, 3)
    R = numbers[:, 9:18].reshape(-1, 3, 3)
    return [r[0] for r in lines], K, R, numbers[:, 18:]
