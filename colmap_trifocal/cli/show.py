"""``colmap-trifocal show MODEL``: the Open3D view of a COLMAP model (window or ``--png``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..common.files import Input, Output, refuse_outputs_over_inputs
from .output import check_output_file, native_output_silenced, warn


def add_parser(commands: argparse._SubParsersAction) -> None:
    """``show MODEL [--png OUT]``."""
    show = commands.add_parser(
        "show", help="Open3D view of a COLMAP model (points, camera frustums)"
    )
    show.add_argument("model", type=Path, help="COLMAP model folder, e.g. WORKSPACE/sparse/0")
    show.add_argument("--png", type=Path, metavar="OUT", help="render offscreen to this PNG")


def run(args: argparse.Namespace) -> int:
    """Check the PNG path, then render (Open3D's own lines only with ``-vv``); exit 0."""
    from ..common.extras import require_extra
    from ..reconstruction.visualize import show  # open3d is imported only for this command

    require_extra("open3d", "show")
    if args.png is None:
        show(args.model, None, warn=warn)  # an interactive window
        return 0
    check_output_file(args.png, "--png")
    refuse_outputs_over_inputs([Output("--png", args.png)], [Input.folder(args.model, "MODEL")])
    problems: list[str] = []  # said after the block: its stderr is /dev/null
    with native_output_silenced(args.verbosity):
        written = show(args.model, args.png, warn=problems.append)
    for problem in problems:
        warn(problem)
    print(f"wrote {written}")
    return 0
