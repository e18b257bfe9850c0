"""The images of ``run``: which files of the image folder go to COLMAP's feature extraction.

A file is an image here when its suffix is one of :data:`IMAGE_SUFFIXES` (any case). Such
a file is *used* when

* it is a regular file once symlinks are resolved (not a FIFO, a socket, a device or a
  folder; not a dangling link or a link loop) and this process can read it;
* it is complete: a JPEG reaches its end-of-image marker, a PNG its ``IEND`` chunk, a
  BMP holds the pixel rows its header announces (COLMAP's decoder, OpenImageIO, turns
  the missing part of such files into grey or black without an error); TIFFs and other
  formats are left to the decoder, which refuses a truncated TIFF;
* COLMAP's own decoder (``pycolmap.Bitmap.read``, what the extraction calls) reads it,
  so 16-bit PNGs and float TIFFs, which COLMAP converts to 8 bits, are used;
* both sides are at least :data:`MIN_IMAGE_SIDE` pixels once the image is downscaled as
  the extraction downscales it (longer side at most ``max_image_size``): thinner images
  have no SIFT features, and one downscaled to zero pixels crashes the extraction.

Other files with an image suffix are skipped, as COLMAP skips an image it cannot read;
each is reported with its reason (:class:`SkippedImage`). Fewer than
:data:`MIN_IMAGES` used images is an error (:class:`CalibrationError`).

A name that is not valid UTF-8 is refused rather than skipped: COLMAP stores image names
as UTF-8 text and pycolmap can neither pass such a name nor read it back, while the image
itself is fine, so renaming the file is the remedy. Folder paths need no such check:
pycolmap takes them as file system paths (bytes), whatever their encoding.

No file is opened before it is known to be a regular file, so a FIFO cannot block the run,
and OpenCV is not used (it crashes on such names and prints warnings for broken files).
"""

from __future__ import annotations

import errno
import os
import re
import stat
import struct
import sys
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from ..common.errors import CalibrationError
from ..common.log import keep_colmap_quiet, logger

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
#: Shortest usable side in pixels, of the image as SIFT sees it (after downscaling).
MIN_IMAGE_SIDE = 8
#: A calibration needs image triplets.
MIN_IMAGES = 3
#: How many skipped files an error message names.
NAMED_IN_ERROR = 3


@dataclass(frozen=True)
class SkippedImage:
    """A file with an image suffix that the extraction does not get, and why."""

    name: str
    reason: str

    def describe(self) -> str:
        """``NAME: REASON``, the name escaped (see :func:`display_name`)."""
        return f"{display_name(self.name)}: {self.reason}"


@dataclass(frozen=True)
class ImageListing:
    """The used images of a folder (sorted names) and the skipped files with their reasons."""

    folder: Path
    names: list[str]
    skipped: list[SkippedImage]


def display_name(name: str | os.PathLike[str]) -> str:
    """A file name as text: bytes that are not UTF-8 as ``\\xNN`` (``caf\\xe9.png``)."""
    return os.fsencode(name).decode("utf-8", "backslashreplace")


