"""Numbers and values on the command line (priors, seeds, sizes, counts, ``--dask``
addresses), and flags that do not go together: refused before any work.
"""

from __future__ import annotations

import json
import socket
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from conftest import CliResult, assert_one_error_line

from bad_input.builders import (
    copy_good,
    image_folder,
    make_model,
    model_and_database,
    models_with,
    run_database,
    run_image_folder,
)
from bad_input.table import (
    QUICK_READ,
    Case,
    table_test,
)

CASES: dict[str, Case] = {
    "unknown camera id": Case(
        copy_good, "camera id 7 is not in the database", ("--camera-id", "7")
    ),
    "NaN prior": Case(copy_good, "must be finite", ("--prior", "nan,1250,530,370")),
    "zero prior": Case(copy_good, "focal lengths positive", ("--prior", "0,1250,530,370")),
    "prior of 3 values": Case(
        copy_good, "expected 4 values FX,FY,CX,CY, got 3", ("--prior", "1,2,3")
    ),
    "prior of 5 values": Case(
        copy_good, "expected 4 values FX,FY,CX,CY, got 5", ("--prior", "1,2,3,4,5")
    ),
    "prior not numbers": Case(copy_good, "expected four numbers", ("--prior", "a,b,c,d")),
    "unknown --method": Case(copy_good, "--method: invalid choice: 'magic'", ("--method", "magic")),
    "prior of 1e-300": Case(
        copy_good, "invalid starting intrinsics from --prior", ("--prior", "1e-300,1e-300,530,370")
    ),
    "prior principal point 1e308": Case(
        copy_good, "principal point within", ("--prior", "525,525,1e308,-1e308")
    ),
    "RuntimeWarning: --prior 1e308": Case(
        copy_good, "invalid starting intrinsics", ("--prior", "1e308,1e308,530,370")
    ),
    "--seed -1": Case(copy_good, "seed must be in [0,", ("--seed", "-1")),
    "run --camera-model FOO": Case(
        copy_good,
        "--camera-model: invalid choice: 'FOO'",
        argv=lambda f, p, w: ("run", f, w, "--camera-model", "FOO"),
    ),
    "run --seed -1": Case(copy_good, "seed must be", argv=run_database("--seed", "-1")),
    "run --max-image-size 2147483648": Case(
        image_folder(lambda _: None, good=3),
        "--max-image-size: must be in [100, 2147483647], got 2147483648",
        argv=run_image_folder("--max-image-size", "2147483648"),
    ),
    "run --max-image-size 99": Case(
        image_folder(lambda _: None, good=3),
        "--max-image-size: must be in [100,",
        argv=run_image_folder("--max-image-size", "99"),
    ),
    "run --max-image-size -1": Case(
        image_folder(lambda _: None, good=3),
        "--max-image-size: must be in",
        argv=run_image_folder("--max-image-size=-1"),
    ),
    "run --max-image-size 1600.5": Case(
        image_folder(lambda _: None, good=3),
        "--max-image-size: expected an integer, got '1600.5'",
        argv=run_image_folder("--max-image-size", "1600.5"),
    ),
    "evaluate: missing dataset folder": Case(
        copy_good,
        "does not exist",
        argv=lambda f, p, w: ("evaluate", "strecha", f / "nope", "--output", w),
    ),
    "evaluate --perturbation a-b": Case(
        copy_good,
        "malformed --perturbation",
        argv=lambda f, p, w: ("evaluate", "strecha", f, "--perturbation", "a-b", "--output", w),
    ),
    "evaluate --methods magic": Case(
        copy_good,
        "unknown method",
        argv=lambda f, p, w: ("evaluate", "strecha", f, "--methods", "magic", "--output", w),
    ),
    "evaluate --images 2": Case(
        copy_good,
        "at least 3 images",
        argv=lambda f, p, w: ("evaluate", "strecha", f, "--images", "2", "--output", w),
    ),
    "synthetic --noise x": Case(
        copy_good,
        "malformed --noise",
        argv=lambda f, p, w: ("synthetic", "--noise", "x", "--output", w),
    ),
    "synthetic --runs 0": Case(
        copy_good,
        "--runs must be at least 1",
        argv=lambda f, p, w: ("synthetic", "--runs", "0", "--output", w),
    ),
    "synthetic --seed -1": Case(
        copy_good, "seed must be", argv=lambda f, p, w: ("synthetic", "--seed", "-1")
    ),
    "synthetic --noise nan": Case(
        copy_good, "invalid --noise 'nan'", argv=lambda f, p, w: ("synthetic", "--noise", "nan")
    ),
    "synthetic --perturbation nan": Case(
        copy_good,
        "expected a finite number",
        argv=lambda f, p, w: ("synthetic", "--perturbation", "nan"),
    ),
    "synthetic --perturbation -500": Case(
        copy_good, "[0, 100) percent", argv=lambda f, p, w: ("synthetic", "--perturbation", "-500")
    ),
    "calibrate --model without --output": Case(
        lambda f, g: copy_good(make_model(f).parent.parent, g),
        "--model and --output go together",
        argv=lambda f, p, w: ("calibrate", p, "--model", f / "sparse" / "0"),
    ),
    "calibrate --refine-distortion without --model": Case(
        copy_good, "--refine and --refine-distortion need --model", ("--refine-distortion",)
    ),
    "model folder with --write": Case(
        models_with(), "--write stores the estimate in a database: ", ("--write",)
    ),
    "model folder with --model and --output": Case(
        models_with(),
        "--model goes with a database: ",
        argv=lambda f, p, w: ("calibrate", p, "--model", p, "--output", w),
    ),
    "several databases with --model": Case(
        model_and_database,
        "--model takes one database, not several inputs",
        argv=lambda f, p, w: ("calibrate", p, p, "--model", f / "sparse" / "0", "--output", w),
    ),
    "several inputs, --write with a model folder": Case(
        model_and_database,
        "is a COLMAP model folder",
        argv=lambda f, p, w: ("calibrate", p, f / "sparse" / "0", "--write"),
    ),
    # ----- issue 37: counts and sizes in ranges; --dask addresses checked before a client
    "synthetic --runs 10000000000000": Case(
        copy_good,
        "--runs must be at most 1000000, got 10000000000000",
        argv=lambda f, p, w: ("synthetic", "--runs", "10000000000000", "--output", w),
    ),
    "synthetic --runs 1e13": Case(
        copy_good,
        "--runs: invalid int value: '1e13'",
        argv=lambda f, p, w: ("synthetic", "--runs", "1e13", "--output", w),
    ),
    "synthetic --points 1000000000000": Case(
        copy_good,
        "--points must be at most 100000",
        argv=lambda f, p, w: ("synthetic", "--points", "1000000000000", "--output", w),
    ),
    "synthetic --noise 1e300": Case(
        copy_good,
        "--noise levels must be at most 100 px, got 1e+300",
        argv=lambda f, p, w: ("synthetic", "--noise", "0,1e300", "--output", w),
    ),
    "synthetic --workers 100000": Case(
        copy_good,
        "--workers: must be in [1, 256], got 100000",
        argv=lambda f, p, w: ("synthetic", "--workers", "100000", "--output", w),
    ),
    "synthetic --workers 0": Case(
        copy_good,
        "--workers: must be in [1, 256], got 0",
        argv=lambda f, p, w: ("synthetic", "--workers", "0", "--output", w),
    ),
    "evaluate --images 1000000000000": Case(
        copy_good,
        "invalid --images '3,1000000000000': values must be in [0, 100000]",
        argv=lambda f, p, w: (
            "evaluate",
            "strecha",
            f,
            "--images",
            "3,1000000000000",
            "--output",
            w,
        ),
    ),
    "evaluate --max-image-size 99": Case(
        copy_good,
        "--max-image-size: must be in [100,",
        argv=lambda f, p, w: ("evaluate", "strecha", f, "--max-image-size", "99", "--output", w),
    ),
    "--dask ''": Case(copy_good, "--dask '': expected HOST:PORT", ("--dask", "")),
    "--dask inproc://x": Case(
        copy_good,
        "--dask 'inproc://x': the scheme must be one of tcp, tls",
        ("--dask", "inproc://x"),
    ),
    "--dask http://localhost:8786": Case(
        copy_good, "the scheme must be one of tcp, tls", ("--dask", "http://localhost:8786")
    ),
    "--dask tcp://[::1": Case(
        copy_good, "'tcp://[::1': expected HOST:PORT", ("--dask", "tcp://[::1")
    ),
    "--dask ::::": Case(copy_good, "'::::': expected HOST:PORT", ("--dask", "::::")),
    "--dask tcp://host:99999": Case(
        copy_good, "port 99999 is not in [1, 65535]", ("--dask", "tcp://host:99999")
    ),
    "synthetic --dask tcp://[::1": Case(
        copy_good,
        "expected HOST:PORT",
        argv=lambda f, p, w: ("synthetic", "--dask", "tcp://[::1", "--output", w),
    ),
}


