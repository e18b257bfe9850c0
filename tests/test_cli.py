"""The command line as a user runs it: exit codes, JSON, --write, the demo, the renderings.

Refused inputs are rows of the bad-input table (``tests/bad_input/``). Here: the installed
``colmap-trifocal`` entry point (a real process), the rest in this process
(``conftest.run_main``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from conftest import (
    CliResult,
    assert_one_error_line,
    database_rows,
    require_rendering,
    run_cli,
    stacks_of,
    synthesize,
)

PARAMS = [1100.0, 1250.0, 530.0, 370.0]
PRIOR = "1140,1210,545,360"
#: The console script pip installed next to this interpreter (``[project.scripts]``).
ENTRY_POINT = Path(sys.executable).parent / "colmap-trifocal"


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def database(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cli") / "database.db"
    synthesize(path, "PINHOLE", PARAMS)
    return path


def test_installed_entry_point_writes_json(database: Path, tmp_path: Path) -> None:
    """``colmap-trifocal calibrate`` through the installed console script."""
    assert ENTRY_POINT.is_file(), f"{ENTRY_POINT} missing: pip install -e '.[test]'"
    before = _sha256(database)
    out = tmp_path / "result.json"
    result = subprocess.run(
        [ENTRY_POINT, "calibrate", database, "--prior", PRIOR, "--json", out, "--seed", "3"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""
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


def test_write_flag(database: Path, tmp_path: Path, run_main: Callable[..., CliResult]) -> None:
    copy = tmp_path / "db.db"
    copy.write_bytes(database.read_bytes())
    result = run_main("calibrate", copy, "--prior", PRIOR, "--write")
    assert result.returncode == 0, result.stderr
    assert "wrote 1 camera(s)" in result.stdout
    assert database_rows(tmp_path / "db.db.bak") == database_rows(database)
    with pycolmap.Database.open(str(copy)) as db:
        np.testing.assert_allclose(db.read_all_cameras()[0].params, PARAMS, rtol=1e-5)


# --------------------------------------------------------------------------- the demo


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, CliResult]:
    """``colmap-trifocal demo --keep DIR``, run once (a process, as a user starts it)."""
    folder = tmp_path_factory.mktemp("demo")
    return folder / "demo", run_cli("demo", "--keep", folder)


def test_demo_runs_the_pipeline(demo: tuple[Path, CliResult]) -> None:
    workspace, result = demo
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    trifocal = float(lines[-1].split(":")[1].split("%")[0])
    refined = float(lines[-2].split("BA-refined")[1].split("%")[0])
    # From a 5 % prior with 0.5 px noise and 20 % wrong matches.
    assert trifocal < 0.5 and refined < 0.5
    assert "registered 10 images" in result.stdout
    assert (workspace / "sparse" / "0" / "cameras.bin").is_file()
    report = json.loads((workspace / "report.json").read_text())
    assert report["num_registered_images"] == 10
    assert set(report["seconds"]) == {"features", "calibrate", "mapping", "refine"}
    # COLMAP's own INFO lines only with -vv (pycolmap's BA resets glog's level).
    assert not [line for line in result.stderr.splitlines() if line.startswith("I20")]


def test_show_renders_png(
    demo: tuple[Path, CliResult], tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    require_rendering()
    workspace, made = demo
    assert made.returncode == 0, made.stderr
    png = tmp_path / "view.png"
    result = run_main("show", workspace / "sparse" / "0", "--png", png)
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""  # Open3D's and Filament's own lines only with -vv
    image = cv2.imread(str(png))
    assert image is not None and image.shape[2] == 3
    assert (image < 250).any(axis=2).mean() > 0.002  # not a blank white background


def test_run_renders_png(
    demo: tuple[Path, CliResult], tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """``run ... --png OUT`` (DESIGN.md): the pipeline, then the model rendered offscreen."""
    require_rendering()
    workspace, made = demo
    assert made.returncode == 0, made.stderr
    database = workspace / "database.db"
    before = _sha256(database)
    png = tmp_path / "run.png"
    target = tmp_path / "ws"
    result = run_main(
        "run", tmp_path / "no-images", target, "--database", database,
        "--refine", "none", "--png", png,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert f"wrote {png}" in result.stdout and (target / "report.json").is_file()
    image = cv2.imread(str(png))
    assert image is not None and (image < 250).any(axis=2).mean() > 0.002
    assert _sha256(database) == before  # the input was copied, not changed


# --------------------------------------------------------------------------- the process itself


def _close(fd: int) -> Callable[[], None]:
    """In the child, before the interpreter starts: close file descriptor ``fd`` (``>&-``)."""
    return lambda: os.close(fd)


def test_closed_stdout_still_writes_the_json(database: Path, tmp_path: Path) -> None:
    """``calibrate DB --json OUT >&-``: the JSON is written, the table dropped, exit 0."""
    out = tmp_path / "result.json"
    result = run_cli("calibrate", database, "--prior", PRIOR, "--json", out, preexec_fn=_close(1))
    assert (result.returncode, result.stderr) == (0, "")
    (entry,) = json.loads(out.read_text())
    np.testing.assert_allclose([entry[k] for k in ("fx", "fy", "cx", "cy")], PARAMS, rtol=1e-5)


def test_closed_stderr_still_writes_the_database(database: Path, tmp_path: Path) -> None:
    """``calibrate DB --write 2>&-``: the database is written (backup first), exit 0."""
    copy = tmp_path / "db.db"
    copy.write_bytes(database.read_bytes())
    result = run_cli("calibrate", copy, "--prior", PRIOR, "--write", preexec_fn=_close(2))
    assert result.returncode == 0
    assert "wrote 1 camera(s)" in result.stdout
    assert database_rows(tmp_path / "db.db.bak") == database_rows(database)
    with pycolmap.Database.open(str(copy)) as db:
        np.testing.assert_allclose(db.read_all_cameras()[0].params, PARAMS, rtol=1e-5)


def test_closed_stdout_refuses_json_to_stdout(database: Path) -> None:
    """``--json - >&-`` has nowhere to go: one line, status 2, before any work."""
    before = _sha256(database)
    result = run_cli("calibrate", database, "--json", "-", preexec_fn=_close(1))
    assert_one_error_line(result, "cannot write --json -: standard output is closed")
    assert _sha256(database) == before


def test_closed_stderr_keeps_the_exit_status_of_an_error(tmp_path: Path) -> None:
    """A refused input with stderr closed: status 2 (the line has nowhere to go)."""
    result = run_cli("calibrate", tmp_path / "missing.db", preexec_fn=_close(2))
    assert (result.returncode, result.stdout) == (2, "")
    assert list(tmp_path.iterdir()) == []


def _run_terminated_when(tmp_path: Path, started: Callable[[Path], bool], settle: float) -> str:
    """``run`` on 16 random 640 x 480 images into a new workspace ``tmp_path / "ws"``, ended
    by SIGTERM (to its process group) ``settle`` seconds after ``started(workspace)``;
    asserts status 143, returns stderr."""
    status, stderr = _run_signalled_when(tmp_path, started, settle, signal.SIGTERM)
    assert status == 143, stderr
    return stderr


def _run_signalled_when(
    tmp_path: Path,
    started: Callable[[Path], bool],
    settle: float,
    signum: int,
    ignored: bool = False,
) -> tuple[int, str]:
    """``run`` on 16 random 640 x 480 images into a new workspace ``tmp_path / "ws"``, sent
    ``signum`` (to its process group) ``settle`` seconds after ``started(workspace)``, the
    signal inherited as ignored where ``ignored`` (as under ``nohup``); its status and
    stderr. Without a signal, ``run`` ends with status 2: random images have no verified
    matches."""
    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(0)
    for index in range(16):
        cv2.imwrite(str(images / f"{index:02d}.png"), rng.integers(0, 256, (480, 640), np.uint8))
    workspace = tmp_path / "ws"
    command = [sys.executable, "-m", "colmap_trifocal.cli", "run", str(images), str(workspace)]
    if ignored:  # as nohup does: the signal ignored, then exec (which keeps it ignored)
        command = [
            sys.executable,
            "-c",
            f"import os, signal, sys; signal.signal({int(signum)}, signal.SIG_IGN); "
            "os.execv(sys.executable, sys.argv[1:])",
            *command,
        ]
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    deadline = time.monotonic() + 300
    while not started(workspace) and process.poll() is None:
        assert time.monotonic() < deadline, "the stage never started"
        time.sleep(0.02)
    assert process.poll() is None, process.communicate()
    time.sleep(settle)
    os.killpg(process.pid, signum)
    _, stderr = process.communicate(timeout=120)
    return process.returncode, stderr


def test_terminated_extraction_prints_one_line(tmp_path: Path) -> None:
    """SIGTERM while pycolmap extracts features: ``error: terminated`` and nothing else
    (COLMAP's glog ERROR line ``Stopping thread...`` only with -vv), status 143."""
    stderr = _run_terminated_when(tmp_path, lambda ws: (ws / "database.db").exists(), 0.5)
    assert stderr.splitlines() == ["error: terminated"]


def test_terminated_matching_leaves_nothing(tmp_path: Path) -> None:
    """SIGTERM while the workers match (their copies of the database in a ``.matching-``
    folder of the workspace): ``error: terminated``, status 143, and nothing left (the
    workspace was new). Before, the build's child died at once (glog's SIGTERM handler)
    and left that folder, copies and all, and with it the workspace."""
    stderr = _run_terminated_when(tmp_path, lambda ws: any(ws.glob(".matching-*")), 0.3)
    assert stderr.splitlines() == ["error: terminated"]
    assert not (tmp_path / "ws").exists()


def test_hangup_under_nohup_is_ignored(tmp_path: Path) -> None:
    """SIGHUP while the workers match, the command started with SIGHUP ignored (``nohup``):
    the run goes on to its own end, as without the signal (random images: the database is
    built, then "no verified matches", status 2). Before, the build's child put its own
    handler on SIGHUP and died (129), so the parent ended with "cannot build the
    database"."""
    status, stderr = _run_signalled_when(
        tmp_path, lambda ws: any(ws.glob(".matching-*")), 0.3, signal.SIGHUP, ignored=True
    )
    assert status == 2, stderr
    assert stderr.splitlines() == [
        f"error: database has no verified matches (run COLMAP feature matching first): "
        f"{tmp_path / 'ws' / 'database.db'}"
    ]
    with pycolmap.Database.open(str(tmp_path / "ws" / "database.db")) as db:
        assert db.num_images() == 16
        assert db.num_matched_image_pairs() == 16 * 15 // 2  # every pair was matched


def test_a_hung_command_shows_where_it_waits() -> None:
    """What ``run_cli`` reports of a command that never ends: the Python stacks of the
    process and of its forked child, each at its own wait."""
    process = subprocess.Popen(
        [
            sys.executable,
            "-X",
            "faulthandler",
            "-c",
            # Each line in one write(2) of its own: two prints into the same pipe
            # interleave ('parentchild', then the two newlines).
            "import os, time\n"
            "def parent_waits(): os.write(1, b'parent\\n'); time.sleep(600)\n"
            "def child_waits(): os.write(1, b'child\\n'); time.sleep(600)\n"
            "child_waits() if os.fork() == 0 else parent_waits()",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert process.stdout is not None
    ready = {process.stdout.readline().strip() for _ in range(2)}  # both in their waits
    assert ready == {"parent", "child"}
    stacks = stacks_of(process)
    assert process.returncode == -signal.SIGABRT
    assert "in parent_waits" in stacks and "in child_waits" in stacks, stacks


# ----------------------------------------------------------------- help, defaults, progress


def _options_without_help(parser: argparse.ArgumentParser, command: str) -> list[str]:
    """``command OPTION`` for every argument (every subcommand's too) without help text."""
    missing = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                missing += _options_without_help(sub, f"{command} {name}")
        elif not action.help or action.help == argparse.SUPPRESS:
            missing.append(f"{command} {'/'.join(action.option_strings) or action.dest}")
    return missing


def test_every_option_of_every_command_has_help() -> None:
    from colmap_trifocal.cli import build_parser

    parser = build_parser()
    assert _options_without_help(parser, "colmap-trifocal") == []
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(commands.choices) == {"calibrate", "run", "evaluate", "synthetic", "show", "demo"}


def test_run_defaults_to_colmaps_camera_model() -> None:
    from colmap_trifocal.cli import build_parser
    from colmap_trifocal.reconstruction.workflow import RunOptions

    args = build_parser().parse_args(["run", "images", "workspace"])
    assert args.camera_model == RunOptions().camera_model == "SIMPLE_RADIAL"
    assert pycolmap.ImageReaderOptions().camera_model == "SIMPLE_RADIAL"  # COLMAP's default


def _by_name(database: Path) -> tuple[dict, dict, dict]:
    """Cameras and keypoint counts by image name; raw matches and verified inliers by pair
    of names."""
    with pycolmap.Database.open(str(database)) as db:
        names = {image.image_id: image.name for image in db.read_all_images()}
        cameras = {c.camera_id: (c.model.name, tuple(c.params)) for c in db.read_all_cameras()}
        images = {
            image.name: (cameras[image.camera_id], db.num_keypoints_for_image(image.image_id))
            for image in db.read_all_images()
        }
        pair_ids, matches = db.read_all_matches()
        raw = dict(zip(pair_ids, map(len, matches), strict=True))
        inliers = dict(zip(*db.read_two_view_geometry_num_inliers(), strict=True))

    def by_pair(counts: dict[int, int]) -> dict[tuple[str, ...], int]:
        return {
            tuple(sorted(names[i] for i in pycolmap.pair_id_to_image_pair(pair_id))): count
            for pair_id, count in counts.items()
        }

    return images, by_pair(raw), by_pair(inliers)


@pytest.mark.parametrize(("mode", "matcher"), [("auto", "exhaustive"), ("single", "sequential")])
def test_progress_bars_over_extraction_and_matching(
    mode: str, matcher: str, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """With ``progress`` the images are extracted a chunk at a time and the matching
    workers' verified pairs are followed, with bars on stderr, and the database holds the
    same cameras, features and matches as a build without bars."""
    from conftest import EXACT_SEARCH_FEATURES, small_texture_views

    from colmap_trifocal.database.features import build_database

    images = tmp_path / "images"
    images.mkdir()
    for k, view in enumerate(small_texture_views(7)):
        cv2.imwrite(str(images / f"{k}.png"), view)
    # A seeded RANSAC and views under pycolmap's exact-search size: the build is the same
    # every time (views of one translated plane are degenerate for verification, where
    # RANSAC unseeded found 55, 799 or 1232 inliers for one pair from run to run).
    options = {"camera_model": "SIMPLE_RADIAL", "camera_mode": mode, "matcher": matcher, "seed": 0}
    plain = build_database(images, tmp_path / "plain.db", **options)
    capfd.readouterr()
    chunked = build_database(images, tmp_path / "chunked.db", **options, progress=True)
    err = capfd.readouterr().err
    assert "features: images: 100%" in err and "7/7" in err
    assert "matching: image pairs: 100%" in err
    chunked_images, *chunked_matches = _by_name(chunked)
    plain_images, *plain_matches = _by_name(plain)
    assert chunked_images == plain_images
    assert all(count < EXACT_SEARCH_FEATURES for _, count in plain_images.values())
    assert chunked_matches == plain_matches
    assert all(chunked_matches[1].values())  # every pair verified, none empty
    assert sorted(p.name for p in tmp_path.iterdir()) == ["chunked.db", "images", "plain.db"]
