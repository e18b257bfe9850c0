"""``colmap-trifocal calibrate DB [DB ...]``: many inputs, one JSON line per camera group.

Each input (a database, or a COLMAP model folder) is calibrated on its own with the same
options (``--write`` stores each database's estimate as a single run does); its lines
(:func:`.batch_input.calibrate_input`) are written as it finishes, to ``--json
FILE`` or to standard output (``--json -``, the default). An input that fails gives one
line ``{"database", "error"}`` and one ``error: PATH: message`` line on stderr, and the
others go on; the exit status is then :data:`EXIT_SOME_FAILED`. Locally the inputs run
one after the other in this process (each calibration uses every core); with ``--dask``
they go to the workers of a Dask scheduler (:func:`..evaluation.runner.completed_tasks`).
A progress bar over the inputs is shown on stderr when it is a terminal.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import os
import stat
import sys
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from tqdm import tqdm

from ..common.errors import CalibrationError
from ..common.files import Input, Output, refuse_outputs_over_inputs
from ..common.streams import StreamOutput, descriptor_of, is_stream
from .calibrate_model import model_copy_flags
from .output import check_output_file, is_stdout, one_line

if TYPE_CHECKING:
    from ..intrinsics.api import CalibrationOptions

#: Exit status when at least one input failed (the others' lines are written).
EXIT_SOME_FAILED = 1

#: Characters that make an argument a glob pattern (when no file has that name).
_GLOB_CHARACTERS = frozenset("*?[")


def expand_inputs(arguments: list[Path]) -> tuple[list[Path], bool]:
    """The inputs the arguments name, and whether they are a batch.

    An argument that names no existing path and holds ``*``, ``?`` or ``[`` is a glob
    pattern (``**`` recursive), expanded in sorted order. The same file named twice is
    kept once. A batch is more than one argument or any pattern.

    Raises:
        CalibrationError: a pattern matches nothing.
    """
    paths: list[Path] = []
    pattern = False
    for argument in arguments:
        text = str(argument)
        if not os.path.lexists(text) and _GLOB_CHARACTERS & set(text):
            matches = sorted(glob.glob(text, recursive=True))
            if not matches:
                raise CalibrationError(f"no database or model folder matches {text}")
            paths.extend(Path(m) for m in matches)
            pattern = True
        else:
            paths.append(argument)
    unique: dict[str, Path] = {}
    for path in paths:
        unique.setdefault(os.path.realpath(path), path)
    return list(unique.values()), pattern or len(arguments) > 1


def run_batch(args: argparse.Namespace, paths: list[Path], options: CalibrationOptions) -> int:
    """Calibrate every input, writing its lines as it finishes; the exit status."""
    from ..evaluation.runner import completed_tasks
    from .batch_input import InputTask, calibrate_input

    _check_batch_arguments(args, paths)
    to_stdout = args.json is None or is_stdout(args.json)
    options = dataclasses.replace(options, progress=False)  # one bar: over the inputs
    tasks = [InputTask(str(path), options, args.write) for path in paths]
    progress = not args.no_progress and sys.stderr.isatty()
    failed = written = 0
    with _Lines(None if to_stdout else args.json) as output:
        for _, lines in completed_tasks(
            calibrate_input, tasks, 1, args.dask, "databases", progress=progress
        ):
            for line in lines:
                output.write(line)
                written += 1
                _report(line)
            failed += any("error" in line for line in lines)
    if not to_stdout:
        print(
            f"{len(paths) - failed} of {len(paths)} inputs calibrated; "
            f"wrote {written} line(s) to {args.json}"
        )
    return EXIT_SOME_FAILED if failed else 0


def _check_batch_arguments(args: argparse.Namespace, paths: list[Path]) -> None:
    """Refuse the flags that take one database, ``--write`` for a model folder, and a
    ``--json`` that cannot be written or is one of the inputs (or their files)."""
    from .batch_input import is_model_folder

    single = model_copy_flags(args) + ["--cameras-txt"] * (args.cameras_txt is not None)
    if single:
        raise CalibrationError(f"{single[0]} takes one database, not several inputs")
    models = [path for path in paths if is_model_folder(path)]
    if args.write and models:
        raise CalibrationError(
            f"--write stores the estimate in a database: {models[0]} is a COLMAP model folder"
        )
    if args.json is not None:
        check_output_file(args.json, "--json")
        if not is_stdout(args.json):
            inputs = [Input.folder(p, "MODEL") if p in models else Input.database(p) for p in paths]
            refuse_outputs_over_inputs([Output("--json", args.json)], inputs)


def _report(line: dict) -> None:
    """An input's error, or a group's warning, as one line on stderr (above the bar)."""
    for kind in ("error", "warning"):
        if line.get(kind):
            tqdm.write(one_line(f"{kind}: {line['database']}: {line[kind]}"), file=sys.stderr)


class _Lines:
    """JSON lines to standard output (``path`` None) or to ``path``, flushed line by line.

    The file is created at the first line, so a run that fails before any input
    finishes (an unreachable scheduler) leaves an existing file as it was.
    """

    def __init__(self, path: Path | None):
        self.path = path
        self.stream: TextIO | None = None
        self.special: StreamOutput | None = None  # a pipe, FIFO or device: never blocks

    def __enter__(self) -> _Lines:
        return self

    def __exit__(self, *_: object) -> None:
        if self.stream is not None and self.path is not None:
            self.stream.close()
        if self.special is not None:
            self.special.close()

    def write(self, line: dict) -> None:
        text = json.dumps(line) + "\n"
        try:
            if self.path is not None and self.stream is None and self.special is None:
                fd = descriptor_of(self.path)
                if fd is not None and stat.S_ISREG(os.fstat(fd).st_mode):  # 2>err.txt
                    self.stream = os.fdopen(os.dup(fd), "w", encoding="utf-8")
                elif fd is not None or is_stream(self.path):
                    self.special = StreamOutput(self.path).open()
                else:
                    self.stream = open(self.path, "w", encoding="utf-8")  # noqa: SIM115
            if self.special is not None:
                self.special.write(text.encode("utf-8"))
                return
            stream = sys.stdout if self.stream is None else self.stream
            stream.write(text)
            stream.flush()
        except OSError as exc:
            where = "standard output" if self.path is None else self.path
            raise CalibrationError(f"cannot write {where}: {exc.strerror or exc}") from None
