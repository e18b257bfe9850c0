"""The command line as a user runs it: exit codes, one-line errors, JSON, --write."""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from conftest import synthesize

PARAMS = [1100.0, 1250.0, 530.0, 370.0]
PRIOR = "1140,1210,545,360"


def run(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "colmap_trifocal.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
    )


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def database(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cli") / "database.db"
    synthesize(path, "PINHOLE", PARAMS)
    return path


def assert_one_line_error(result: subprocess.CompletedProcess, fragment: str) -> None:
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ") and fragment in lines[0], lines[0]
    assert "Traceback" not in result.stderr


def test_calibrate_writes_json(database: Path, tmp_path: Path) -> None:
    before = _sha256(database)
    out = tmp_path / "result.json"
    result = run("calibrate", database, "--prior", PRIOR, "--json", out, "--seed", "3")
    assert result.returncode == 0, result.stderr
    (entry,) = json.loads(out.read_text())
    assert set(entry) >= {
        "camera_id",
        "model",
        "method",
        "fx",
        "fy",
        "cx",
        "cy",
        "std",
        "observable",
        "num_triplets",
        "num_inlier_triplets",
        "seconds",
    }
    assert set(entry["std"]) == set(entry["observable"]) == {"fx", "fy", "cx", "cy"}
    assert entry["method"] == "msac-opt" and entry["model"] == "PINHOLE"
    np.testing.assert_allclose([entry[k] for k in ("fx", "fy", "cx", "cy")], PARAMS, rtol=1e-5)
    assert "PINHOLE" in result.stdout
    assert _sha256(database) == before


def test_write_flag(database: Path, tmp_path: Path) -> None:
    copy = tmp_path / "db.db"
    copy.write_bytes(database.read_bytes())
    result = run("calibrate", copy, "--prior", PRIOR, "--write")
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "db.db.bak").read_bytes() == database.read_bytes()
    with pycolmap.Database.open(str(copy)) as db:
        np.testing.assert_allclose(db.read_all_cameras()[0].params, PARAMS, rtol=1e-5)


def test_write_refused_on_read_only_database(database: Path, tmp_path: Path) -> None:
    copy = tmp_path / "db.db"
    copy.write_bytes(database.read_bytes())
    copy.chmod(0o444)
    before = _sha256(copy)
    assert_one_line_error(run("calibrate", copy, "--prior", PRIOR, "--write"), "read-only")
    assert _sha256(copy) == before


def test_missing_database(tmp_path: Path) -> None:
    missing = tmp_path / "nope.db"
    assert_one_line_error(run("calibrate", missing), "not found")
    assert not missing.exists()


def test_not_a_database(tmp_path: Path) -> None:
    text = tmp_path / "notes.db"
    text.write_text("hello\n")
    assert_one_line_error(run("calibrate", text), "not an SQLite database")
    assert text.read_text() == "hello\n"


def test_fewer_than_three_images(tmp_path: Path) -> None:
    path = tmp_path / "two.db"
    synthesize(path, "PINHOLE", PARAMS, frames=2)
    assert_one_line_error(run("calibrate", path), "only 2 images, at least 3")


def test_no_verified_matches(database: Path, tmp_path: Path) -> None:
    copy = tmp_path / "db.db"
    copy.write_bytes(database.read_bytes())
    with sqlite3.connect(copy) as con:
        con.execute("DELETE FROM two_view_geometries")
    assert_one_line_error(run("calibrate", copy), "verified matches")


def test_no_triplet(tmp_path: Path) -> None:
    path = tmp_path / "sparse.db"
    synthesize(path, "PINHOLE", PARAMS, points=30)
    assert_one_line_error(run("calibrate", path), "no image triplet")


@pytest.mark.parametrize(
    ("prior", "fragment"),
    [
        ("1100,1250,530", "expected 4 values"),
        ("1100,1250,530,370,1", "expected 4 values"),
        ("a,b,c,d", "expected four numbers"),
        ("nan,1250,530,370", "finite"),
        ("0,1250,530,370", "positive"),
    ],
)
def test_malformed_prior(database: Path, prior: str, fragment: str) -> None:
    assert_one_line_error(run("calibrate", database, "--prior", prior), fragment)


def test_unknown_method(database: Path) -> None:
    assert_one_line_error(run("calibrate", database, "--method", "magic"), "invalid choice")


def test_json_into_missing_folder(database: Path, tmp_path: Path) -> None:
    out = tmp_path / "missing" / "r.json"
    assert_one_line_error(run("calibrate", database, "--json", out), "does not exist")


def test_demo_runs_the_pipeline(tmp_path: Path) -> None:
    result = run("demo", "--keep", tmp_path)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    trifocal = float(lines[-1].split(":")[1].split("%")[0])
    refined = float(lines[-2].split("BA-refined")[1].split("%")[0])
    # From a 5 % prior with 0.5 px noise and 20 % wrong matches.
    assert trifocal < 0.5 and refined < 0.5
    assert "registered 10 images" in result.stdout
    assert (tmp_path / "demo" / "sparse" / "0" / "cameras.bin").is_file()
    report = json.loads((tmp_path / "demo" / "report.json").read_text())
    assert report["num_registered_images"] == 10
    assert set(report["seconds"]) == {"features", "calibrate", "mapping", "refine"}
    # COLMAP's own INFO lines only with -vv (pycolmap's BA resets glog's level).
    assert not [line for line in result.stderr.splitlines() if line.startswith("I20")]


def test_show_renders_png(tmp_path: Path) -> None:
    assert run("demo", "--keep", tmp_path).returncode == 0
    png = tmp_path / "view.png"
    result = run("show", tmp_path / "demo" / "sparse" / "0", "--png", png)
    if result.returncode != 0 and "offscreen" in result.stderr and os.environ.get("CI") != "true":
        pytest.skip(result.stderr.strip())
    assert result.returncode == 0, result.stderr
    image = cv2.imread(str(png))
    assert image is not None and image.shape[2] == 3
    assert (image < 250).any(axis=2).mean() > 0.002  # not a blank white background


def test_run_renders_png(tmp_path: Path) -> None:
    """``run ... --png OUT`` (DESIGN.md): the pipeline, then the model rendered offscreen."""
    assert run("demo", "--keep", tmp_path).returncode == 0
    png = tmp_path / "run.png"
    workspace = tmp_path / "ws"
    result = run(
        "run", tmp_path / "no-images", workspace, "--database", tmp_path / "demo" / "database.db",
        "--refine", "none", "--png", png,
    )  # fmt: skip
    if result.returncode != 0 and "offscreen" in result.stderr and os.environ.get("CI") != "true":
        pytest.skip(result.stderr.strip())
    assert result.returncode == 0, result.stderr
    assert f"wrote {png}" in result.stdout and (workspace / "report.json").is_file()
    image = cv2.imread(str(png))
    assert image is not None and (image < 250).any(axis=2).mean() > 0.002
    refused = run("run", tmp_path, tmp_path / "ws2", "--png", tmp_path / "missing" / "x.png")
    assert_one_line_error(refused, "cannot write --png")


def test_show_missing_model(tmp_path: Path) -> None:
    assert_one_line_error(run("show", tmp_path / "nope"), "nope")
