"""``run``'s image folder and workspace where the process or the whole run is the point.

The refused inputs are rows of the bad-input table (``tests/bad_input/``). Here: which files
the image check keeps (formats COLMAP converts, every truncation point of each format), a run
that skips
unusable files and goes on, a non-UTF-8 name in other locales (a subprocess: the locale is
the process's), and two runs on one workspace at once.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from conftest import CliResult, assert_one_error_line, run_cli, texture_views

from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.database.features import build_database
from colmap_trifocal.reconstruction.images import list_images, unusable_reason
from colmap_trifocal.reconstruction.workspace import LOCK_NAME


def _encoded(suffix: str, image: np.ndarray, *params: int) -> bytes:
    ok, data = cv2.imencode(suffix, image, list(params))
    assert ok
    return data.tobytes()


def _image_folder(folder: Path, count: int = 3) -> Path:
    folder.mkdir(parents=True)
    for index, image in enumerate(texture_views(count)):
        (folder / f"{index:02d}.jpg").write_bytes(_encoded(".jpg", image))
    return folder


def _tree(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


#: Each format COLMAP reads, as the encoder writes it: (suffix, bytes).
VIEW = texture_views(1)[0]
FORMATS = {
    "JPEG": (".jpg", _encoded(".jpg", VIEW)),
    "progressive JPEG": (".jpg", _encoded(".jpg", VIEW, cv2.IMWRITE_JPEG_PROGRESSIVE, 1)),
    "PNG": (".png", _encoded(".png", VIEW)),
    "16-bit PNG": (".png", _encoded(".png", VIEW.astype(np.uint16) * 257)),
    "BMP": (".bmp", _encoded(".bmp", VIEW)),
    "TIFF": (".tif", _encoded(".tif", VIEW)),
    "uncompressed TIFF": (".tif", _encoded(".tif", VIEW, cv2.IMWRITE_TIFF_COMPRESSION, 1)),
    "float TIFF": (".tiff", _encoded(".tif", VIEW.astype(np.float32) / 255)),
}


@pytest.mark.parametrize("kind", list(FORMATS))
def test_every_truncation_is_skipped(kind: str, tmp_path: Path) -> None:
    """The whole file is used; the file cut at any of 40 points (or by its last byte) is
    skipped. COLMAP's decoder fills a cut JPEG with grey, a cut PNG or BMP with black."""
    suffix, data = FORMATS[kind]
    path = tmp_path / f"x{suffix}"
    path.write_bytes(data)
    assert unusable_reason(path, 1600) is None
    cuts = sorted({*np.linspace(2, len(data) - 2, 40).astype(int), len(data) - 1})
    accepted = []
    for cut in cuts:
        path.write_bytes(data[:cut])
        if unusable_reason(path, 1600) is None:
            accepted.append(cut)
    assert accepted == [], f"{kind} of {len(data)} bytes accepted when cut at {accepted}"


