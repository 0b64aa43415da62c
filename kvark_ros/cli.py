"""The ``kvark`` command: one entry point, one sub-command per job."""
from __future__ import annotations

import argparse
import sys

from kvark_ros import __version__
from kvark_ros.core.augmentation import AugmentationError
from kvark_ros.core.config import ConfigError
from kvark_ros.core.observers import ObserverError
from kvark_ros.core.residual import ResidualModelError
from kvark_ros.core.robot_model import RobotModelError
from kvark_ros.gap import diagnose
from kvark_ros.io import BagError
from kvark_ros.sim.plant import PlantError
from kvark_ros.tools import bench, benchmark, config, importer, init, replay, soak, train

USER_ERRORS = (AugmentationError, ConfigError, ResidualModelError, RobotModelError, BagError, ObserverError, PlantError,
               FileNotFoundError)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kvark", description="Sensorless external torque and wrench estimation (K-VARK) for robot arms.")
    parser.add_argument("--version", action="version", version=f"kvark_ros {__version__}")
    subparsers = parser.add_subparsers(title="commands", metavar="COMMAND")
    try:
        from kvark_ros.sim.cli import add_simulate_parser
    except ImportError:          # the simulator needs the [sim] extra (mujoco)
        pass
    else:
        simulate = add_simulate_parser(subparsers)
        simulate.set_defaults(run=simulate.get_default("func"))
    diagnose.add_parser(subparsers)
    train.add_parser(subparsers)
    replay.add_parser(subparsers)
    benchmark.add_parser(subparsers)
    bench.add_parser(subparsers)
    soak.add_parser(subparsers)
    config.add_parser(subparsers)
    init.add_parser(subparsers)
    importer.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "run"):
        parser.print_help()
        return 2
    try:
        return args.run(args)
    except USER_ERRORS as exc:
        print(f"kvark: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("kvark: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
