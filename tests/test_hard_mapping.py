"""Issue 13, item 4: `run` on a straight drive, where plain COLMAP builds no model.

A camera looking along a straight drive sees every pair's baseline along its optical
axis (|t_z| ≈ 1), which COLMAP's ``init_max_forward_motion`` (0.95) rejects at any
triangulation angle. ``run`` seeds the retries with the widest pair of the
calibration's best triplets and lifts that limit for it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_trifocal.reconstruction.mapping import (
    SEEDED_MAX_FORWARD_MOTION,
    measure_pairs,
)
from colmap_trifocal.reconstruction.workflow import RunOptions, run_pipeline
from colmap_trifocal.synthetic.database import scene_contents, write_database
from colmap_trifocal.synthetic.driving import driving_sequence

NUM_IMAGES = 12


@pytest.fixture(scope="module")
def straight_drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A 12-frame straight drive (1 m steps, KITTI camera) stored with COLMAP's default
    camera (f = 1.2 · 1241 px, centred); returns the database and the true K."""
    scene = driving_sequence(NUM_IMAGES, 0.0, seed=0, num_points=3000)
    default = np.array([1.2 * scene.width, 1.2 * scene.width, scene.width / 2, scene.height / 2])
    database = tmp_path_factory.mktemp("drive") / "drive.db"
    write_database(scene_contents(scene), database, intrinsics=default)
    return database, scene.intrinsics


def test_every_pair_of_a_straight_drive_is_forward_motion(
    straight_drive: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    """The cause: COLMAP's own two-view estimate (true K) puts every baseline along the
    optical axis, beyond the 0.95 limit, and the widest pair spans about 4°."""
    database, truth = straight_drive
    copy = tmp_path / "true_k.db"
    write_database(
        scene_contents(driving_sequence(NUM_IMAGES, 0.0, seed=0, num_points=3000)), copy, truth
    )
    pairs = [(1, j) for j in range(2, NUM_IMAGES + 1)]
    measured = measure_pairs(copy, pairs)
    assert len(measured) == len(pairs)
    assert min(p.forward_motion for p in measured) > 0.999
    assert 3.0 < max(p.tri_angle for p in measured) < 8.0


@pytest.mark.slow  # plain mapping, then run with its retries (about 20 s)
def test_plain_colmap_has_no_model_and_run_registers_the_drive(
    straight_drive: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    database, truth = straight_drive
    plain = tmp_path / "plain.db"
    plain.write_bytes(database.read_bytes())
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = 1
    models = pycolmap.incremental_mapping(plain, tmp_path, tmp_path / "plain", options)
    assert max((m.num_reg_images() for m in models.values()), default=0) < NUM_IMAGES // 2

    report = run_pipeline(None, tmp_path / "ws", RunOptions(database=database)).to_json()
    assert report["num_registered_images"] >= NUM_IMAGES - 1
    mapping = report["mapping"]
    first, *retries = mapping["attempts"]
    assert first["init_pair"] is None and first["num_registered_images"] < NUM_IMAGES // 2
    seeded = mapping["seeded_pair"]
    assert seeded is not None and seeded["forward_motion"] > 0.95
    assert retries[-1]["init_pair"] == seeded["image_ids"]
    assert retries[-1]["init_max_forward_motion"] == SEEDED_MAX_FORWARD_MOTION
    assert "seeded" in mapping["note"]  # the command line prints it
    camera = report["cameras"][0]
    refined = np.array([camera["refined"][name] for name in ("fx", "fy", "cx", "cy")])
    error = np.abs(refined / truth - 1)
    # Measured: 0.18 / 1.12 / 0.07 / 0.23 %.
    assert error.max() < 0.03 and error.mean() < 0.015