def test_jpeg_with_thumbnail_and_trailer_is_used(tmp_path: Path) -> None:
    """A complete JPEG is used whatever surrounds its image: an EXIF thumbnail (a whole
    JPEG with its own end marker inside APP1) and bytes after the end marker (camera
    trailers). Cut inside its scan, it is skipped even though the thumbnail's end marker
    remains."""
    main = _encoded(".jpg", VIEW)
    thumbnail = _encoded(".jpg", cv2.resize(VIEW, (60, 45)))
    body = b"Exif\x00\x00" + thumbnail
    app1 = b"\xff\xe1" + (len(body) + 2).to_bytes(2, "big") + body
    data = main[:2] + app1 + main[2:] + b"\x00" * 64 + b"TRAILER"
    path = tmp_path / "x.jpg"
    path.write_bytes(data)
    assert unusable_reason(path, 1600) is None
    path.write_bytes(data[: len(app1) + len(main) // 2])
    assert unusable_reason(path, 1600) == "truncated JPEG (no end-of-image marker)"


def test_images_colmap_converts_are_used_and_extracted(tmp_path: Path) -> None:
    """16-bit PNGs and float TIFFs (COLMAP converts both to 8 bits), an upper-case
    suffix and a symlink to an image elsewhere are used, and the extraction finds
    features in each; a non-image next to them is skipped with its reason."""
    images = tmp_path / "images"
    images.mkdir()
    views = texture_views(4)
    (images / "a.png").write_bytes(_encoded(".png", views[0].astype(np.uint16) * 257))
    (images / "b.tiff").write_bytes(_encoded(".tif", views[1].astype(np.float32) / 255))
    (images / "c.JPG").write_bytes(_encoded(".jpg", views[2]))
    elsewhere = tmp_path / "elsewhere.jpg"
    elsewhere.write_bytes(_encoded(".jpg", views[3]))
    (images / "d.jpg").symlink_to(elsewhere)
    (images / "notes.jpg").write_text("not an image\n")
    listing = list_images(images, 1600)
    assert listing.names == ["a.png", "b.tiff", "c.JPG", "d.jpg"]
    assert [(s.name, s.reason) for s in listing.skipped] == [
        ("notes.jpg", "not an image COLMAP can decode")
    ]
    database = build_database(images, tmp_path / "database.db", listing.names)
    with pycolmap.Database.open(str(database)) as db:
        counts = {i.name: db.num_keypoints_for_image(i.image_id) for i in db.read_all_images()}
    assert sorted(counts) == listing.names
    assert min(counts.values()) > 100, counts


def test_size_check_follows_the_downscaling(tmp_path: Path) -> None:
    """A 2000 x 40 image is used at full size and at 400 px (400 x 8 for SIFT), skipped
    at 300 px (300 x 6); an 8 x 8 image is used, 7 x 8 is not."""
    path = tmp_path / "x.png"
    path.write_bytes(_encoded(".png", np.zeros((40, 2000), np.uint8)))
    assert unusable_reason(path, 2000) is None
    assert unusable_reason(path, 400) is None
    assert unusable_reason(path, 300) == (
        "2000 x 40 px, 300 x 6 px once downscaled to at most 300 px: "
        "sides under 8 px have no features"
    )
    path.write_bytes(_encoded(".png", np.zeros((8, 8), np.uint8)))
    assert unusable_reason(path, 1600) is None
    path.write_bytes(_encoded(".png", np.zeros((8, 7), np.uint8)))
    assert unusable_reason(path, 1600) is not None


def test_api_refuses_max_image_size_out_of_range(tmp_path: Path) -> None:
    """RunOptions and build_database refuse what COLMAP's option cannot hold."""
    from colmap_trifocal.reconstruction.workflow import RunOptions

    for value in (2**31, 99, 0, -1):
        with pytest.raises(CalibrationError, match="max image size must be an integer"):
            RunOptions(max_image_size=value)
        with pytest.raises(CalibrationError, match="max image size must be an integer"):
            build_database(tmp_path, tmp_path / "database.db", max_image_size=value)
    assert not (tmp_path / "database.db").exists()


def test_run_skips_unusable_files_with_a_warning(
    tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """Three good images among a FIFO, a truncated JPEG, a 1 x 1 PNG, a folder and a
    dangling link named as images: the run completes on the three (exit 0), one
    ``warning: skipped`` line per file on stderr, the same in report.json."""
    images = _image_folder(tmp_path / "images")
    os.mkfifo(images / "fifo.png")
    (images / "cut.jpg").write_bytes(_encoded(".jpg", VIEW)[:3000])
    (images / "dot.png").write_bytes(_encoded(".png", np.zeros((1, 1), np.uint8)))
    (images / "folder.jpg").mkdir()
    (images / "gone.jpg").symlink_to("nowhere.jpg")
    result = run_main("run", images, tmp_path / "ws", "--refine", "none")
    assert result.returncode == 0, result.stderr
    skipped = [line for line in result.stderr.splitlines() if line.startswith("warning: skipped")]
    assert skipped == [
        "warning: skipped cut.jpg: truncated JPEG (no end-of-image marker)",
        "warning: skipped dot.png: 1 x 1 px: sides under 8 px have no features",
        "warning: skipped fifo.png: not a regular file (a FIFO)",
        "warning: skipped folder.jpg: not a regular file (a folder)",
        "warning: skipped gone.jpg: a dangling symlink (to nowhere.jpg)",
    ]
    assert "[ WARN" not in result.stderr  # OpenCV's reader is not used
    assert not any(line.startswith("error") for line in result.stderr.splitlines())
    report = json.loads((tmp_path / "ws" / "report.json").read_text())
    assert [s["name"] for s in report["skipped_images"]] == [
        "cut.jpg",
        "dot.png",
        "fifo.png",
        "folder.jpg",
        "gone.jpg",
    ]
    assert report["num_images"] == 3
    assert sorted(os.listdir(tmp_path / "ws")) == ["database.db", "report.json", "sparse"]


@pytest.mark.parametrize(
    "environment",
    [
        {},
        {"LANG": "C"},
        {"LC_ALL": "C"},
        {"LC_ALL": "C", "PYTHONUTF8": "0"},  # file system encoding ASCII
    ],
    ids=["default", "LANG=C", "LC_ALL=C", "LC_ALL=C PYTHONUTF8=0"],
)
def test_non_utf8_name_in_any_locale(environment: dict[str, str], tmp_path: Path) -> None:
    """``caf\\xe9.png`` (Latin-1 bytes) among the images: one line naming it, escaped, exit
    2, no workspace; cv2.imread on such a name ended the process with SIGSEGV. The
    process's locale decides how Python decodes the name, so each runs in a subprocess."""
    images = _image_folder(tmp_path / "images")
    (images / os.fsdecode(b"caf\xe9.png")).write_bytes(_encoded(".png", VIEW))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("LC_", "LANG", "PYTHONUTF8"))}
    done = subprocess.run(
        [sys.executable, "-m", "colmap_trifocal.cli", "run", images, tmp_path / "ws"],
        capture_output=True,
        text=True,
        timeout=300,
        env={**env, **environment},
    )
    result = CliResult(done.returncode, done.stdout, done.stderr)
    assert_one_error_line(result, "image file name is not valid UTF-8: ")
    assert "caf\\xe9.png (COLMAP stores image names as UTF-8 text" in result.stderr
    assert not (tmp_path / "ws").exists()


def test_utf8_name_under_an_ascii_file_system_encoding(tmp_path: Path) -> None:
    """``café.png`` is valid UTF-8 but, with ``LC_ALL=C PYTHONUTF8=0``, Python decodes it
    to surrogates that pycolmap cannot take: one line that says why (not a TypeError)."""
    images = _image_folder(tmp_path / "images")
    (images / "café.png").write_bytes(_encoded(".png", VIEW))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("LC_", "LANG", "PYTHONUTF8"))}
    done = subprocess.run(
        [sys.executable, "-m", "colmap_trifocal.cli", "run", images, tmp_path / "ws"],
        capture_output=True,
        text=True,
        timeout=300,
        env={**env, "LC_ALL": "C", "PYTHONUTF8": "0"},
    )
    result = CliResult(done.returncode, done.stdout, done.stderr)
    assert_one_error_line(result, "cannot be decoded with this process's file system encoding")
    assert not (tmp_path / "ws").exists()


