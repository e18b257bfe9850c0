"""BlendedMVS (Yao et al., CVPR 2020) scenes, MVSNet camera format.

Kind ``blendedmvs``; ``path`` is a scene folder (``<PID>/``) holding

* ``blended_images/XXXXXXXX.jpg`` (the ``*_masked.jpg`` files are skipped),
* ``cams/XXXXXXXX_cam.txt``: ``extrinsic`` and 4 rows of the 4x4 world-to-camera
  matrix, ``intrinsic`` and 3 rows of K, then a depth line (ignored),
* ``cams/pair.txt`` (optional): the number of views, then per view a line with its
  id and a line ``k id1 score1 id2 score2 ...`` → :attr:`DatasetScene.overlap`.

K is in the OpenCV pixel convention; cx and cy are shifted by +0.5 to COLMAP's.
Views are sorted by name; width and height come from the first image.
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
    list_images,
    parsing,
    require_dir,
    require_file,
    text_rows,
)


def read_blendedmvs_scene(path: Path | str) -> DatasetScene:
    """A BlendedMVS scene folder as a :class:`DatasetScene`."""
    scene = require_dir(path, "BlendedMVS scene folder")
    image_dir = scene / "blended_images"
    names = [n for n in list_images(image_dir) if not Path(n).stem.endswith("_masked")]
    if not names:
        raise CalibrationError(f"no images in {image_dir}")
    size = image_size(image_dir / names[0]) or (None, None)
    views = []
    for name in names:
        extrinsic, K = read_cam_file(scene / "cams" / f"{Path(name).stem}_cam.txt")
        views.append(
            GroundTruthView(
                name=name,
                intrinsics=from_opencv(K),
                width=size[0],
                height=size[1],
                rotation=extrinsic[:3, :3],
                translation=extrinsic[:3, 3],
            )
        )
    pair_file = scene / "cams" / "pair.txt"
    overlap = read_pair_file(pair_file, names) if pair_file.is_file() else None
    return DatasetScene(
        kind="blendedmvs", name=scene.name, image_dir=image_dir, views=views, overlap=overlap
    )


def read_cam_file(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(4x4 world-to-camera matrix, 3x3 K) of an MVSNet ``_cam.txt`` file."""
    require_file(path, "BlendedMVS camera file")
    with parsing(path, "BlendedMVS camera file"):
        rows = text_rows(path)
        words = [r[0].lower() for r in rows]
        e, i = words.index("extrinsic"), words.index("intrinsic")
        extrinsic = np.array(rows[e + 1 : e + 5], dtype=float).reshape(4, 4)
        K = np.array(rows[i + 1 : i + 4], dtype=float).reshape(3, 3)
    return extrinsic, K


def read_pair_file(path: Path, names: list[str]) -> dict[str, list[tuple[str, float]]]:
    """View name -> [(neighbour name, score), ...] from an MVSNet ``pair.txt``.

    Ids are mapped to the names of ``names`` by their numeric stem (``00000012.jpg``
    for id 12); an id without an image is named ``f"{id:08d}.jpg"``.
    """
    by_id = {int(Path(n).stem): n for n in names if Path(n).stem.isdigit()}
    with parsing(path, "BlendedMVS pair file"):
        rows = text_rows(path)
        count = int(rows[0][0])
        if len(rows) < 1 + 2 * count:
            raise ValueError(f"{count} views announced, {(len(rows) - 1) // 2} found")
        overlap = {}
        pairs = zip(rows[1 : 1 + 2 * count : 2], rows[2 : 2 + 2 * count : 2], strict=True)
        for view, neighbours in pairs:
            k = int(neighbours[0])
            if len(neighbours) != 1 + 2 * k:
                raise ValueError(f"view {view[0]}: {k} neighbours announced")
            ids = np.array(neighbours[1::2], dtype=int)
            scores = np.array(neighbours[2::2], dtype=float)
            overlap[_name(int(view[0]), by_id)] = [
                (_name(int(i), by_id), float(s)) for i, s in zip(ids, scores, strict=True)
            ]
    return overlap


def _name(view_id: int, by_id: dict[int, str]) -> str:
    return by_id.get(view_id, f"{view_id:08d}.jpg")
