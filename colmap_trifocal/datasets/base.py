"""Common types of the dataset readers, and the helpers they share.

Every reader returns a :class:`DatasetScene`: the image folder and, per image, a
:class:`GroundTruthView` with the intrinsics (fx, fy, cx, cy) in pixels in COLMAP's
pixel convention (the centre of the top-left pixel at (0.5, 0.5)) and, where the
format has them, the world-to-camera pose ``x_cam = R X + t``. Formats in the
OpenCV convention (centre of the top-left pixel at (0, 0)) are shifted with
:func:`from_opencv`. Skew, where a format has it, is dropped.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..common.errors import CalibrationError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")
#: Added to (fx, fy, cx, cy) to go from the OpenCV to the COLMAP pixel convention.
OPENCV_TO_COLMAP = np.array([0.0, 0.0, 0.5, 0.5])


@dataclass(frozen=True)
class GroundTruthView:
    """Ground truth of one image."""

    name: str  # image path relative to DatasetScene.image_dir (posix string)
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy in pixels, COLMAP convention
    width: int | None = None
    height: int | None = None
    rotation: np.ndarray | None = None  # (3, 3) world-to-camera, x_cam = R X + t
    translation: np.ndarray | None = None  # (3,)

    def __post_init__(self) -> None:
        object.__setattr__(self, "intrinsics", _frozen(self.intrinsics, (4,)))
        if (self.rotation is None) != (self.translation is None):
            raise ValueError(f"{self.name}: give both rotation and translation, or neither")
        if self.rotation is not None and self.translation is not None:
            object.__setattr__(self, "rotation", _frozen(self.rotation, (3, 3)))
            object.__setattr__(self, "translation", _frozen(self.translation, (3,)))

    @property
    def centre(self) -> np.ndarray | None:
        """Camera centre in world coordinates, ``-Rᵀ t`` (None without a pose)."""
        if self.rotation is None or self.translation is None:
            return None
        return -self.rotation.T @ self.translation


@dataclass
class DatasetScene:
    """One scene: its images and their ground truth."""

    kind: str
    name: str
    image_dir: Path
    views: list[GroundTruthView]  # in the dataset's natural order
    # name -> most-overlapping names with scores, where the format provides it
    overlap: dict[str, list[tuple[str, float]]] | None = None
    #: The lens's distortion where the format gives one (OpenCV's names: k1, k2, p1, p2).
    distortion: dict[str, float] | None = None

    def view(self, name: str) -> GroundTruthView:
        """The view of an image (name relative to ``image_dir``)."""
        # Name index cached outside the dataclass fields; rebuilt when ``views`` changes.
        views, count, index = self.__dict__.get("_view_index", (None, -1, {}))
        if views is not self.views or count != len(self.views):
            index = {v.name: v for v in self.views}
            self.__dict__["_view_index"] = (self.views, len(self.views), index)
        try:
            return index[name]
        except KeyError:
            raise CalibrationError(
                f"no ground truth for image {name!r} in {self.kind} scene {self.name}"
            ) from None

    def mean_intrinsics(self) -> np.ndarray:
        """(fx, fy, cx, cy) averaged over the views."""
        if not self.views:
            raise CalibrationError(f"{self.kind} scene {self.name} has no views")
        return np.mean([v.intrinsics for v in self.views], axis=0)


def _frozen(values: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    array = np.array(values, dtype=float).reshape(shape)
    array.setflags(write=False)
    return array


def from_opencv(K: np.ndarray) -> np.ndarray:
    """(fx, fy, cx, cy) in COLMAP's convention from a 3x3 K in OpenCV's (cx, cy + 0.5)."""
    K = np.asarray(K, dtype=float)
    return K[[0, 1, 0, 1], [0, 1, 2, 2]] + OPENCV_TO_COLMAP


def one_line(exc: BaseException) -> str:
    """An exception's message on one line."""
    return " ".join(str(exc).split()) or type(exc).__name__


@contextmanager
def parsing(path: Path | str, what: str) -> Iterator[None]:
    """Turn the errors of parsing ``path`` into one-line :class:`CalibrationError`."""
    try:
        yield
    except CalibrationError:
        raise
    except (OSError, ValueError, IndexError, KeyError, TypeError) as exc:
        raise CalibrationError(f"cannot read {what} {path}: {one_line(exc)}") from None


def number_rows(path: Path, comment: str = "#") -> list[list[float]]:
    """The non-empty, non-comment lines of a text file as rows of floats."""
    lines = Path(path).read_text().splitlines()
    return [list(map(float, s.split())) for s in lines if s.strip() and not _comment(s, comment)]


def text_rows(path: Path, comment: str = "#") -> list[list[str]]:
    """The non-empty, non-comment lines of a text file, split on whitespace."""
    lines = Path(path).read_text().splitlines()
    return [s.split() for s in lines if s.strip() and not _comment(s, comment)]


def _comment(line: str, comment: str) -> bool:
    return bool(comment) and line.lstrip().startswith(comment)


def list_images(folder: Path) -> list[str]:
    """Sorted names of the image files in a folder (raises if it does not exist)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"image folder {folder} does not exist")
    return sorted(p.name for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an image file, or None if it cannot be read."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if Path(path).is_file() else None
    return None if image is None else (int(image.shape[1]), int(image.shape[0]))


def require_dir(path: Path | str, what: str) -> Path:
    """``path`` as a Path if it is a folder, else a CalibrationError."""
    path = Path(path)
    if not path.is_dir():
        raise CalibrationError(f"{what} {path} does not exist or is not a folder")
    return path


def require_file(path: Path, what: str) -> Path:
    """``path`` if it is a file, else a CalibrationError."""
    if not Path(path).is_file():
        raise CalibrationError(f"{what} {path} not found")
    return Path(path)


def pose_from_camera_to_world(rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(…, 3, 4) world-to-camera [R | t] from camera-to-world rotations and centres."""
    R = np.swapaxes(np.asarray(rotation, dtype=float), -1, -2)
    t = -np.einsum("...ij,...j->...i", R, np.asarray(centre, dtype=float))
    return np.concatenate([R, t[..., None]], axis=-1)
