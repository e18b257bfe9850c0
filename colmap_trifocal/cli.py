"""Command line: ``colmap-trifocal calibrate DATABASE ...`` (see README / DESIGN.md).

Exit status 0 on success. Input problems print one line ``error: ...`` on
stderr and exit with status 2 (130 when interrupted by Ctrl-C, 143 on SIGTERM, 129 on
SIGHUP); no traceback.

The heavy modules (numpy, scipy, pycolmap, the pipeline) are imported inside
:func:`main`, under its error handling, so that Ctrl-C during the first second
(while they load) also ends with one ``error: interrupted`` line.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from . import __version__
from .common.arguments import seed
from .common.errors import TERMINATING_SIGNALS, CalibrationError
from .common.files import file_identity, refuse_overwriting_input, write_text_atomically

EXIT_INPUT_ERROR = 2
EXIT_INTERRUPTED = 130


def one_line(text: str) -> str:
    """``text`` with control characters escaped (a newline in a path becomes ``\\n``)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class _OneLineParser(argparse.ArgumentParser):
    """argparse that reports usage mistakes as a single ``error: ...`` line."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"error: {one_line(message)} (see '{self.prog} --help')\n")
        raise SystemExit(EXIT_INPUT_ERROR)


def build_parser() -> argparse.ArgumentParser:
    """The ``colmap-trifocal`` argument parser (imports the pipeline for its defaults)."""
    from .evaluation.commands import add_evaluate_parser, add_synthetic_parser

    parser = _OneLineParser(
        prog="colmap-trifocal",
        description="Self-calibrate COLMAP cameras (fx, fy, cx, cy) with TrifocalCalib.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="-v info, -vv debug")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_OneLineParser)
    _add_calibrate_parser(commands)
    _add_run_parser(commands)
    add_evaluate_parser(commands)
    add_synthetic_parser(commands)
    _add_show_parser(commands)
    _add_demo_parser(commands)
    for subparser in commands.choices.values():  # also accepted after the subcommand
        subparser.add_argument(
            "-v",
            "--verbose",
            action="count",
            default=0,
            dest="verbose_after",
            help="-v info, -vv debug",
        )
    return parser


def _add_calibrate_parser(commands: argparse._SubParsersAction) -> None:
    """``calibrate DATABASE``: the contract in DESIGN.md."""
    from .database.camera_groups import GROUPINGS
    from .intrinsics.calibrate import METHODS, CalibrationOptions
    from .reconstruction.mapping import REFINE_CHOICES

    calibrate = commands.add_parser(
        "calibrate", help="estimate the intrinsics of the cameras of a COLMAP database"
    )
    calibrate.add_argument("database", type=Path, help="COLMAP database with verified matches")
    calibrate.add_argument("--method", choices=METHODS, default="msac-opt")
    calibrate.add_argument(
        "--prior",
        metavar="FX,FY,CX,CY",
        help="starting intrinsics in pixels (default: the camera stored in the database)",
    )
    calibrate.add_argument(
        "--camera-id",
        type=int,
        action="append",
        dest="camera_ids",
        metavar="ID",
        help="calibrate only the group of this camera (repeatable)",
    )
    calibrate.add_argument(
        "--group",
        choices=GROUPINGS,
        default="auto",
        help="camera ids sharing intrinsics: auto (same model, size and stored parameters; "
        "default), camera (each camera id alone), all (every image one camera)",
    )
    calibrate.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    calibrate.add_argument(
        "--json",
        type=Path,
        metavar="OUT",
        help="write the results as JSON (-: to stdout, the table then goes to stderr)",
    )
    calibrate.add_argument(
        "--write",
        action="store_true",
        help="store the estimate in the database (a backup <name>.bak is made first)",
    )
    calibrate.add_argument("--max-triplets", type=int, default=CalibrationOptions.max_triplets)
    calibrate.add_argument(
        "--no-prior",
        action="store_true",
        help="ignore the stored camera: start from f = 1.2 · max(width, height), centred",
    )
    calibrate.add_argument(
        "--no-focal-search",
        action="store_true",
        help="start the tensors from the prior's focal length instead of searching it",
    )
    calibrate.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    calibrate.add_argument(
        "--model",
        type=Path,
        metavar="DIR",
        help="existing COLMAP model of this database: write the estimate into a copy (--output)",
    )
    calibrate.add_argument(
        "--output", type=Path, metavar="DIR", help="new folder for the model written with --model"
    )
    calibrate.add_argument(
        "--refine",
        choices=REFINE_CHOICES,
        help="with --model: bundle adjustment of focal lengths and principal points (default ba)",
    )
    calibrate.add_argument(
        "--refine-distortion",
        action="store_true",
        help="with --model --refine ba: also refine the distortion parameters",
    )


def _add_run_parser(commands: argparse._SubParsersAction) -> None:
    """``run IMAGES WORKSPACE``: features, calibration, mapping, bundle adjustment."""
    from .database.camera_groups import GROUPINGS
    from .database.cameras import SUPPORTED_MODELS
    from .database.features import MATCHERS
    from .intrinsics.calibrate import METHODS
    from .reconstruction.mapping import MAPPERS, REFINE_CHOICES
    from .reconstruction.workflow import RunOptions

    run = commands.add_parser(
        "run", help="images -> features -> TrifocalCalib -> mapping -> bundle adjustment"
    )
    run.add_argument(
        "images", type=Path, help="folder of images (with --database: optional, for colours)"
    )
    run.add_argument(
        "workspace", type=Path, help="output folder: database.db, sparse/0, report.json"
    )
    run.add_argument("--max-image-size", type=int, default=RunOptions.max_image_size)
    run.add_argument("--matcher", choices=MATCHERS, default=RunOptions.matcher)
    run.add_argument(
        "--camera-model",
        default=RunOptions.camera_model,
        choices=SUPPORTED_MODELS,
        help="COLMAP model of the new cameras (default PINHOLE; one camera per image, as "
        "COLMAP's default, grouped into physical cameras by --group)",
    )
    run.add_argument("--group", choices=GROUPINGS, default=RunOptions.group)
    run.add_argument(
        "--mapper",
        choices=MAPPERS,
        default=RunOptions.mapper,
        help="pycolmap incremental mapping or the global mapper (GLOMAP), both started "
        "from the TrifocalCalib estimate",
    )
    run.add_argument("--method", choices=METHODS, default=RunOptions.method)
    run.add_argument("--refine", choices=REFINE_CHOICES, default=RunOptions.refine)
    run.add_argument("--seed", type=seed, default=0)
    run.add_argument("--database", type=Path, help="start from this database (it is copied)")
    run.add_argument(
        "--model",
        type=Path,
        help="existing COLMAP model (with --database): write the estimate, refine",
    )
    run.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the results of an earlier run in WORKSPACE",
    )
    run.add_argument(
        "--png", type=Path, metavar="OUT", help="render the model offscreen to this PNG (Open3D)"
    )


def _add_show_parser(commands: argparse._SubParsersAction) -> None:
    """``show MODEL``: the Open3D view of a COLMAP model."""
    show = commands.add_parser(
        "show", help="Open3D view of a COLMAP model (points, camera frustums)"
    )
    show.add_argument("model", type=Path, help="COLMAP model folder, e.g. WORKSPACE/sparse/0")
    show.add_argument("--png", type=Path, metavar="OUT", help="render offscreen to this PNG")


def _add_demo_parser(commands: argparse._SubParsersAction) -> None:
    """``demo``: the whole pipeline on a synthetic database with a known camera."""
    from .intrinsics.calibrate import METHODS

    demo = commands.add_parser(
        "demo", help="calibrate a synthetic database with a known camera (no download)"
    )
    demo.add_argument("--seed", type=seed, default=0)
    demo.add_argument("--method", choices=METHODS, default="msac-opt")
    demo.add_argument("--keep", type=Path, metavar="DIR", help="keep the demo database in DIR")


def _configure_logging(verbosity: int) -> None:
    """Package log level from -v/-vv; COLMAP's own (glog) messages only with -vv."""
    import logging

    import pycolmap

    from .common.log import logger

    pycolmap.logging.minloglevel = 0 if verbosity > 1 else 2  # 2: errors only
    if verbosity <= 0:
        return
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG if verbosity > 1 else logging.INFO)


