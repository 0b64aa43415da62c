"""The ``kvark`` command: one entry point, one sub-command per job.

The sub-commands are a table: ``kvark --help`` lists them without importing their modules (which import
pinocchio, scipy, sklearn, rosbags, matplotlib, mujoco), and ``kvark COMMAND ...`` imports COMMAND's alone.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
from typing import Any, NamedTuple, Protocol

from kvark_ros import __version__


class SubParsers(Protocol):
    """The ``subparsers`` a command module's ``add_parser`` registers on (argparse's own class for it is private)."""

    def add_parser(self, name: str, **kwargs: Any) -> argparse.ArgumentParser:
        """Register the sub-command ``name`` (``kwargs``: ``help`` and ArgumentParser's) and return its parser."""


class Command(NamedTuple):
    """A sub-command: its name, the module whose ``add_parser(subparsers)`` registers it, and its one-line help."""

    name: str
    module: str
    help: str


COMMANDS = (
    Command("simulate", "kvark_ros.sim.cli", "record a simulated run with ground truth into a bag"),
    Command("excitation", "kvark_ros.sim.excitation_command",
            "write an optimised excitation trajectory within a real arm's limits (CSV, JointTrajectory)"),
    Command("diagnose", "kvark_ros.gap.diagnose",
            "name the physical effects the nominal model lacks, from contact-free bags"),
    Command("train", "kvark_ros.tools.train", "train the residual models and filter tuning from contact-free bags"),
    Command("replay", "kvark_ros.tools.replay",
            "run a bag through observers; write an output bag, metrics, plots and a report"),
    Command("evaluate", "kvark_ros.tools.evaluate",
            "run many bags through observers on a Dask cluster; one table of every bag's metrics"),
    Command("benchmark", "kvark_ros.tools.benchmark",
            "simulate, train and compare every observer (writes results.json and report.md)"),
    Command("bench", "kvark_ros.tools.step_latency", "per-step latency of the estimator on a synthetic stream"),
    Command("soak", "kvark_ros.tools.soak", "long faulty run of the estimator: NaN, crashes, covariance SPD, memory"),
    Command("config", "kvark_ros.tools.config", "print a config's validated settings, or every key (--keys)"),
    Command("init", "kvark_ros.tools.init", "write a commented config for a new robot from its URDF or xacro"),
    Command("import", "kvark_ros.tools.importer", "convert a robot log (CSV/text, NPZ, MAT) into a ROS 2 bag"),
    Command("play", "kvark_ros.ros.player", "publish a bag's joint states and effort commands to ROS 2 (rclpy)"),
    Command("node-check", "kvark_ros.ros.node_check",
            "run the ROS 2 node on a bag over loopback DDS and compare it with replay (rclpy)"),
)
ROS_HINT = ("source a ROS 2 Jazzy environment, or install the ROS 2 wheels: pip install -e '.[ros]' "
            "(linux x86_64; `make demo` and `make test` put them in .venv)")

# The errors a user causes (a bad file, config, model, bag or plant), printed as one line: (defining module, class).
# A class whose module is not loaded cannot have been raised, so checking for them imports nothing.
USER_ERRORS = (("kvark_ros.core.estimation.augmentation", "AugmentationError"),
               ("kvark_ros.core.config", "ConfigError"), ("kvark_ros.core.files", "OutputExistsError"),
               ("kvark_ros.core.estimation.observers.base", "ObserverError"),
               ("kvark_ros.core.estimation.residual.files", "ResidualModelError"),
               ("kvark_ros.core.estimation.robot_model", "RobotModelError"), ("kvark_ros.io.runs", "BagError"),
               ("kvark_ros.sim.plant", "PlantError"))


def available_commands() -> tuple[Command, ...]:
    """The sub-commands this installation has: ``simulate`` needs the [sim] extra (mujoco)."""
    has_mujoco = importlib.util.find_spec("mujoco") is not None
    return tuple(command for command in COMMANDS if command.name != "simulate" or has_mujoco)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``kvark`` parser; only ``command``'s module is imported, to register its full sub-parser."""
    parser = argparse.ArgumentParser(
        prog="kvark", description="Sensorless external torque and wrench estimation (K-VARK) for robot arms.")
    parser.add_argument("--version", action="version", version=f"kvark_ros {__version__}")
    subparsers = parser.add_subparsers(title="commands", metavar="COMMAND")
    for entry in available_commands():
        if entry.name == command:
            try:
                module = importlib.import_module(entry.module)
            except ModuleNotFoundError as exc:
                if not entry.module.startswith("kvark_ros.ros."):
                    raise
                parser.exit(1, f"kvark {entry.name}: needs ROS 2 rclpy ({exc.name} is missing): {ROS_HINT}\n")
            module.add_parser(subparsers)
        else:           # listed in `kvark --help`; never parsed
            subparsers.add_parser(entry.name, help=entry.help)
    return parser


def user_errors() -> tuple[type[Exception], ...]:
    """The ``USER_ERRORS`` classes of the loaded modules, and FileNotFoundError."""
    loaded = tuple(getattr(sys.modules[module], name) for module, name in USER_ERRORS if module in sys.modules)
    return loaded + (FileNotFoundError,)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(next((arg for arg in argv if not arg.startswith("-")), None))
    args = parser.parse_args(argv)
    if not hasattr(args, "run"):
        parser.print_help()
        return 2
    try:
        return args.run(args)
    except user_errors() as exc:        # evaluated once the command has run: its modules are loaded
        print(f"kvark: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("kvark: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