# --------------------------------------------------------------------------- the workspace lock

_HOLDER = """
import sys
from pathlib import Path
from colmap_trifocal.reconstruction.workspace import workspace_lock
with workspace_lock(Path(sys.argv[1])):
    print("locked", flush=True)
    sys.stdin.readline()
"""


def test_workspace_in_use_is_left_alone(tmp_path: Path, run_main: Callable[..., CliResult]) -> None:
    """Another process holds the workspace's lock (a run in progress): ``run --overwrite``
    says so in one line, exit 2, and the workspace's files stay byte-identical (before,
    the second run removed the first one's database and died in a traceback)."""
    images = _image_folder(tmp_path / "images")
    workspace = tmp_path / "ws"
    (workspace / "sparse" / "0").mkdir(parents=True)
    (workspace / "database.db").write_bytes(b"the first run's database")
    (workspace / "report.json").write_text("{}\n")
    (workspace / "sparse" / "0" / "cameras.bin").write_bytes(b"model")
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(workspace)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "locked\n"
        before = _tree(workspace)
        result = run_main("run", images, workspace, "--overwrite")
        assert _tree(workspace) == before
    finally:
        assert holder.stdin is not None
        holder.stdin.close()
        assert holder.wait(timeout=60) == 0
    assert_one_error_line(result, f"workspace {workspace} is in use by another colmap-trifocal")
    assert not (workspace / LOCK_NAME).exists()  # the holder removed it when it ended


def test_lock_file_is_removed_and_not_content(
    tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """A lock file left by a killed run does not make the workspace "not empty"; the next
    run takes the lock and removes the file when it ends."""
    from colmap_trifocal.reconstruction.workspace import open_workspace

    workspace = tmp_path / "ws"
    workspace.mkdir()
    (workspace / LOCK_NAME).write_bytes(b"")
    with open_workspace(workspace, overwrite=False):
        assert os.listdir(workspace) == [LOCK_NAME]
    assert os.listdir(workspace) == []


@pytest.mark.slow  # two whole runs
def test_two_runs_on_one_workspace(tmp_path: Path) -> None:
    """Two ``run IMAGES WS --overwrite`` started together: one completes (exit 0, a full
    database and model); the other says the workspace is in use (exit 2, one line) or,
    where the first ended before it took the lock (a run of three images takes about a
    second), runs after it. Either way the workspace ends whole. The refusal itself is
    checked deterministically by ``test_workspace_in_use_is_left_alone``."""
    images = _image_folder(tmp_path / "images")
    workspace = tmp_path / "ws"
    command = [sys.executable, "-m", "colmap_trifocal.cli", "run", str(images), str(workspace)]
    first = subprocess.Popen(
        [*command, "--overwrite"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 120
    while not (workspace / LOCK_NAME).exists() and first.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    second = run_cli("run", images, workspace, "--overwrite")
    out, err = first.communicate(timeout=300)
    outcomes = sorted([(first.returncode, err), (second.returncode, second.stderr)])
    assert outcomes[0][0] == 0, outcomes
    if outcomes[1][0] != 0:
        assert_one_error_line(CliResult(outcomes[1][0], "", outcomes[1][1]), "is in use")
    assert sorted(os.listdir(workspace)) == ["database.db", "report.json", "sparse"]
    with pycolmap.Database.open(str(workspace / "database.db")) as db:
        assert db.num_images() == 3 and db.num_keypoints() > 0
    assert json.loads((workspace / "report.json").read_text())["num_images"] == 3
