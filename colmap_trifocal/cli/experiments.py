"""What ``evaluate`` and ``synthetic`` share: their common flags, list arguments, outputs.

Both write ``<stem>.csv``, ``<stem>.md`` and ``<stem>.png`` into ``--output`` and, with
``--json``, every run; the paths are checked before the first run.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from ..common.arguments import MAX_WORKERS_FLAG, integer_in, seed
from ..common.errors import CalibrationError
from ..common.extras import require_extra
from ..common.files import Input, Output, refuse_outputs_over_inputs, write_text_atomically
from .output import check_output_file, check_output_folder

if TYPE_CHECKING:
    from ..evaluation.records import RunRecord


#: The most runs per case ``--runs`` takes: a sweep's size, not a typo's (1e13 runs asked
#: for petabytes of seeds before).
MAX_RUNS = 1_000_000


def check_dask_flag(address: str) -> None:
    """``--dask ADDRESS``: well-formed (one line otherwise, before Dask raises ValueError
    or allocates what a web server's first bytes say), Dask installed, and a Dask
    scheduler answering there (:mod:`..evaluation.dask_address`)."""
    from ..evaluation.dask_address import check_dask_address, parse_dask_address

    parse_dask_address(address)
    require_extra("distributed", "--dask")
    check_dask_address(address)


def add_common_flags(parser: argparse.ArgumentParser, stem: str) -> None:
    """``--seed``, ``--output``, ``--json``, ``--workers`` and ``--dask``."""
    parser.add_argument(
        "--seed", type=seed, default=0, help="seed of the runs' random draws (default 0)"
    )
    parser.add_argument(
        "--output",
        type=Path,
        default=Path(stem),
        help=f"folder for {stem}.csv, {stem}.md and {stem}.png (default ./{stem})",
    )
    parser.add_argument("--json", type=Path, metavar="OUT", help="write every run as JSON")
    parser.add_argument(
        "--workers",
        type=integer_in(1, MAX_WORKERS_FLAG),
        help="local processes (default: one per core)",
    )
    parser.add_argument("--dask", metavar="ADDRESS", help="run on this Dask scheduler instead")


def numbers(
    text: str, name: str, kind: type = float, bounds: tuple[float, float] | None = None
) -> list:
    """Comma-separated finite numbers of type ``kind``, each within ``bounds`` if given
    (CalibrationError otherwise)."""
    try:
        values = [kind(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise CalibrationError(
            f"malformed {name} {text!r}: expected comma-separated numbers"
        ) from None
    if not values:
        raise CalibrationError(f"{name} is empty")
    if not all(math.isfinite(v) for v in values):
        raise CalibrationError(f"invalid {name} {text!r}: values must be finite")
    if bounds is not None and not all(bounds[0] <= v <= bounds[1] for v in values):
        low, high = bounds
        raise CalibrationError(f"invalid {name} {text!r}: values must be in [{low}, {high}]")
    return values


def methods(text: str, allowed: tuple[str, ...]) -> tuple[str, ...]:
    """Comma-separated method names, each one of ``allowed``."""
    chosen = tuple(m.strip() for m in text.split(",") if m.strip())
    unknown = [m for m in chosen if m not in allowed]
    if unknown or not chosen:
        raise CalibrationError(
            f"unknown method {unknown[0] if unknown else ''!r} (choose from {','.join(allowed)})"
        )
    return chosen


def check_outputs(
    args: argparse.Namespace, stem: str, inputs: Callable[[], Sequence[Input]] = list
) -> None:
    """``--runs``, and the outputs: writable, and none of them a file of the inputs
    (listed by ``inputs`` only when an output exists already)."""
    if args.runs < 1:
        raise CalibrationError("--runs must be at least 1")
    if args.runs > MAX_RUNS:
        raise CalibrationError(f"--runs must be at most {MAX_RUNS}, got {args.runs}")
    if args.dask is not None:
        check_dask_flag(args.dask)
    require_extra("matplotlib", stem)  # the plot is one of the outputs
    check_output_folder(args.output, "--output")
    outputs = [Output("--output", args.output / f"{stem}.{ext}") for ext in ("csv", "md", "png")]
    if args.json is not None:
        check_output_file(args.json, "--json")
        outputs.append(Output("--json", args.json))
    if any(output.path.exists() for output in outputs):
        refuse_outputs_over_inputs(outputs, inputs())


def dataset_inputs(folders: dict[str, Path | None], stem: str) -> list[Input]:
    """The files below each dataset folder (``PATH``, ``--cache``: name -> path) that a
    run may read: all but JSON files and this command's own outputs, which a rerun
    replaces."""
    own = {f"{stem}.csv", f"{stem}.md", f"{stem}.png"}
    inputs = []
    for name, folder in folders.items():
        if folder is None or not Path(folder).exists():
            continue
        below = [Path(folder)] if Path(folder).is_file() else sorted(Path(folder).rglob("*"))
        files = tuple(
            p for p in below if p.is_file() and p.suffix.lower() != ".json" and p.name not in own
        )
        inputs.append(Input(name, Path(folder), "a file of the dataset", files))
    return inputs


def finish(records: list[RunRecord], args: argparse.Namespace, stem: str, title: str) -> None:
    """Write the table, the plot and the JSON; print the table and what was written."""
    from ..evaluation.report import markdown_table, summarize, with_prior_rows, write_outputs

    try:
        paths = write_outputs(records, args.output, stem, title)
        if args.json is not None:
            text = json.dumps([r.to_json() for r in records], indent=1) + "\n"
            write_text_atomically(args.json, text)
    except OSError as exc:
        raise CalibrationError(f"cannot write the results: {exc.strerror or exc}") from None
    print(markdown_table(summarize(with_prior_rows(records))), end="")
    print(f"wrote {paths['csv']}, {paths['markdown']}, {paths['png']}")
