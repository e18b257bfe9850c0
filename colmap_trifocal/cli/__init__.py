"""The command line, ``colmap-trifocal COMMAND``: one module per command, and what they share.

Takes every stage; no stage takes anything from it. Each command module
(:mod:`intrinsics.api`, :mod:`.run`, :mod:`.show`, :mod:`.demo`, :mod:`.evaluate`,
:mod:`.synthetic`) has ``add_parser`` and ``run``; ``calibrate`` hands a model folder to
:mod:`.calibrate_model` and several inputs to :mod:`.batch`, and prints :mod:`.tables`.
:mod:`.app` holds the parser and :func:`main`, :mod:`.signals` the handling of
SIGINT/SIGTERM/SIGHUP, :mod:`.output` the one-line messages, the standard streams and the
output path checks. Only this package prints; the library returns results and raises
:class:`CalibrationError`.

Exit status 0 on success. Input problems print one line ``error: ...`` on stderr and
exit with status 2 (130 when interrupted by Ctrl-C, 143 on SIGTERM, 129 on SIGHUP); no
traceback. ``calibrate`` with several inputs exits with status 1 when some of them
failed (one ``error: PATH: ...`` line each) and the others were calibrated.
"""

from .app import build_parser, main

__all__ = ["build_parser", "main"]
