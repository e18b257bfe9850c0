"""``colmap-trifocal demo``: the whole pipeline on a synthetic database with a known camera."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..common.arguments import seed
from .output import check_output_folder


def add_parser(commands: argparse._SubParsersAction) -> None:
    """``demo [--seed N] [--method M] [--keep DIR]``."""
    from ..intrinsics.api import METHODS

    demo = commands.add_parser(
        "demo", help="calibrate a synthetic database with a known camera (no download)"
    )
    demo.add_argument(
        "--seed", type=seed, default=0, help="seed of the synthetic scene and the run (default 0)"
    )
    demo.add_argument(
        "--method",
        choices=METHODS,
        default="msac-opt",
        help="TrifocalCalib variant (default msac-opt) or the Mendonça-Cipolla baseline",
    )
    demo.add_argument("--keep", type=Path, metavar="DIR", help="keep the demo database in DIR")


def run(args: argparse.Namespace) -> int:
    """Build the demo database, run the pipeline, print true against estimated; exit 0."""
    from ..synthetic.demo import format_demo, run_demo

    if args.keep is not None:
        check_output_folder(args.keep, "--keep")
    result = run_demo(seed=args.seed, workdir=args.keep, method=args.method)
    print(format_demo(result))
    return 0
