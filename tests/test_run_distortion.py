"""`run` on a lens whose distortion the stored camera does not hold.

COLMAP's default camera (``SIMPLE_RADIAL``, k = 0) on a real lens biases every
intrinsic the constraints estimate; the calibration estimates k from the triplets'
calibrated bundle adjustment (:mod:`colmap_trifocal.intrinsics.lens.distortion`),
mapping starts from it, and ``run`` refines the distortion while mapping and in the
final bundle adjustment, as plain COLMAP does.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest
from conftest import handheld_lens_contents

from colmap_trifocal import reconstruct
from colmap_trifocal.cli.run import format_report
from colmap_trifocal.reconstruction.workflow import RunOptions, run_pipeline
from colmap_trifocal.synthetic.database import write_database

K1 = -0.05


def _default_camera_database(folder: Path, k1: float, k2: float = 0.0) -> tuple[Path, np.ndarray]:
    """The synthetic handheld set through a (k1, k2) lens, stored as COLMAP stores a new
    camera (SIMPLE_RADIAL, f = 1.2 · max(w, h), centred, k = 0), in ``folder``; and its
    true intrinsics."""
    contents, truth = handheld_lens_contents(k1, 0, k2)
    database = folder / "database.db"
    write_database(contents, database)
    return database, truth


@pytest.fixture(scope="module")
def barrel_lens_database(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A k1 = −0.05 lens behind COLMAP's default camera."""
    return _default_camera_database(tmp_path_factory.mktemp("lens"), K1)


def test_run_estimates_the_distortion_and_the_intrinsics(
    barrel_lens_database: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    database, truth = barrel_lens_database
    report = run_pipeline(None, tmp_path / "ws", RunOptions(database=database)).to_json()
    camera = report["cameras"][0]
    assert report["mapping"]["refined_while_mapping"]["distortion"]
    trifocal = np.array([camera["trifocal"][n] for n in ("fx", "fy", "cx", "cy")])
    refined = np.array([camera["refined"][n] for n in ("fx", "fy", "cx", "cy")])
    # Without k the constraints absorb the barrel distortion into the focal length
    # (+7.9 %); with k estimated from the triplets the focal length is 0.9 % off, and
    # bundle adjustment of the model refines both.
    assert abs(trifocal[0] / truth[0] - 1) < 0.015
    assert camera["trifocal_distortion"]["present"]
    assert abs(camera["trifocal_distortion"]["params"][0] - K1) < 0.005
    assert np.all(np.abs(refined / truth - 1) < 0.015)
    (k,) = camera["distortion"]
    assert abs(k - K1) < 0.01
    assert camera["mapped_model"] == "SIMPLE_RADIAL"  # one term holds this lens


@pytest.fixture(scope="module")
def k2_lens_database(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A k1 = −0.2, k2 = +0.1 lens behind COLMAP's default camera."""
    return _default_camera_database(tmp_path_factory.mktemp("k2"), -0.2, 0.1)


def test_run_maps_a_lens_that_needs_k2_in_the_model_that_holds_it(
    k2_lens_database: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    """The tracks determine RADIAL's k2 behind the SIMPLE_RADIAL camera, so the workspace
    maps the camera as RADIAL from that fit's (f, cx, cy, k1, k2), says so, and leaves
    the user's database as it was."""
    database, truth = k2_lens_database
    before = database.read_bytes()
    report = run_pipeline(None, tmp_path / "ws", RunOptions(database=database)).to_json()
    camera = report["cameras"][0]
    assert camera["trifocal_distortion"]["richer_model"] == "RADIAL"
    assert camera["model"] == "SIMPLE_RADIAL" and camera["mapped_model"] == "RADIAL"
    k1, k2 = camera["distortion"]
    assert abs(k1 + 0.2) < 0.02 and abs(k2 - 0.1) < 0.03
    refined = np.array([camera["refined"][n] for n in ("fx", "fy", "cx", "cy")])
    assert np.all(np.abs(refined - truth) < 0.01 * truth[0])
    assert "mapped as RADIAL" in format_report(report)
    assert database.read_bytes() == before
    with pycolmap.Database.open(str(tmp_path / "ws" / "database.db")) as workspace:
        assert {c.model.name for c in workspace.read_all_cameras()} == {"RADIAL"}


def test_the_estimate_applies_to_the_radial_camera_reconstruct_mapped(
    k2_lens_database: tuple[Path, np.ndarray],
) -> None:
    """``reconstruct`` maps the same lens as RADIAL; ``result.apply`` on its model writes
    the RADIAL fit's camera there (not a SIMPLE_RADIAL one, which it would refuse)."""
    database, _ = k2_lens_database
    reconstruction, (result,) = reconstruct(database)
    (camera_id,) = reconstruction.cameras
    assert reconstruction.camera(camera_id).model.name == "RADIAL"
    assert result.apply(reconstruction) == [camera_id]
    expected = result.mapping_cameras()[camera_id]
    assert reconstruction.camera(camera_id).params.tolist() == expected.params.tolist()
    assert expected.params.tolist()[3:] == result.lens_distortion["richer_params"]
