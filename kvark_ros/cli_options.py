"""Command-line options of the commands that read samples from bags: ``--trim`` (replay, train, diagnose), ``--rate``
and ``--holdout`` (train, diagnose), with the rules of ``core.estimation.inputs.select_samples``."""
from __future__ import annotations

import argparse


def add_trim_option(parser: argparse.ArgumentParser) -> None:
    """``--trim START END`` (``select_samples``), as replay, train and diagnose take it."""
    parser.add_argument("--trim", nargs=2, type=float, default=(0.0, 0.0), metavar=("START", "END"),
                        help="drop the first START and the last END seconds of the bag(s) (a start-up, a stop, a "
                             "contact)")


def holdout_share(text: str) -> float:
    """A held-out share in [0.05, 0.9] (argparse type of --holdout): enough to judge by and to fit on."""
    value = float(text)
    if not 0.05 <= value <= 0.9:
        raise argparse.ArgumentTypeError(f"must be in [0.05, 0.9], got {value:g}")
    return value


def add_sample_options(parser: argparse.ArgumentParser, holdout: float, holdout_help: str) -> None:
    """``--trim``, ``--rate`` and ``--holdout`` of the commands that learn from bags (train, diagnose)."""
    add_trim_option(parser)
    parser.add_argument("--rate", type=float, default=0.0, metavar="HZ",
                        help="keep every k-th sample for about this rate (default 0: as recorded)")
    parser.add_argument("--holdout", type=holdout_share, default=holdout, metavar="FRACTION",
                        help=f"{holdout_help} (default {holdout:g})")