def list_images(image_dir: Path, max_image_size: int) -> ImageListing:
    """The images of ``image_dir`` that COLMAP's feature extraction can use.

    Args:
        image_dir: the folder (not searched recursively).
        max_image_size: the extraction's longest side in pixels (images are downscaled
            to it), for the size check.

    Raises:
        CalibrationError: the folder is missing or unreadable, a name is not UTF-8, or
            fewer than :data:`MIN_IMAGES` images are usable (the message names the first
            skipped files and their reasons).
    """
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise CalibrationError(f"image folder not found: {display_name(image_dir)}")
    try:
        entries = sorted(p.name for p in image_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    except OSError as exc:
        raise CalibrationError(
            f"cannot list image folder {display_name(image_dir)}: {exc.strerror or exc}"
        ) from None
    if not entries:
        raise CalibrationError(
            f"no images ({', '.join(IMAGE_SUFFIXES)}) in {display_name(image_dir)}"
        )
    for name in entries:
        _refuse_unencodable(image_dir, name)
    names: list[str] = []
    skipped: list[SkippedImage] = []
    for name in entries:
        reason = unusable_reason(image_dir / name, max_image_size)
        if reason is None:
            names.append(name)
        else:
            skipped.append(SkippedImage(name, reason))
            logger.warning("skipped %s", skipped[-1].describe())
    if len(names) < MIN_IMAGES:
        raise CalibrationError(_too_few(image_dir, names, skipped))
    return ImageListing(image_dir, names, skipped)


def _refuse_unencodable(image_dir: Path, name: str) -> None:
    """Refuse a file name that pycolmap cannot take as text (it encodes names as UTF-8).

    Python decodes names with the file system encoding, undecodable bytes as lone
    surrogates: a name whose bytes are not UTF-8, or (in a process whose file system
    encoding is ASCII: the C locale with ``PYTHONUTF8=0``) any non-ASCII name.
    """
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        pass
    else:
        return
    shown = display_name(image_dir / name)
    try:
        os.fsencode(name).decode("utf-8")
    except UnicodeDecodeError:
        raise CalibrationError(
            f"image file name is not valid UTF-8: {shown} "
            "(COLMAP stores image names as UTF-8 text; rename the file)"
        ) from None
    raise CalibrationError(
        f"image file name {shown} cannot be decoded with this process's file system "
        f"encoding ({sys.getfilesystemencoding()}); run under a UTF-8 locale "
        "(e.g. LC_ALL=C.UTF-8) or rename the file"
    )


def _too_few(image_dir: Path, names: list[str], skipped: list[SkippedImage]) -> str:
    """The one-line error for a folder with fewer than :data:`MIN_IMAGES` usable images."""
    message = (
        f"{display_name(image_dir)} has {len(names)} usable image(s); "
        f"at least {MIN_IMAGES} are needed"
    )
    if skipped:
        named = "; ".join(s.describe() for s in skipped[:NAMED_IN_ERROR])
        extra = len(skipped) - NAMED_IN_ERROR
        more = f"; and {extra} more" if extra > 0 else ""
        message += f" ({len(skipped)} skipped: {named}{more})"
    return message


def unusable_reason(path: Path, max_image_size: int) -> str | None:
    """Why the extraction cannot use the file at ``path``; None when it can.

    The checks of the module docstring, in order; the file is opened only once it is
    known to be a regular file (``O_NONBLOCK``, checked again on the open descriptor).
    """
    try:
        st = os.stat(path)
    except OSError as exc:
        return _stat_problem(path, exc)
    if not stat.S_ISREG(st.st_mode):
        return f"not a regular file ({_kind(st.st_mode)})"
    try:
        data = _read_regular_file(path)
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if data is None:
        return "not a regular file (replaced while it was checked)"
    if not data:
        return "empty file"
    incomplete = _incomplete(data)
    if incomplete is not None:
        return incomplete
    with keep_colmap_quiet():  # the decoder's own messages (libpng's), unless -vv
        bitmap = pycolmap.Bitmap.read(str(path), as_rgb=False)
    if bitmap is None:
        return "not an image COLMAP can decode"
    width, height = int(bitmap.width), int(bitmap.height)
    scale = min(1.0, max_image_size / max(width, height, 1))
    if min(width, height) * scale < MIN_IMAGE_SIDE:
        seen = (
            f", {width * scale:.0f} x {height * scale:.0f} px once downscaled to at most "
            f"{max_image_size} px"
            if scale < 1
            else ""
        )
        return f"{width} x {height} px{seen}: sides under {MIN_IMAGE_SIDE} px have no features"
    return None


def _stat_problem(path: Path, exc: OSError) -> str:
    """The reason for a file whose ``stat`` failed (a link to nothing, a link loop, ...)."""
    if exc.errno == errno.ELOOP:
        return "a symlink loop"
    if exc.errno == errno.ENOENT and path.is_symlink():
        return f"a dangling symlink (to {display_name(os.readlink(path))})"
    return f"cannot be read ({exc.strerror or exc})"


def _kind(mode: int) -> str:
    """What a non-regular file is, in words."""
    kinds = (
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    )
    return next((word for test, word in kinds if test(mode)), "not a file")


def _read_regular_file(path: Path) -> bytes | None:
    """The contents of ``path``; None if what is opened is not a regular file after all."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        with os.fdopen(fd, "rb", closefd=False) as stream:
            return stream.read()
    finally:
        os.close(fd)


# --------------------------------------------------------------------------- completeness

_JPEG = b"\xff\xd8"
_PNG = b"\x89PNG\r\n\x1a\n"
_BMP = b"BM"
#: A marker after entropy-coded data: 0xFF followed by neither a stuffed zero, a restart
#: marker (0xD0-0xD7) nor another fill byte.
_JPEG_MARKER = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
#: JPEG markers without a length field: TEM, RST0-7, SOI, EOI.
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8), 0xD8})


def _incomplete(data: bytes) -> str | None:
    """Why the file is truncated (by its format's structure), None if complete or not
    a format checked here."""
    if data.startswith(_JPEG):
        return None if _jpeg_complete(data) else "truncated JPEG (no end-of-image marker)"
    if data.startswith(_PNG):
        return None if _png_complete(data) else "truncated PNG (no IEND chunk)"
    if data.startswith(_BMP):
        return None if _bmp_complete(data) else "truncated BMP (fewer pixel bytes than announced)"
    return None


def _jpeg_complete(data: bytes) -> bool:
    """The JPEG's segments, and the entropy-coded data after each scan, lead to an EOI.

    Segments are skipped by their length (so a thumbnail's EOI inside the EXIF segment
    does not count); data after the EOI (camera trailers) is ignored.
    """
    pos, size = 2, len(data)
    while True:
        pos = data.find(b"\xff", pos)
        while 0 <= pos < size - 1 and data[pos + 1] == 0xFF:  # fill bytes
            pos += 1
        if pos < 0 or pos + 1 >= size:
            return False
        marker = data[pos + 1]
        pos += 2
        if marker == 0xD9:
            return True
        if marker in _JPEG_STANDALONE:
            continue
        if pos + 2 > size:
            return False
        (length,) = struct.unpack_from(">H", data, pos)
        if length < 2 or pos + length > size:
            return False
        pos += length
        if marker == 0xDA:  # start of scan: entropy-coded data up to the next marker
            found = _JPEG_MARKER.search(data, pos)
            if found is None:
                return False
            pos = found.start()


def _png_complete(data: bytes) -> bool:
    """The PNG's chunks, each within the file, lead to an ``IEND`` chunk."""
    pos, size = len(_PNG), len(data)
    while pos + 8 <= size:
        length, kind = struct.unpack_from(">I4s", data, pos)
        end = pos + 12 + length  # length, type, data, CRC
        if end > size:
            return False
        if kind == b"IEND":
            return True
        pos = end
    return False


def _bmp_complete(data: bytes) -> bool:
    """The BMP holds the pixel bytes its headers announce (rows padded to 4 bytes)."""
    if len(data) < 26:
        return False
    offset, header = struct.unpack_from("<II", data, 10)
    if header == 12:  # OS/2 BITMAPCOREHEADER
        width, height, _, bits = struct.unpack_from("<HHHH", data, 18)
        compression, image_size = 0, 0
    elif len(data) >= 38:
        width, height, _, bits, compression, image_size = struct.unpack_from("<iiHHII", data, 18)
    else:
        return False
    if compression in (0, 3, 6):  # uncompressed rows (BI_RGB, BI_BITFIELDS, ...)
        needed = offset + (abs(width) * bits + 31) // 32 * 4 * abs(height)
    else:  # RLE, embedded JPEG/PNG: the header gives the size
        needed = offset + image_size
    return len(data) >= needed