def _check_output(path: Path, option: str) -> None:
    """Refuse an output that :func:`_write_text` cannot write, before any work is done."""
    if path.exists() and not path.is_file():  # a device or a pipe, written directly
        if path.is_dir() or not os.access(path, os.W_OK):
            raise CalibrationError(f"cannot write {option}: {path} is not a writable file")
        return
    folder = Path(os.path.realpath(path)).parent
    if not folder.is_dir():
        raise CalibrationError(f"cannot write {option}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK):  # the new file is made next to it, then renamed
        raise CalibrationError(f"cannot write {option}: folder {folder} is not writable")


def _run_calibrate(args: argparse.Namespace) -> int:
    from .database.camera_groups import format_ids
    from .database.snapshot import check_writable
    from .intrinsics.calibrate import (
        CalibrationOptions,
        add_read_seconds,
        calibrate_groups,
        check_options,
        parse_prior,
        read_contents,
        updated_cameras,
        write_calibrations,
    )

    # The database is written last (after the JSON), by write_calibrations below.
    options = CalibrationOptions(
        method=args.method,
        prior=parse_prior(args.prior) if args.prior is not None else None,
        camera_ids=args.camera_ids,
        seed=args.seed,
        max_triplets=args.max_triplets,
        focal_search=not args.no_focal_search,
        no_prior=args.no_prior,
        progress=not args.no_progress and sys.stderr.isatty(),
        group=args.group,
    )
    if args.max_triplets < 1:
        raise CalibrationError("--max-triplets must be at least 1")
    if (args.model is None) != (args.output is None):
        raise CalibrationError("--model and --output go together")
    if args.model is None and (args.refine is not None or args.refine_distortion):
        raise CalibrationError("--refine and --refine-distortion need --model and --output")
    if args.refine_distortion and args.refine == "none":
        raise CalibrationError("--refine-distortion needs --refine ba")
    if args.model is not None:
        from .reconstruction.into_model import check_model_images, check_output_folder, read_model

        check_output_folder(args.output, args.model)
        read_model(args.model)  # a one-line error now, not after the calibration
    json_to_stdout = args.json is not None and _is_stdout(args.json)
    if args.json is not None and not json_to_stdout:
        _check_output(args.json, "--json")
        refuse_overwriting_input(
            args.json, _database_files(args.database), "--json", "the database"
        )
    if args.write:  # refuse a read-only database now, not after the calibration
        check_writable(args.database)
    check_options(options)
    contents, read_seconds = read_contents(args.database)
    if args.model is not None:
        check_model_images(read_model(args.model), contents.image_names.values(), args.model)
    by_method, skipped = calibrate_groups(contents, options, (options.method,))
    results = by_method[options.method]
    add_read_seconds(results, read_seconds)
    # With the JSON on stdout, the table and messages go to stderr: stdout stays JSON.
    out = sys.stderr if json_to_stdout else sys.stdout
    print(
        f"{'camera':>6} {'model':<14} {'method':<11} {'fx':>10} {'fy':>10} {'cx':>10} "
        f"{'cy':>10} {'triplets':>9} {'time':>7} {'ids':>4}",
        file=out,
    )
    for r in results:
        print(
            f"{r.camera_id:>6} {r.model:<14} {r.method:<11} {r.fx:>10.2f} {r.fy:>10.2f} "
            f"{r.cx:>10.2f} {r.cy:>10.2f} {r.num_inlier_triplets:>4}/{r.num_triplets:<4} "
            f"{r.seconds:>6.1f}s {len(r.camera_ids):>4}",
            file=out,
        )
        if len(r.camera_ids) > 1:
            print(f"{'':>6} shared by camera ids {format_ids(r.camera_ids)}", file=out)
        warning = r.warning()
        if warning is not None:
            print(f"warning: {warning}", file=sys.stderr)
    for group in skipped:
        print(f"warning: {group.message()}", file=sys.stderr)
    update = None
    if args.model is not None:
        from .reconstruction.into_model import calibrate_model

        update = calibrate_model(
            args.model,
            args.output,
            updated_cameras(results),
            args.refine or "ba",
            args.refine_distortion,
        )
        print(update.describe(), file=out)
    if args.json is not None:
        entries = [r.to_json() for r in results] + [g.to_json() for g in skipped]
        if update is not None:
            for entry in entries:
                entry["model"] = update.to_json()
        text = json.dumps(entries, indent=2) + "\n"
        try:
            if json_to_stdout:
                sys.stdout.write(text)
                sys.stdout.flush()
            else:
                write_text_atomically(args.json, text)
        except OSError as exc:
            raise CalibrationError(f"cannot write {args.json}: {exc.strerror or exc}") from None
    if args.write:
        written = write_calibrations(args.database, results)
        if written:
            print(f"wrote {written} camera(s) to {args.database}", file=out)
        for r in results:
            if not r.determined_anything:
                print(
                    f"camera {r.camera_id} not written: the images determine none of its values",
                    file=out,
                )
    return 0


def _is_stdout(path: Path) -> bool:
    """``-``, or a path naming this process's standard output (``/dev/stdout``, ...)."""
    if str(path) == "-":
        return True
    try:
        st = os.fstat(sys.stdout.fileno())
    except (OSError, ValueError):  # no usable file descriptor (captured, closed)
        return False
    return file_identity(path) == (st.st_dev, st.st_ino)


def _files_in(folder: Path) -> list[Path]:
    """The files directly in ``folder`` (none if it is not a folder)."""
    return [p for p in folder.iterdir() if p.is_file()] if folder.is_dir() else []


def _database_files(database: Path) -> list[Path]:
    """The database and SQLite's companion files (which no output may replace either)."""
    return [database, *(database.with_name(database.name + s) for s in ("-wal", "-journal"))]


def _run_pipeline(args: argparse.Namespace) -> int:
    from .reconstruction.workflow import RunOptions, format_report, run_pipeline

    if args.max_image_size < 100:
        raise CalibrationError("--max-image-size must be at least 100 pixels")
    if args.png is not None:
        _check_output(args.png, "--png")
        if args.database is not None:
            refuse_overwriting_input(
                args.png, _database_files(args.database), "--png", "the database"
            )
        if args.model is not None:
            refuse_overwriting_input(args.png, _files_in(args.model), "--png", "a file of --model")
    options = RunOptions(
        max_image_size=args.max_image_size,
        matcher=args.matcher,
        camera_model=args.camera_model,
        group=args.group,
        mapper=args.mapper,
        method=args.method,
        refine=args.refine,
        seed=args.seed,
        database=args.database,
        model=args.model,
        overwrite=args.overwrite,
        progress=sys.stderr.isatty(),
    )
    # With --database, IMAGES is optional (only used to colour the points).
    images = args.images if args.database is None or args.images.is_dir() else None
    report = run_pipeline(images, args.workspace, options)
    print(format_report(report))
    for camera in report["cameras"]:
        if camera["warning"] is not None:
            print(f"warning: {camera['warning']}", file=sys.stderr)
    if args.png is not None:
        from .reconstruction.visualize import show

        print(f"wrote {show(args.workspace / 'sparse' / '0', args.png)}")
    return 0


def _dispatch(args: argparse.Namespace) -> int:
    """Run the chosen command; its exit status."""
    if args.command == "calibrate":
        return _run_calibrate(args)
    if args.command == "run":
        return _run_pipeline(args)
    if args.command == "show":
        from .reconstruction.visualize import show  # open3d is imported only for this command

        if args.png is not None:
            refuse_overwriting_input(args.png, _files_in(args.model), "--png", "a file of MODEL")
        written = show(args.model, args.png)
        if written is not None:
            print(f"wrote {written}")
        return 0
    if args.command == "evaluate":
        from .evaluation.commands import run_evaluate

        return run_evaluate(args, sys.stderr.isatty())
    if args.command == "synthetic":
        from .evaluation.commands import run_synthetic

        return run_synthetic(args, sys.stderr.isatty())
    if args.command == "demo":
        from .synthetic.demo import format_demo, run_demo

        result = run_demo(seed=args.seed, workdir=args.keep, method=args.method)
        print(format_demo(result))
        return 0
    return EXIT_INPUT_ERROR


class _InterruptWatch:
    """Handler of SIGINT, SIGTERM and SIGHUP: raises KeyboardInterrupt and remembers the signal.

    All three end a run the same way (the write in progress rolled back, one ``error:``
    line), SIGINT as Python's own handler does. Some libraries turn the KeyboardInterrupt
    into another exception, e.g. pycolmap's C++ module, interrupted while it loads, fails
    with an ``ImportError``/``RuntimeError``; :func:`main` still reports such a run as
    interrupted.
    """

    def __init__(self) -> None:
        self.signum: int | None = None

    @property
    def received(self) -> bool:
        return self.signum is not None

    def __call__(self, signum: int, frame: object) -> None:
        if self.signum is None:
            self.signum = signum
        raise KeyboardInterrupt

    def install(self) -> dict[int, Any]:
        """Install for every signal not ignored (``nohup``); the previous handlers."""
        return {
            signum: signal.signal(signum, self)
            for signum in TERMINATING_SIGNALS
            if signal.getsignal(signum) is not signal.SIG_IGN
        }


@contextmanager
def _glog_cannot_take_sigterm(watch: _InterruptWatch, in_main_thread: bool) -> Iterator[None]:
    """Hold SIGTERM back while pycolmap loads; then install ``watch`` for it again.

    Importing pycolmap installs glog's failure handler for SIGTERM (and SIGSEGV, ...),
    which ends the process with a stack dump and no clean-up. A SIGTERM that arrives
    meanwhile stays pending (``pthread_sigmask``) and reaches ``watch`` afterwards.
    """
    if not in_main_thread or signal.getsignal(signal.SIGTERM) is not watch:
        yield
        return
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, watch)
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def _log_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: object = None,
    line: str | None = None,
) -> None:
    """Python warnings (numpy's RuntimeWarnings, ...) go to the package log (-v).

    stderr carries one ``error:`` line or the tool's own ``warning:`` lines only; a
    numerical warning says nothing the result's checks do not say better.
    """
    from .common.log import logger

    logger.info("%s: %s (%s:%d)", category.__name__, message, filename, lineno)


