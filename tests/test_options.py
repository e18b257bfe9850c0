"""The Python API refuses bad options when they are built: CalibrationError, one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from colmap_trifocal import CalibrationError, CalibrationOptions, calibrate_database
from colmap_trifocal.synthetic.demo import make_demo_database

BAD = [
    ({"seed": -1}, "--seed must be an integer"),
    ({"seed": 1.5}, "--seed must be an integer"),
    ({"seed": 2**70}, "--seed must be an integer"),
    ({"seed": True}, "--seed must be an integer"),
    ({"prior": "540,540,320,240"}, "--prior must be four numbers"),
    ({"prior": (540, 540, 320)}, "--prior must be four numbers"),
    ({"prior": (540, 540, 320, "x")}, "--prior must be four numbers"),
    ({"prior": (540, float("nan"), 320, 240)}, "values must be finite"),
    ({"prior": (0, 540, 320, 240)}, "focal lengths positive"),
    ({"camera_ids": 1}, "--camera-id: a list of integer camera ids"),
    ({"camera_ids": ["1"]}, "--camera-id: a list of integer camera ids"),
    ({"tau": float("nan")}, "tau must be a finite number above 0"),
    ({"tau": 0.0}, "tau must be a finite number above 0"),
    ({"max_triplets": 0}, "--max-triplets must be at least 1"),
    ({"min_tracks": 3}, "min_tracks must be an integer of at least 7"),
    ({"workers": 0}, "workers must be a positive integer"),
    ({"method": "magic"}, "unknown method 'magic'"),
    ({"group": "nope"}, "unknown --group 'nope'"),
]


@pytest.mark.parametrize(("values", "fragment"), BAD, ids=[repr(v) for v, _ in BAD])
def test_bad_option_refused_when_built(values: dict, fragment: str) -> None:
    with pytest.raises(CalibrationError) as raised:
        CalibrationOptions(**values)
    message = str(raised.value)
    assert fragment in message and "\n" not in message


def test_good_options_are_normalised() -> None:
    options = CalibrationOptions(prior=np.array([540, 541, 320, 240]), seed=np.int64(3))
    assert CalibrationOptions(seed=2380376695).seed == 2380376695  # the evaluation's seeds
    assert options.prior == (540.0, 541.0, 320.0, 240.0)
    assert all(type(v) is float for v in options.prior)
    assert CalibrationOptions(prior=[540, 541, 320.5, 240]).prior == (540.0, 541.0, 320.5, 240.0)


def test_options_of_another_type_refused(tmp_path: Path) -> None:
    database = tmp_path / "demo.db"
    make_demo_database(database, seed=0)
    before = database.read_bytes()
    with pytest.raises(CalibrationError, match="options must be a CalibrationOptions, got dict"):
        calibrate_database(database, {"seed": 1})  # type: ignore[arg-type]
    assert database.read_bytes() == before
