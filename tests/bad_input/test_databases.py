"""Database files: missing, not SQLite, not COLMAP's, corrupt blobs, cameras no calibration
can use; and valid databases that must be accepted.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import CliResult, database_rows, run_cli

from bad_input.builders import (
    FIRST_PAIR_ID,
    MAX_NUM_IMAGES,
    all_degenerate,
    blob_edit,
    colmap_pair_id,
    copy_good,
    empty_colmap,
    empty_file,
    fisheye,
    hot_journal,
    identical_images,
    jittered_copies,
    keypoint_value,
    other_tool,
    random_consistent_matches,
    random_inconsistent_matches,
    run_database,
    stored_params,
    stored_radial,
    synthetic_database,
    text_file,
    truncated_sqlite,
    user_table,
    utf16_copy,
    without_rows,
)
from bad_input.table import (
    PARAMS,
    PRIOR,
    PRIOR_VALUES,
    QUICK,
    QUICK_READ,
    Case,
    camera_params,
    listing,
    sha256,
    table_test,
)

CASES: dict[str, Case] = {
    "missing path": Case(lambda folder, _: folder / "nope.db", "database not found"),
    "directory": Case(lambda folder, _: folder, "is a directory"),
    "text file named .db": Case(text_file, "not an SQLite database"),
    "empty file": Case(empty_file, "not an SQLite database"),
    "truncated SQLite": Case(truncated_sqlite, "truncated or corrupt"),
    "another tool's SQLite": Case(other_tool, "not a COLMAP database (no table cameras"),
    "COLMAP database without images": Case(empty_colmap, "database has no images"),
    "images without keypoints": Case(
        without_rows("keypoints", "descriptors", "matches", "two_view_geometries"),
        "database has no keypoints (run COLMAP feature extraction first)",
    ),
    "keypoints without matches": Case(
        without_rows("matches", "two_view_geometries"),
        "no verified matches (run COLMAP feature matching first)",
    ),
    "matches never verified": Case(
        without_rows("two_view_geometries"), "15 image pairs have raw matches"
    ),
    "all pairs DEGENERATE": Case(
        all_degenerate, "of 15 verified image pairs 15 are DEGENERATE or WATERMARK"
    ),
    "outlier matches, no consistent triplet": Case(
        random_inconsistent_matches, "no image triplet with at least 30 three-view tracks"
    ),
    "outlier matches, no consistent tensor": Case(
        random_consistent_matches, "no triplet gave a consistent trifocal tensor"
    ),
    "20 points, no triplet": Case(
        synthetic_database(points=20), "no image triplet with at least 30 three-view tracks"
    ),
    "single image": Case(synthetic_database(1), "database has only 1 image, at least 3"),
    "two images": Case(synthetic_database(2), "database has only 2 images, at least 3"),
    "identical images": Case(identical_images, "3 are duplicates (the matched keypoints coincide"),
    "fisheye camera": Case(fisheye, "fisheye camera model OPENCV_FISHEYE is not supported"),
    "keypoint NaN": Case(keypoint_value(np.nan), "keypoint(s) of image 1"),
    "keypoint inf": Case(keypoint_value(np.inf), "are NaN or infinite"),
    "keypoints with a negative row count": Case(
        blob_edit("UPDATE keypoints SET rows = -5 WHERE image_id = 1"),
        "corrupt database: keypoints",
    ),
    "stored params NaN": Case(stored_params(np.nan, 1250, 530, 370), "stored params (nan,"),
    "stored fx = fy = 0": Case(stored_params(0, 0, 530, 370), "give --prior or --no-prior"),
    "RuntimeWarning: stored focal 1e300": Case(
        stored_params(1e300, 1e300, 530, 370), "from the stored camera"
    ),
    "0x0 camera (exit 0 before)": Case(
        blob_edit("UPDATE cameras SET width = 0, height = 0"), "image size of 0x0"
    ),
    "0x0 camera with --no-prior": Case(
        blob_edit("UPDATE cameras SET width = 0, height = 0"), "image size of 0x0", ("--no-prior",)
    ),
    "hot rollback journal": Case(hot_journal, "hot rollback journal"),
    "read-only database with --write": Case(
        copy_good, "cannot write to read-only database", ("--write",), read_only=True
    ),
    "verified pair of image id 2**31 - 1": Case(
        blob_edit(FIRST_PAIR_ID, colmap_pair_id(MAX_NUM_IMAGES, 1)),
        "verified image pair 4611686014132420610 refers to image id 2147483647, which the",
    ),
    "verified pair of a missing image": Case(
        blob_edit(FIRST_PAIR_ID, colmap_pair_id(1, 99)), "refers to image id 99, which the database"
    ),
    "keypoints of 1 column": Case(  # x and y as 2 rows each: pycolmap read them as (n, 1)
        blob_edit("UPDATE keypoints SET rows = rows * cols, cols = 1 WHERE image_id = 2"),
        "keypoints of image 2 (camera000001_frame000001.png) have 1 column, COLMAP writes 2, 4",
    ),
    "inlier matches of 1 column": Case(
        blob_edit("UPDATE two_view_geometries SET rows = rows * cols, cols = 1"),
        "the inlier matches of image pair 2147483649 have 1 column, COLMAP writes 2",
    ),
    "newline in the path": Case(
        lambda f, _: f / "new\nline.db",
        "data/new\\nline.db",  # escaped: backslash, n
    ),
    "empty folder: neither a database nor a model": Case(
        lambda f, _: f, "not a COLMAP model folder either (no cameras, images, points3D"
    ),
    "a glob pattern that matches nothing": Case(
        lambda f, _: f / "*.sqlite", "no database or model folder matches"
    ),
    # ----- issue 37: a stored distortion that folds the image over
    "stored k1 = -1000 (the lens model folds over)": Case(
        stored_radial(-1000.0), "its stored distortion (k -1000) cannot be undone at"
    ),
    "stored k1 = -3": Case(stored_radial(-3.0), "its stored distortion (k -3) cannot be undone"),
    # ----- issue 37: a refused --database leaves no workspace behind
    "run --database truncated: no workspace made": Case(
        truncated_sqlite, "truncated or corrupt", argv=run_database()
    ),
    "run --database without images: no workspace made": Case(
        empty_colmap, "database has no images", argv=run_database()
    ),
    "DATABASE is ., with --json": Case(
        copy_good,
        "database path is a directory: .",
        argv=lambda f, p, w: ("calibrate", ".", "--json", f / "out.json"),
    ),
}


test_bad_input = table_test(CASES)


def test_jittered_copies_determine_nothing_and_write_nothing(
    tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """Three copies of one image with 1.5 px jitter pass the duplicate check (about 2.5 px
    apart) but have no parallax: every parameter is reported undetermined, the prior is
    returned, and ``--write`` leaves the database as it was (no backup either)."""
    path = jittered_copies(tmp_path, tmp_path)
    before, files = sha256(path), listing(tmp_path)
    out = tmp_path / "result.json"
    result = run_main("calibrate", path, "--prior", PRIOR, "--write", "--json", out)
    assert result.returncode == 0, result.stderr
    (warning,) = result.stderr.strip().splitlines()
    assert warning.startswith("warning: camera 1: fx (") and "too similar images" in warning
    assert "camera 1 not written: the images determine none of its values" in result.stdout
    (entry,) = json.loads(out.read_text())
    assert not any(entry["observable"].values()) and not any(entry["estimated"].values())
    np.testing.assert_allclose([entry[k] for k in ("fx", "fy", "cx", "cy")], PRIOR_VALUES)
    assert sha256(path) == before and listing(tmp_path) == sorted([*files, "result.json"])


@pytest.mark.slow  # the whole run: calibration, mapping, bundle adjustment
def test_run_copies_what_is_still_in_the_wal(good_database: Path, tmp_path: Path) -> None:
    """``run --database`` copies with SQLite's backup API: committed rows still in the
    ``-wal`` reach the workspace's copy (a copy of the main file lost the verified
    matches, and mapping found none; issue 15, item 4). The input stays as it was."""
    source = tmp_path / "input" / "database.db"
    source.parent.mkdir()
    shutil.copyfile(good_database, source)
    con = sqlite3.connect(source, isolation_level=None)
    try:
        assert con.execute("PRAGMA journal_mode=WAL").fetchone() == ("wal",)
        rows = con.execute("SELECT * FROM two_view_geometries").fetchall()
        con.execute("DELETE FROM two_view_geometries")
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")  # the main file has no matches now
        con.execute("PRAGMA wal_autocheckpoint=0")
        marks = ",".join("?" * len(rows[0]))
        con.executemany(f"INSERT INTO two_view_geometries VALUES ({marks})", rows)
        wal = source.with_name("database.db-wal")
        assert wal.stat().st_size > 0  # committed, and only in the -wal while con is open
        before = sha256(source), sha256(wal)
        workspace = tmp_path / "ws"
        result = run_cli("run", tmp_path / "no-images", workspace, "--database", source)
        assert (sha256(source), sha256(wal)) == before
    finally:
        con.close()
    assert result.returncode == 0, result.stderr
    copy = sqlite3.connect(workspace / "database.db")
    try:
        assert copy.execute("SELECT COUNT(*) FROM two_view_geometries").fetchone() == (len(rows),)
    finally:
        copy.close()
    report = json.loads((workspace / "report.json").read_text())
    assert report["num_registered_images"] == 6


#: Valid databases that were refused as "truncated or corrupt?" (the snapshot copied every
#: table with its SQL, unquoted names, into a database of another text encoding).
VALID_VARIANTS = {
    'a user table named we"ird': user_table(
        'CREATE TABLE "we""ird" (x); INSERT INTO "we""ird" VALUES (1);'
    ),
    "an FTS5 table": user_table(
        "CREATE VIRTUAL TABLE notes USING fts5(body); INSERT INTO notes VALUES ('hello');"
    ),
    "an R*Tree table": user_table(
        "CREATE VIRTUAL TABLE boxes USING rtree(id, x0, x1); INSERT INTO boxes VALUES (1, 0, 1);"
    ),
    "UTF-16 text": utf16_copy,
}


@pytest.mark.parametrize("variant", list(VALID_VARIANTS))
def test_valid_database_variants_are_calibrated_and_written(
    variant: str, good_database: Path, tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """A COLMAP database that also holds other tables, or stores text as UTF-16, is read
    (byte-identical) and written (``--write``: backup of the same rows, the new params)."""
    path = VALID_VARIANTS[variant](tmp_path, good_database)
    before, rows = sha256(path), database_rows(path)
    out = tmp_path / "result.json"
    result = run_main("calibrate", path, *QUICK_READ, "--json", out)
    assert (result.returncode, result.stderr) == (0, ""), result.stderr
    (entry,) = json.loads(out.read_text())
    np.testing.assert_allclose([entry[k] for k in ("fx", "fy", "cx", "cy")], PARAMS, rtol=1e-4)
    assert sha256(path) == before
    result = run_main("calibrate", path, *QUICK)
    assert (result.returncode, result.stderr) == (0, ""), result.stderr
    assert "wrote 1 camera(s)" in result.stdout
    assert database_rows(path.with_name("database.db.bak")) == rows
    np.testing.assert_allclose(camera_params(path), PARAMS, rtol=1e-4)