def _interrupted(exc: BaseException, signum: int | None = None) -> int:
    """Print the one line for an interrupted run; its exit status (128 + the signal).

    Ctrl-C (SIGINT) is "interrupted", SIGTERM and SIGHUP "terminated".
    """
    detail = f" ({exc})" if isinstance(exc, KeyboardInterrupt) and str(exc) else ""
    signum = signal.SIGINT if signum is None else signum
    word = "interrupted" if signum == signal.SIGINT else "terminated"
    if signum == signal.SIGHUP:
        detail = f" (hangup){detail}"
    print(one_line(f"error: {word}{detail}"), file=sys.stderr)
    return 128 + int(signum)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``colmap-trifocal`` console script.

    Problems with the input or the environment end in one ``error: ...`` line on stderr:
    :class:`CalibrationError` and ``OSError`` (a full disk, a missing permission: the
    system's message and the file) with status 2, Ctrl-C with status 130 (whatever
    exception it turned into). Any other exception is a bug and keeps its traceback.
    """
    watch = _InterruptWatch()
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = watch.install() if in_main_thread else {}
    try:
        with _glog_cannot_take_sigterm(watch, in_main_thread):
            args = build_parser().parse_args(argv)  # imports numpy, scipy, pycolmap, ...
            _configure_logging(args.verbose + args.verbose_after)
        if watch.received:  # a Ctrl-C that an import swallowed (ImportError fallbacks)
            raise KeyboardInterrupt
        with warnings.catch_warnings():
            warnings.showwarning = _log_warning  # numerical warnings: -v, not stderr
            return _dispatch(args)
    except KeyboardInterrupt as exc:
        return _interrupted(exc, watch.signum)
    except CalibrationError as exc:
        if watch.received:
            return _interrupted(exc, watch.signum)
        print(one_line(f"error: {exc}"), file=sys.stderr)
        return EXIT_INPUT_ERROR
    except OSError as exc:
        if watch.received:
            return _interrupted(exc, watch.signum)
        where = f": {exc.filename}" if exc.filename is not None else ""
        print(one_line(f"error: {exc.strerror or exc}{where}"), file=sys.stderr)
        return EXIT_INPUT_ERROR
    except Exception as exc:
        if watch.received:
            return _interrupted(exc, watch.signum)
        raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


if __name__ == "__main__":
    sys.exit(main())
