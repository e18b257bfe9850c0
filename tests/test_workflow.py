"""``run``: database in, calibrated and refined reconstruction out (pycolmap synthetic data)."""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_trifocal import CalibrationError
from colmap_trifocal.reconstruction.workflow import RunOptions, run_pipeline
from colmap_trifocal.synthetic.demo import make_demo_database


@pytest.fixture(scope="module")
def demo_database(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    path = tmp_path_factory.mktemp("demo") / "source.db"
    truth, _ = make_demo_database(path, seed=1, num_images=8, num_points=800)
    return path, truth


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _intrinsics(values: dict) -> np.ndarray:
    return np.array([values[k] for k in ("fx", "fy", "cx", "cy")])


def test_run_from_database(demo_database: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    source, truth = demo_database
    before = _sha256(source)
    workspace = tmp_path / "ws"
    report = run_pipeline(None, workspace, RunOptions(database=source)).to_json()
    assert _sha256(source) == before  # the user's database is copied, never changed
    assert report["num_registered_images"] == 8
    (camera,) = report["cameras"]
    trifocal, refined = _intrinsics(camera["trifocal"]), _intrinsics(camera["refined"])
    assert np.mean(np.abs(trifocal / truth - 1)) < 0.005
    assert np.mean(np.abs(refined / truth - 1)) < 0.005
    np.testing.assert_allclose(_intrinsics(camera["difference"]), refined - trifocal)
    assert camera["observable"] == dict.fromkeys(("fx", "fy", "cx", "cy"), True)
    assert camera["assumptions"] == [] and camera["warning"] is None
    assert 0 < report["mean_reprojection_error_px"] < 2.0
    assert json.loads((workspace / "report.json").read_text()) == report
    model = pycolmap.Reconstruction(workspace / "sparse" / "0")
    assert model.num_reg_images() == 8
    np.testing.assert_allclose(model.cameras[camera["camera_id"]].params, refined)


def test_stages_go_to_the_callback_not_to_stderr(
    demo_database: tuple[Path, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The library prints nothing: each long stage is announced to ``on_stage`` (the
    command line prints it)."""
    source, _ = demo_database
    stages: list[str] = []
    run_pipeline(None, tmp_path / "ws", RunOptions(database=source), on_stage=stages.append)
    assert stages == [
        "mapping (pycolmap incremental)",
        "bundle adjustment of focal lengths, principal points",
    ]
    assert capsys.readouterr() == ("", "")


def test_refine_none_keeps_the_estimate(
    demo_database: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    source, _ = demo_database
    report = run_pipeline(
        None, tmp_path / "ws", RunOptions(database=source, refine="none")
    ).to_json()
    (camera,) = report["cameras"]
    np.testing.assert_allclose(_intrinsics(camera["refined"]), _intrinsics(camera["trifocal"]))


def test_the_report_counts_the_images_mapping_left_out(
    demo_database: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    """An image without verified matches is not registered: ``registered 7/8``, where the
    mapper's model (its 7 images) said 7/7 before."""
    source, _ = demo_database
    copy = tmp_path / "database.db"
    shutil.copyfile(source, copy)
    con = sqlite3.connect(copy)
    with con:  # image 8's verified matches gone: pair ids id1 * 2**31 - 1 + id2, id1 < id2
        con.execute("DELETE FROM two_view_geometries WHERE pair_id % 2147483647 = 8")
    con.close()
    report = run_pipeline(None, tmp_path / "ws", RunOptions(database=copy)).to_json()
    assert (report["num_registered_images"], report["num_images"]) == (7, 8)


def test_existing_model_gets_estimate_and_refinement(
    demo_database: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    source, truth = demo_database
    first = tmp_path / "first"
    run_pipeline(None, first, RunOptions(database=source, refine="none"))
    model = pycolmap.Reconstruction(first / "sparse" / "0")
    for camera in model.cameras.values():
        camera.params = np.asarray(camera.params) * 1.03  # a wrong camera in the model
    wrong = tmp_path / "wrong_model"
    wrong.mkdir()
    model.write(wrong)
    report = run_pipeline(
        None, tmp_path / "second", RunOptions(database=source, model=wrong)
    ).to_json()
    (camera,) = report["cameras"]
    assert np.mean(np.abs(_intrinsics(camera["refined"]) / truth - 1)) < 0.005


def test_workspace_with_other_content_is_refused(
    demo_database: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    source, _ = demo_database
    workspace = tmp_path / "ws"
    workspace.mkdir()
    (workspace / "notes.txt").write_text("mine")
    with pytest.raises(CalibrationError, match="not empty"):
        run_pipeline(None, workspace, RunOptions(database=source))
    run_pipeline(None, workspace, RunOptions(database=source, refine="none", overwrite=True))
    assert (workspace / "notes.txt").read_text() == "mine"  # --overwrite keeps foreign files
    assert (workspace / "report.json").is_file()


def test_image_folder_errors(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="image folder not found"):
        run_pipeline(tmp_path / "missing", tmp_path / "ws", RunOptions())
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(CalibrationError, match="no images"):
        run_pipeline(empty, tmp_path / "ws", RunOptions())
    broken = tmp_path / "broken"
    broken.mkdir()
    for name in ("a.jpg", "b.jpg", "c.jpg"):
        (broken / name).write_bytes(b"not a jpeg")
    with pytest.raises(CalibrationError, match="has 0 usable image.*not an image COLMAP can"):
        run_pipeline(broken, tmp_path / "ws", RunOptions())
    assert not (tmp_path / "ws").exists()  # nothing created before the input is checked


def test_model_without_database(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="--model needs the --database"):
        run_pipeline(None, tmp_path / "ws", RunOptions(model=tmp_path))