test_bad_input = table_test(CASES)


def test_repeated_camera_id_is_calibrated_once(
    database_copy: Path, tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """``--camera-id 1 --camera-id 1``: one result, not two (issue 15, item 8)."""
    out = tmp_path / "result.json"
    result = run_main(
        "calibrate",
        database_copy,
        *QUICK_READ,
        "--camera-id",
        "1",
        "--camera-id",
        "1",
        "--json",
        out,
    )
    assert result.returncode == 0, result.stderr
    assert [entry["camera_id"] for entry in json.loads(out.read_text())] == [1]
    rows = [line for line in result.stdout.splitlines()[1:] if line.split()[0].isdigit()]
    assert len(rows) == 1  # one camera (its std line follows it)


@contextmanager
def listening(greeting: bytes | None) -> Iterator[int]:
    """A local TCP server (its port) that accepts connections and sends ``greeting``
    at once, or (None) answers nothing until it has read a request, as a web server does."""
    server = socket.create_server(("127.0.0.1", 0))
    stop = threading.Event()

    def serve() -> None:
        server.settimeout(0.1)
        while not stop.is_set():
            try:
                connection, _ = server.accept()
            except TimeoutError:
                continue
            with connection:
                if greeting is not None:
                    connection.sendall(greeting)
                stop.wait(5)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield server.getsockname()[1]
    finally:
        stop.set()
        thread.join(timeout=10)
        server.close()


@pytest.mark.parametrize(
    ("greeting", "fragment"),
    [
        (None, "no Dask scheduler answered within 0.5 s"),
        (b"HTTP/1.1 200 OK\r\n\r\n", "is not a Dask scheduler (its first bytes b'HTTP/1.1'"),
    ],
    ids=["silent until asked (a web server)", "sends HTTP"],
)
def test_dask_address_of_a_server_that_is_no_scheduler(
    greeting: bytes | None,
    fragment: str,
    database_copy: Path,
    monkeypatch: pytest.MonkeyPatch,
    run_main: Callable[..., CliResult],
) -> None:
    """``--dask`` at a web server's address: one line, nothing else tried (before: Dask
    read the answer's first bytes as a message length and asked for exbibytes)."""
    from colmap_trifocal.evaluation import dask_address

    monkeypatch.setattr(dask_address, "PROBE_TIMEOUT_S", 0.5)
    with listening(greeting) as port:
        result = run_main("calibrate", database_copy, "--dask", f"tcp://127.0.0.1:{port}")
    assert_one_error_line(result, fragment)
