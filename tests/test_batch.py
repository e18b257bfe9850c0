"""``calibrate`` with several inputs (JSON lines, locally and on a Dask cluster) and with a
COLMAP model folder (its tracks, beside its own intrinsics).

Bad input of both is in the bad-input table (``tests/bad_input/``).
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import CliResult, assert_one_error_line, run_cli, synthesize

PINHOLE = [1100.0, 1250.0, 530.0, 370.0]
RADIAL = [900.0, 512.0, 384.0, -0.01]
#: Fewer triplets than the default: the batch and the single runs take the same options.
QUICK = ("--max-triplets", "4", "--seed", "3")
#: Keys that differ between two runs of the same input: wall seconds, the input's path,
#: the warning line (compared through ``observable``).
VARYING = {"seconds", "stage_seconds", "database", "warning"}


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``a.db`` (PINHOLE), ``b.db`` (SIMPLE_RADIAL, 8 images) and ``broken.db`` (text)."""
    folder = tmp_path_factory.mktemp("batch")
    synthesize(folder / "a.db", "PINHOLE", PINHOLE)
    synthesize(folder / "b.db", "SIMPLE_RADIAL", RADIAL, frames=8)
    (folder / "broken.db").write_text("not a database\n" * 20)
    return folder


@pytest.fixture(scope="module")
def single_runs(inputs: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    """``calibrate DB --json`` of each good database (one group each), in a process."""
    out = tmp_path_factory.mktemp("single")
    entries = {}
    for name in ("a.db", "b.db"):
        result = run_cli("calibrate", inputs / name, *QUICK, "--json", out / f"{name}.json")
        assert result.returncode == 0, result.stderr
        (entries[name],) = json.loads((out / f"{name}.json").read_text())
    return entries


def _stable(entry: dict) -> dict:
    return {key: value for key, value in entry.items() if key not in VARYING}


def _check_batch(result: CliResult, lines: list[dict], inputs: Path, singles: dict) -> None:
    """Exit 1, one error line for the broken database, the good ones as single runs."""
    assert result.returncode == 1, result.stderr
    (error,) = result.stderr.splitlines()
    assert error == f"error: {inputs / 'broken.db'}: not an SQLite database: {inputs / 'broken.db'}"
    by_database = {Path(line["database"]).name: line for line in lines}
    assert sorted(by_database) == ["a.db", "b.db", "broken.db"] and len(lines) == 3
    assert by_database["broken.db"] == {
        "database": str(inputs / "broken.db"),
        "error": f"not an SQLite database: {inputs / 'broken.db'}",
    }
    for name in ("a.db", "b.db"):
        assert _stable(by_database[name]) == _stable(singles[name]), name
        assert by_database[name]["warning"] is None


def test_json_lines_as_single_runs(
    inputs: Path, single_runs: dict, tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """Three databases, one of them broken: one JSON line each, in the given order, the
    good ones exactly as their single runs; exit 1; the databases unchanged."""
    before = {p.name: sha256(p) for p in inputs.iterdir()}
    paths = [inputs / name for name in ("a.db", "broken.db", "b.db")]
    out = tmp_path / "lines.jsonl"
    result = run_main("calibrate", *paths, *QUICK, "--json", out)
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    _check_batch(result, lines, inputs, single_runs)
    assert [line["database"] for line in lines] == [str(p) for p in paths]
    assert result.stdout == f"2 of 3 inputs calibrated; wrote 3 line(s) to {out}\n"
    # Without --json (and with --json -) the lines are all that stdout holds.
    for extra in ((), ("--json", "-")):
        again = run_main("calibrate", *paths, *QUICK, *extra)
        again_lines = [json.loads(line) for line in again.stdout.splitlines()]
        assert [_stable(line) for line in again_lines] == [_stable(line) for line in lines]
    assert {p.name: sha256(p) for p in inputs.iterdir()} == before


def test_quoted_glob_with_write(inputs: Path, tmp_path: Path, run_main: Callable[..., CliResult]):
    """A quoted pattern names the databases; ``--write`` stores each one's estimate (a
    backup first), as a single ``--write`` does; the broken one stays as it was."""
    for name in ("a.db", "b.db", "broken.db"):
        (tmp_path / name).write_bytes((inputs / name).read_bytes())
    broken = sha256(tmp_path / "broken.db")
    result = run_main("calibrate", tmp_path / "*.db", *QUICK, "--write", "--json", "-")
    assert result.returncode == 1
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert [Path(line["database"]).name for line in lines] == ["a.db", "b.db", "broken.db"]
    for line in lines[:2]:
        assert line["written"] is True
        path = Path(line["database"])
        assert path.with_name(f"{path.name}.bak").is_file()
        con = sqlite3.connect(f"{path.as_uri()}?mode=ro", uri=True)
        (model, blob) = con.execute("SELECT model, params FROM cameras").fetchone()
        con.close()
        params = np.frombuffer(blob, "<f8")
        stored = params[:4] if model == 1 else params[[0, 0, 1, 2]]  # PINHOLE, SIMPLE_RADIAL
        expected = [line[k] for k in ("fx", "fy", "cx", "cy")]
        if model != 1:
            expected[:2] = [(expected[0] + expected[1]) / 2] * 2
        np.testing.assert_allclose(stored, expected, rtol=1e-12)
    assert sha256(tmp_path / "broken.db") == broken
    assert not (tmp_path / "broken.db.bak").exists()


@pytest.mark.slow  # starts a Dask cluster of two worker processes
def test_dask_cluster_as_single_runs(inputs: Path, single_runs: dict, tmp_path: Path) -> None:
    """On a LocalCluster of two workers: the same lines as single runs, the broken
    database in its own line, exit 1; an existing --json replaced by the lines."""
    distributed = pytest.importorskip("distributed")
    out = tmp_path / "lines.jsonl"
    out.write_text("an earlier run's lines\n")
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        result = run_cli(
            "calibrate", inputs / "a.db", inputs / "broken.db", inputs / "b.db", *QUICK,
            "--json", out, "--dask", cluster.scheduler_address,
        )  # fmt: skip
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    _check_batch(result, lines, inputs, single_runs)


@pytest.mark.slow  # the client gives up after its 10 s timeout
def test_unreachable_dask_scheduler(inputs: Path, tmp_path: Path) -> None:
    """No scheduler: one line after the timeout, and no --json file made."""
    out = tmp_path / "lines.jsonl"
    result = run_cli("calibrate", inputs / "a.db", "--dask", "tcp://127.0.0.1:9", "--json", out)
    assert_one_error_line(result, "cannot connect to the Dask scheduler tcp://127.0.0.1:9")
    assert not out.exists()


# --------------------------------------------------------------------------- a model folder


def test_model_folder(tmp_path: Path, run_main: Callable[..., CliResult]) -> None:
    """A model (pycolmap's synthetic scene, exact tracks) whose camera is 2–4 % off: the
    estimate from its tracks is the true camera, printed beside the model's own values,
    with ``reference`` in the JSON; binary and text models alike, neither changed."""
    truth = synthesize(tmp_path / "scene.db", "PINHOLE", PINHOLE)
    off = [PINHOLE[0] * 1.03, PINHOLE[1] * 0.98, PINHOLE[2] * 1.04, PINHOLE[3] * 0.96]
    truth.cameras[1].params = off
    for kind in ("bin", "txt"):
        model = tmp_path / kind
        model.mkdir()
        truth.write(model) if kind == "bin" else truth.write_text(model)
        before = {p.name: sha256(p) for p in model.iterdir()}
        out = tmp_path / f"{kind}.json"
        result = run_main("calibrate", model, *QUICK, "--json", out)
        assert result.returncode == 0, result.stderr
        assert "camera 1: the estimate beside the model's own intrinsics" in result.stdout
        assert "diff %" in result.stdout and result.stderr == ""
        (entry,) = json.loads(out.read_text())
        np.testing.assert_allclose([entry[k] for k in ("fx", "fy", "cx", "cy")], PINHOLE, 1e-4)
        np.testing.assert_allclose(list(entry["reference"].values()), off)
        assert {p.name: sha256(p) for p in model.iterdir()} == before
    # In a batch beside a database: its line carries the reference too.
    result = run_main("calibrate", tmp_path / "bin", tmp_path / "scene.db", *QUICK)
    assert result.returncode == 0, result.stderr
    model_line, database_line = (json.loads(line) for line in result.stdout.splitlines())
    assert model_line["database"] == str(tmp_path / "bin")
    assert model_line["reference"] is not None and database_line["reference"] is None
