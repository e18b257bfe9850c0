"""A SIFT database built on many threads is the one built on one thread; a seeded build is
the same every time, and so is ``run``'s from the same images and seed.

pycolmap's extraction threads write the images they create in the order they finish; the
build imports the images in name order first (``database.features``), so the ids, pair ids
and everything keyed by them do not depend on the threads.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from conftest import (
    EXACT_SEARCH_FEATURES,
    CliResult,
    database_rows,
    small_texture_views,
    texture_views,
)

from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.database import matching
from colmap_trifocal.database.features import build_database

#: Tables whose rows hold no ids of their own: created the same way on every build.
TABLES = ("cameras", "images", "keypoints", "descriptors", "matches", "two_view_geometries")


def _images(folder: Path) -> Path:
    """Seven small views of one texture (under pycolmap's exact-search size,
    ``conftest.EXACT_SEARCH_FEATURES``), the first by name in a corner of a plain
    1200 x 900 canvas (its SIFT takes longest, so on two threads the others finish before
    it)."""
    folder.mkdir()
    for k, view in enumerate(small_texture_views(7)):
        if k == 0:
            canvas = np.full((900, 1200), 128, np.uint8)
            canvas[: view.shape[0], : view.shape[1]] = view
            view = canvas
        cv2.imwrite(str(folder / f"{k}.png"), view)
    return folder


def _exact_search(rows: dict[str, list[tuple]]) -> bool:
    """Whether every image of a database's rows has fewer features than pycolmap's matcher
    searches exactly (the ``keypoints`` rows: image id, rows, ...)."""
    return all(row[1] < EXACT_SEARCH_FEATURES for row in rows["keypoints"])


def _ids_by_name(database: Path) -> dict[str, int]:
    with pycolmap.Database.open(str(database)) as db:
        return {image.name: image.image_id for image in db.read_all_images()}


def test_a_build_on_two_threads_holds_what_one_thread_builds(tmp_path: Path) -> None:
    images = _images(tmp_path / "images")
    options = {"camera_model": "SIMPLE_RADIAL", "camera_mode": "auto", "seed": 0}
    one = build_database(images, tmp_path / "one.db", num_threads=1, **options)
    two = build_database(images, tmp_path / "two.db", num_threads=2, **options)
    chunked = build_database(
        images, tmp_path / "chunked.db", num_threads=2, progress=True, **options
    )
    assert _ids_by_name(two) == {f"{k}.png": k + 1 for k in range(7)}
    rows = [database_rows(path) for path in (one, two, chunked)]
    assert _exact_search(rows[0])
    for table in TABLES:
        assert rows[1][table] == rows[0][table], table
        assert rows[2][table] == rows[0][table], table
    verified = rows[0]["two_view_geometries"]
    assert len(verified) == 21 and all(row[1] > 0 for row in verified)  # every pair verified


def test_run_builds_the_same_database_from_the_same_images_and_seed(
    tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """Views of one translated plane are degenerate for the verification: unseeded, its
    RANSAC found 55, 799 or 1232 inliers for one pair from build to build."""
    images = _images(tmp_path / "images")
    for name in ("a", "b"):
        result = run_main("run", images, tmp_path / name, "--refine", "none", "--seed", 3)
        assert result.returncode == 0, result.stderr
    first, second = (database_rows(tmp_path / name / "database.db") for name in ("a", "b"))
    assert _exact_search(first)
    for table in TABLES:
        assert first[table] == second[table], table
    assert np.sum([row[1] for row in first["two_view_geometries"]]) > 0


def test_image_names_with_spaces_are_matched(tmp_path: Path) -> None:
    """COLMAP reads a pairs file's lines as two names split at a space: the workers' copies
    name each image by its id, so images whose names hold spaces are matched (before, on
    the progress path, every pair of ``view 0.png``, ``view 1.png``, ... had no match)."""
    folder = tmp_path / "images"
    folder.mkdir()
    for k, view in enumerate(small_texture_views(5)):
        cv2.imwrite(str(folder / f"view {k}.png"), view)
    options = {"camera_model": "SIMPLE_RADIAL", "camera_mode": "auto", "seed": 0}
    one = database_rows(build_database(folder, tmp_path / "one.db", num_threads=1, **options))
    two = database_rows(
        build_database(folder, tmp_path / "two.db", num_threads=2, progress=True, **options)
    )
    assert len(one["matches"]) == 10 and all(row[1] > 0 for row in one["matches"])
    for table in TABLES:
        assert two[table] == one[table], table
    with pycolmap.Database.open(str(tmp_path / "two.db")) as db:
        assert sorted(image.name for image in db.read_all_images()) == [
            f"view {k}.png" for k in range(5)
        ]


def test_pairs_without_matches_come_back_from_every_worker(tmp_path: Path) -> None:
    """Views of two textures: the pairs across them have no match, and their empty rows
    (which pycolmap's ``read_all_matches`` leaves out) come back from the second worker's
    copy as a build on one thread writes them."""
    folder = tmp_path / "images"
    folder.mkdir()
    views = texture_views(4) + texture_views(3, seed=1)
    for k, view in enumerate(views):
        small = cv2.resize(view, (100, 75), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(folder / f"{k}.png"), small)
    options = {"camera_model": "SIMPLE_RADIAL", "camera_mode": "auto", "seed": 0}
    one = database_rows(build_database(folder, tmp_path / "one.db", num_threads=1, **options))
    two = database_rows(build_database(folder, tmp_path / "two.db", num_threads=2, **options))
    assert _exact_search(one)
    for table in TABLES:
        assert two[table] == one[table], table
    empty = {row[0] for row in one["matches"] if row[1] == 0}
    # (4, 5) is in the second half of the 21 pairs, the second worker's share.
    assert pycolmap.image_pair_to_pair_id(4, 5) in empty
    assert len(one["matches"]) == len(one["two_view_geometries"]) == 21


@pytest.mark.parametrize(
    ("worker", "message"),
    [
        (
            "import sys; sys.stderr.write('F1203 sift.cc:42] Check failed: boom\\n'); sys.exit(3)",
            "F1203 sift.cc:42] Check failed: boom (a worker stopped, exit status 3)",
        ),
        (
            "import os, signal; os.kill(os.getpid(), signal.SIGKILL)",
            "a worker stopped, killed by signal 9",
        ),
    ],
)
def test_a_worker_that_fails_is_one_error(
    worker: str, message: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A matching worker that ends in failure (COLMAP aborts the process it runs in) is
    one CalibrationError with the last line of its log; the workers' files are removed."""
    images = _images(tmp_path / "images")
    monkeypatch.setattr(matching, "_WORKER", worker)
    with pytest.raises(CalibrationError) as error:
        build_database(images, tmp_path / "database.db", camera_mode="auto", num_threads=2, seed=0)
    database = tmp_path / "database.db"
    assert str(error.value) == f"cannot match the image pairs of {database}: {message}"
    assert len(str(error.value).splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["database.db", "images"]


@pytest.mark.parametrize(
    ("pairs", "workers", "database_bytes", "free_bytes", "count"),
    [
        (45, 2, 17 << 20, 100 << 30, 2),  # entry-P10 on two cores
        (45, 64, 17 << 20, 100 << 30, 12),  # one worker per 4 pairs
        (780, 64, 1 << 30, 10 << 30, 5),  # 5 copies of 1 GB in half of 10 GB free
        (780, 64, 1 << 30, 1 << 30, 1),  # room for no copy: still one worker
        (3, 8, 1 << 20, 1 << 30, 1),  # too few pairs for a second worker
        (0, 8, 1 << 20, 1 << 30, 1),
    ],
)
def test_how_many_workers_match(
    pairs: int, workers: int, database_bytes: int, free_bytes: int, count: int
) -> None:
    """Workers are bounded by the cores, the pairs and the room for the database's copies."""
    assert matching.worker_count(pairs, workers, database_bytes, free_bytes) == count
