"""The evaluation protocol, its reports, and the evaluate / synthetic commands."""

from __future__ import annotations

import csv
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import CliResult, assert_one_error_line, run_cli

from colmap_trifocal.datasets import read_scene
from colmap_trifocal.evaluation.protocol import (
    perturbed_prior,
    scene_database_path,
    select_sequence,
)
from colmap_trifocal.evaluation.records import RunRecord
from colmap_trifocal.evaluation.report import boxplots, markdown_table, summarize, write_csv

TRUTH = np.array([1000.0, 1000.0, 500.0, 400.0])


def test_sequence_grows_by_overlap_with_the_chosen_images() -> None:
    overlap = {("a", "b"): 1.0, ("a", "c"): 50.0, ("c", "d"): 60.0, ("b", "d"): 5.0}
    assert select_sequence(["a", "b", "c", "d"], overlap, 3) == ["a", "c", "d"]
    assert select_sequence(["a", "b", "c", "d"], overlap, 10) == ["a", "c", "d", "b"]


def test_perturbed_prior_stays_in_its_range() -> None:
    rng = np.random.default_rng(0)
    priors = np.array([perturbed_prior(TRUTH, (5.0, 10.0), rng) for _ in range(200)])
    offsets = np.abs(priors / TRUTH - 1)
    assert offsets.min() >= 0.05 and offsets.max() <= 0.10
    assert (priors > TRUTH).any() and (priors < TRUTH).any()  # both signs


def _record(method: str, error: float | None, run: int) -> RunRecord:
    estimate = None if error is None else TRUTH * (1 + error / 100)
    return RunRecord.finished(
        estimate,
        TRUTH,
        TRUTH * 1.05,
        experiment="strecha",
        scene="s",
        method=method,
        run=run,
        seed=run,
        num_images=8,
        perturbation="0-5",
        message="" if error is not None else "failed",
    )


def test_summary_statistics_csv_markdown_and_plot(tmp_path: Path) -> None:
    records = [_record("msac-opt", e, i) for i, e in enumerate([0.1, 0.2, 0.6])]
    records += [_record("fundamental", 2.0, 0), _record("fundamental", None, 1)]
    rows = {row.method: row for row in summarize(records)}
    assert rows["msac-opt"].mean == pytest.approx(0.3)
    assert rows["msac-opt"].median == pytest.approx(0.2)
    assert rows["msac-opt"].std == pytest.approx(np.std([0.1, 0.2, 0.6]))
    assert (rows["fundamental"].runs, rows["fundamental"].failures) == (2, 1)
    table = markdown_table(list(rows.values()))
    assert "| s | 8 | 0-5 | msac-opt | 0.300 | 0.200 |" in table
    write_csv(list(rows.values()), tmp_path / "t.csv")
    with open(tmp_path / "t.csv") as handle:
        assert len(list(csv.DictReader(handle))) == 2
    png = tmp_path / "t.png"
    boxplots(records, png)
    assert png.stat().st_size > 5000


def test_synthetic_command(tmp_path: Path, run_main: Callable[..., CliResult]) -> None:
    out = tmp_path / "runs.json"
    result = run_main(
        "synthetic", "--runs", "2", "--noise", "0.5", "--output", tmp_path, "--json", out
    )
    assert result.returncode == 0, result.stderr
    records = json.loads(out.read_text())
    assert sorted({r["method"] for r in records}) == [
        "ba-floor",
        "direct",
        "fundamental",
        "msac-opt",
    ]
    assert len(records) == 8
    for r in records:
        if r["method"] in ("msac-opt", "ba-floor"):
            assert r["error_percent"] < 0.5  # the prior is off by up to 5 %
    msac = [r for r in records if r["method"] == "msac-opt"]
    assert all(s > 0 for r in msac for s in r["std"])
    for suffix in ("csv", "md", "png"):
        assert (tmp_path / f"synthetic.{suffix}").is_file()
    assert "| cube-500 | 0.5 | msac-opt |" in result.stdout


def test_synthetic_on_a_dask_cluster_matches_local(tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        remote = run_cli(
            "synthetic", "--runs", "1", "--noise", "0.5", "--methods", "msac-opt",
            "--output", tmp_path / "dask", "--json", tmp_path / "dask.json",
            "--dask", cluster.scheduler_address,
        )  # fmt: skip
    assert remote.returncode == 0, remote.stderr
    local = run_cli(
        "synthetic", "--runs", "1", "--noise", "0.5", "--methods", "msac-opt",
        "--output", tmp_path / "local", "--json", tmp_path / "local.json", "--workers", "1",
    )  # fmt: skip
    assert local.returncode == 0, local.stderr
    estimates = [
        json.loads((tmp_path / f"{name}.json").read_text())[0]["estimate"]
        for name in ("dask", "local")
    ]
    assert estimates[0] == estimates[1]


@pytest.mark.slow  # the client gives up after its 10 s timeout
def test_unreachable_dask_scheduler(tmp_path: Path) -> None:
    """No scheduler at the address: one line after the client's 10 s timeout, nothing
    written. A process (the other bad inputs are rows of the bad-input table,
    ``tests/bad_input/``, in the test process): the failed client must not keep the process
    from ending."""
    output = tmp_path / "out"
    result = run_cli("synthetic", "--dask", "tcp://127.0.0.1:9", "--runs", "1", "--output", output)
    assert_one_error_line(result, "cannot connect to the Dask scheduler tcp://127.0.0.1:9")
    assert not output.exists()


@pytest.mark.slow
@pytest.mark.real_data
def test_evaluate_on_strecha(strecha_database, tmp_path: Path) -> None:
    """Two runs per perturbation range on 8 images of fountain-P11, from the cached database."""
    database, folder = strecha_database("fountain-P11")
    cache = tmp_path / "cache"
    cache.mkdir()
    shutil.copyfile(database, scene_database_path(read_scene("strecha", folder), cache, 1600))
    out = tmp_path / "runs.json"
    result = run_cli(
        "evaluate", "strecha", folder, "--images", "8", "--runs", "2",
        "--methods", "msac-opt,fundamental,calibrate_view_graph",
        "--cache", cache, "--output", tmp_path, "--json", out,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    records = json.loads(out.read_text())
    assert len(records) == 2 * 2 * 3
    assert {r["num_images"] for r in records} == {8}
    assert {r["perturbation"] for r in records} == {"0-5", "5-10"}
    by_method: dict[str, list[float]] = {}
    for r in records:
        by_method.setdefault(r["method"], []).append(r["error_percent"])
    assert max(by_method["msac-opt"]) < 0.5
    assert np.mean(by_method["msac-opt"]) < np.mean(by_method["calibrate_view_graph"])
    assert (tmp_path / "evaluation.png").stat().st_size > 5000
