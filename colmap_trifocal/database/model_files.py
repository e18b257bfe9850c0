"""Check the sizes of a binary COLMAP model against its headers before pycolmap reads it.

pycolmap's reader trusts the counts in the files: an empty or truncated ``points3D.bin``
makes it allocate without bound (docs/reliability.md) or fail with an
``IndexError``/``std::bad_alloc``. The layout (COLMAP ``src/colmap/scene/
reconstruction_io_binary.cc``, little-endian, no padding) is walked here record by record
for the cameras and images, whose counts are small, and checked as a whole for the points:

* ``cameras.bin``: uint64 count; per camera uint32 id, int32 model id, uint64 width,
  uint64 height, float64 params[the model's number of params].
* ``images.bin``: uint64 count; per image uint32 id, float64 qw, qx, qy, qz, tx, ty, tz,
  uint32 camera id, the name NUL-terminated, uint64 num_points2D, then per point2D
  float64 x, y and uint64 point3D id (``2**64 - 1``: none).
* ``points3D.bin``: uint64 count; per point uint64 id, float64 x, y, z, uint8 r, g, b,
  float64 error, uint64 track length, then per track element uint32 image id, uint32
  point2D index. Every observation of ``images.bin`` is one track element, so the file
  has exactly ``8 + 51 · count + 8 · observations`` bytes.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import stat
import struct
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..common.streams import file_kind

#: Every file of a model folder pycolmap may open (a FIFO among them blocked it for good).
_MODEL_FILE_NAMES = tuple(
    f"{name}.{ext}"
    for name in ("cameras", "images", "points3D", "rigs", "frames")
    for ext in ("bin", "txt")
)

_COUNT = struct.Struct("<Q")
_CAMERA = struct.Struct("<IiQQ")
_IMAGE_HEAD = 4 + 7 * 8 + 4  # id, pose, camera id (before the name)
_POINT2D_BYTES = 24
_POINT3D_FIXED = 8 + 3 * 8 + 3 + 8 + 8  # id, xyz, rgb, error, track length
_TRACK_ELEMENT = 8
_NO_POINT3D = np.iinfo(np.uint64).max


@cache
def _num_params(model_id: int) -> int | None:
    """Number of params of a COLMAP camera model id; None for an unknown id."""
    try:
        model = pycolmap.CameraModelId(model_id)
        return len(pycolmap.Camera.create_from_model_id(1, model, 1.0, 1, 1).params)
    except (ValueError, TypeError, RuntimeError):
        return None


def _count(data: bytes | mmap.mmap, path: Path) -> int:
    if len(data) < _COUNT.size:
        raise CalibrationError(f"truncated COLMAP model file ({len(data)} bytes): {path}")
    return _COUNT.unpack_from(data)[0]


@contextlib.contextmanager
def _mapped(path: Path) -> Iterator[bytes | mmap.mmap]:
    """The file's bytes, mapped rather than read: a huge (or sparse, 60 GB) file costs
    address space only, and the walk touches its first records alone."""
    with path.open("rb") as stream:
        if os.fstat(stream.fileno()).st_size == 0:
            yield b""
            return
        with mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as data:
            yield data


def _check_cameras(path: Path) -> None:
    with _mapped(path) as data:
        _walk_cameras(data, path)


def _walk_cameras(data: bytes | mmap.mmap, path: Path) -> None:
    offset, count = _COUNT.size, _count(data, path)
    if count * (_CAMERA.size + 8) > len(data):
        raise CalibrationError(f"truncated COLMAP model file ({count} cameras): {path}")
    for _ in range(count):
        if offset + _CAMERA.size > len(data):
            raise CalibrationError(f"truncated COLMAP model file: {path}")
        _, model_id, _, _ = _CAMERA.unpack_from(data, offset)
        params = _num_params(model_id)
        if params is None:
            raise CalibrationError(f"corrupt COLMAP model file (camera model {model_id}): {path}")
        offset += _CAMERA.size + 8 * params
    _check_end(offset, len(data), path)


def _check_images(path: Path) -> int:
    """Walk ``images.bin``; the number of observations (point2Ds with a 3D point)."""
    with _mapped(path) as data:
        return _walk_images(data, path)


def _walk_images(data: bytes | mmap.mmap, path: Path) -> int:
    offset, count = _COUNT.size, _count(data, path)
    if count * (_IMAGE_HEAD + 1 + _COUNT.size) > len(data):
        raise CalibrationError(f"truncated COLMAP model file ({count} images): {path}")
    observations = 0
    for _ in range(count):
        end_of_name = data.find(b"\0", offset + _IMAGE_HEAD)
        if end_of_name < 0 or end_of_name + 1 + _COUNT.size > len(data):
            raise CalibrationError(f"truncated COLMAP model file: {path}")
        offset = end_of_name + 1
        (num_points,) = _COUNT.unpack_from(data, offset)
        offset += _COUNT.size
        if num_points > (len(data) - offset) // _POINT2D_BYTES:
            raise CalibrationError(f"truncated COLMAP model file: {path}")
        points = data[offset : offset + _POINT2D_BYTES * num_points]  # a copy: no export
        ids = np.frombuffer(points, "<u8", count=3 * num_points)[2::3]
        observations += int(np.count_nonzero(ids != _NO_POINT3D))
        offset += _POINT2D_BYTES * num_points
    _check_end(offset, len(data), path)
    return observations


def _check_points(path: Path, observations: int) -> None:
    size = path.stat().st_size
    with path.open("rb") as stream:
        count = _count(stream.read(_COUNT.size), path)
    expected = _COUNT.size + _POINT3D_FIXED * count + _TRACK_ELEMENT * observations
    if size != expected:
        raise CalibrationError(
            f"truncated or corrupt COLMAP model file: {count} points and {observations} "
            f"observations need {expected} bytes, the file has {size}: {path}"
        )


def _check_end(offset: int, size: int, path: Path) -> None:
    if offset != size:
        raise CalibrationError(
            f"corrupt COLMAP model file ({size - offset} bytes after the last record): {path}"
        )


def check_regular_files(folder: Path) -> None:
    """Refuse a model folder where a file pycolmap opens is not a regular file (a FIFO
    blocked the read for good, a folder failed deep inside)."""
    for name in _MODEL_FILE_NAMES:
        try:
            mode = os.stat(Path(folder) / name).st_mode
        except OSError:
            continue
        if not stat.S_ISREG(mode):
            raise CalibrationError(
                f"cannot read the COLMAP model in {folder}: {name} is not a regular file "
                f"({file_kind(mode)})"
            )


def check_binary_model(folder: Path) -> None:
    """Check a model folder's ``cameras.bin``, ``images.bin`` and ``points3D.bin``.

    Does nothing when the folder has no complete set of ``.bin`` files (a text model,
    which pycolmap reads line by line). Walks the cameras and images files (mapped, not
    read: only their records are touched) and reads only the header of the points file.

    Raises:
        CalibrationError: a file is shorter or longer than its counts say, or unreadable.
    """
    folder = Path(folder)
    check_regular_files(folder)
    files = {name: folder / f"{name}.bin" for name in ("cameras", "images", "points3D")}
    if not all(path.is_file() for path in files.values()):
        return
    try:
        _check_cameras(files["cameras"])
        _check_points(files["points3D"], _check_images(files["images"]))
    except OSError as exc:
        raise CalibrationError(
            f"cannot read the COLMAP model in {folder}: {exc.strerror or exc}"
        ) from exc
