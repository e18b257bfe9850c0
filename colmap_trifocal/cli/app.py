"""The ``colmap-trifocal`` program: the parser, logging, and :func:`main` around a command.

The heavy modules (numpy, scipy, pycolmap, the pipeline) are imported inside
:func:`main`, under its error handling, so that Ctrl-C during the first second (while
they load) also ends with one ``error: interrupted`` line.
"""

from __future__ import annotations

import argparse
import sys
import warnings

from .. import __version__
from ..common.errors import CalibrationError
from . import calibrate, demo, evaluate, run, show, synthetic
from .output import EXIT_INPUT_ERROR, one_line, say_error, standard_streams
from .signals import glog_cannot_take_sigterm, report_interrupted, watching_signals

#: The commands in the order ``--help`` lists them: each module has ``add_parser`` and ``run``.
COMMANDS = {
    "calibrate": calibrate,
    "run": run,
    "evaluate": evaluate,
    "synthetic": synthetic,
    "show": show,
    "demo": demo,
}


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports usage mistakes as a single ``error: ...`` line (status 2)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"error: {one_line(message)} (see '{self.prog} --help')\n")
        raise SystemExit(EXIT_INPUT_ERROR)


def build_parser() -> argparse.ArgumentParser:
    """The ``colmap-trifocal`` argument parser (imports the pipeline for its defaults)."""
    parser = OneLineParser(
        prog="colmap-trifocal",
        description="Self-calibrate COLMAP cameras (fx, fy, cx, cy) with TrifocalCalib.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="-v info, -vv debug")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    for command in COMMANDS.values():
        command.add_parser(commands)
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


def configure_logging(verbosity: int) -> None:
    """The package's log level from -v/-vv (on stderr); the libraries' own logs only with -vv.

    Quiet by default: COLMAP's glog shows only FATAL lines (not the ERROR line
    ``Stopping thread...`` of an interrupted extraction; failures reach the user as
    exceptions), OpenCV none (its ``[ WARN:0@...]`` for an unreadable image: the
    image check says it in one line).
    """
    import logging

    import cv2
    import pycolmap

    from ..common.log import logger

    pycolmap.logging.minloglevel = 0 if verbosity > 1 else 3  # 3: FATAL only
    cv2.utils.logging.setLogLevel(
        cv2.utils.logging.LOG_LEVEL_WARNING if verbosity > 1 else cv2.utils.logging.LOG_LEVEL_SILENT
    )
    if verbosity <= 0:
        return
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG if verbosity > 1 else logging.INFO)


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
    from ..common.log import logger

    logger.info("%s: %s (%s:%d)", category.__name__, message, filename, lineno)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``colmap-trifocal`` console script; the exit status.

    Problems with the input or the environment end in one ``error: ...`` line on stderr:
    :class:`CalibrationError` and ``OSError`` (a full disk, a missing permission: the
    system's message and the file) with status 2, Ctrl-C with status 130, SIGTERM 143,
    SIGHUP 129 (whatever exception the signal turned into). Any other exception is a bug
    and keeps its traceback. Closed standard streams do not stop the command
    (:func:`~colmap_trifocal.cli.output.standard_streams`).
    """
    with standard_streams(), watching_signals() as watch:
        try:
            with glog_cannot_take_sigterm(watch):
                args = build_parser().parse_args(argv)  # imports numpy, scipy, pycolmap, ...
                args.verbosity = args.verbose + args.verbose_after
                configure_logging(args.verbosity)
            if watch.received:  # a Ctrl-C that an import swallowed (ImportError fallbacks)
                raise KeyboardInterrupt
            with warnings.catch_warnings():
                warnings.showwarning = _log_warning  # numerical warnings: -v, not stderr
                return COMMANDS[args.command].run(args)
        except KeyboardInterrupt as exc:
            return report_interrupted(exc, watch.signum)
        except CalibrationError as exc:
            if watch.received:
                return report_interrupted(exc, watch.signum)
            say_error(f"error: {exc}")
            return EXIT_INPUT_ERROR
        except OSError as exc:
            if watch.received:
                return report_interrupted(exc, watch.signum)
            where = f": {exc.filename}" if exc.filename is not None else ""
            say_error(f"error: {exc.strerror or exc}{where}")
            return EXIT_INPUT_ERROR
        except Exception as exc:
            if watch.received:
                return report_interrupted(exc, watch.signum)
            raise
