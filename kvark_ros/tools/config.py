"""``kvark config``: print a config file's validated settings, or the table of every key.

``kvark config --keys`` prints the Markdown table of ``kvark_ros.core.config_schema`` (the README's
key table is exactly this output); ``kvark config FILE`` prints every key of FILE after validation
and path resolution, defaults filled in: what the node, train and replay will run with. FILE is also
checked against the URDF it names (joint names, their chain order, ee and flange frames, payload) and
against the model its model_dir holds, if trained (the same joints, the same URDF).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from kvark_ros.core.config import ROBOT_DESCRIPTION, ConfigError, EstimatorConfig, load_config
from kvark_ros.core.config_schema import KEYS, Key, keys_table

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser("config", help="print a config's validated settings, or every key (--keys)",
                                   description=__doc__.split("\n\n")[1])
    parser.add_argument("file", nargs="?", help="config YAML (the node's parameter file)")
    parser.add_argument("--keys", action="store_true", help="print the table of every key (Markdown)")
    parser.set_defaults(run=run)


def _value(config: object, key: Key) -> object:
    """The config value of one key (``config.<group>.<attr>`` or ``config.<attr>``)."""
    if key.group == "payload":
        payload = getattr(config, "payload")
        return getattr(payload, key.attr) if payload is not None else key.default
    owner = getattr(config, key.group) if key.group else config
    return getattr(owner, key.attr)


def _check(path: str, config: EstimatorConfig) -> list[str]:
    """``config`` against its URDF and its trained model (module docstring): what was checked, one line each; a
    ConfigError naming ``path`` when a check fails."""
    if config.urdf == ROBOT_DESCRIPTION:
        return ["checked: not against a URDF (robot_model.urdf is robot_description: the node checks the joint and "
                "frame names when it receives the URDF)"]
    from kvark_ros.core.estimation.model_store import MODEL_FILE, load_model
    from kvark_ros.core.estimation.residual.files import ResidualModelError
    from kvark_ros.core.estimation.robot_model import RobotModel, RobotModelError, urdf_sha256
    try:
        robot = RobotModel.from_config(config)
        lines = [f"checked against {robot.urdf_name}: {robot.n} joints in chain order, ee_frame {config.ee_frame}, "
                 f"flange_frame {config.flange_frame}"]
        if not (Path(config.model_dir) / MODEL_FILE).is_file():
            return lines + [f"model: {config.model_dir} not trained yet (`kvark train` writes it)"]
        load_model(config.model_dir, config.joint_names, urdf_sha256(config.urdf))
    except (RobotModelError, ResidualModelError) as exc:
        raise ConfigError(f"{path}: {exc}") from exc
    return lines + [f"checked against the model {config.model_dir}: trained for these joints and this URDF"]


def run(args: argparse.Namespace) -> int:
    if args.keys:
        print(keys_table())
        return 0
    if not args.file:
        raise SystemExit("kvark: error: give a config FILE or --keys")
    config = load_config(args.file)
    checked = _check(args.file, config)
    width = max(len(key.name) for key in KEYS)
    for key in KEYS:
        print(f"{key.name:<{width}}  {_value(config, key)!r}")
    print("\n".join(checked))
    return 0
