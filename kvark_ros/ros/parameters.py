"""The node's ROS parameters: declared from the config key table, read back into one frozen config.

Every key of ``kvark_ros.core.config_schema`` becomes a parameter with a descriptor made from its row
(meaning, allowed values, range, read-only unless the key may change at run time); there are no
node-only parameters (``input.torque_source`` replaced the former ``torque_source``). Validation is
the config's own (``config_from_parameters``): one set of rules for the YAML file, the CLI and the
node, plus, for a payload changed at run time, that it is a physical rigid body
(``kvark_ros.core.estimation.estimator.payload_problem``).
"""
from __future__ import annotations

import array
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter

from kvark_ros.core.config import ConfigError, EstimatorConfig, config_from_parameters, path_folders, with_folders
from kvark_ros.core.config_schema import KEYS, KEYS_BY_NAME, Key
from kvark_ros.core.estimation.estimator import payload_problem

T = Parameter.Type
PAYLOAD_PREFIX = "robot_model.payload."
PARAMETERS: dict[str, Key] = KEYS_BY_NAME
RUNTIME_KEYS = tuple(key.name for key in KEYS if key.runtime)
_ROS_TYPES = {"number": T.DOUBLE, "integer": T.INTEGER, "names": T.STRING_ARRAY, "vector3": T.DOUBLE_ARRAY,
              "vector6": T.DOUBLE_ARRAY, "per_joint": T.DOUBLE_ARRAY}


def _plain(value: Any) -> Any:
    """A parameter value as the config expects it: arrays as lists."""
    return list(value) if isinstance(value, (array.array, tuple)) else value


def config_folder() -> Path | None:
    """The folder relative config paths resolve against, as ``kvark`` resolves them against the config file's
    folder: share/kvark_ros/config of the ament index (a colcon install, ``ros2 run``), else the source tree's
    config/ (a checkout, an editable install), else ``<prefix>/share/kvark_ros/config`` (a pip install: setup.py's
    data_files); None: the working directory. Without an ament environment (no ``AMENT_PREFIX_PATH``, as after
    ``pip install``) the index is skipped, not an error."""
    candidates = []
    try:
        from ament_index_python.packages import get_package_share_directory
        candidates.append(Path(get_package_share_directory("kvark_ros")) / "config")
    except (ImportError, LookupError, OSError, ValueError):   # no index, no AMENT_PREFIX_PATH, or not in it
        pass
    candidates += [Path(__file__).resolve().parents[2] / "config", Path(sys.prefix) / "share" / "kvark_ros" / "config"]
    return next((folder for folder in candidates if folder.is_dir()), None)


def descriptor(key: Key) -> ParameterDescriptor:
    """The ROS descriptor of one config key: meaning, allowed values, read-only unless run-time, range."""
    kind = _ROS_TYPES.get(key.kind, T.STRING)
    result = ParameterDescriptor(description=key.meaning, additional_constraints=key.allowed,
                                 read_only=not key.runtime)
    if kind in (T.DOUBLE, T.DOUBLE_ARRAY):
        result.dynamic_typing = True      # YAML integers are numbers too; the config validates
    if key.low is not None:
        if kind == T.INTEGER:
            result.integer_range = [IntegerRange(from_value=int(key.low), to_value=int(key.high), step=1)]
        else:
            result.floating_point_range = [FloatingPointRange(from_value=float(key.low), to_value=float(key.high),
                                                              step=0.0)]
    return result


def declare(node: Node) -> None:
    """Declare every config key (a required one by type only, so the parameter file must set it)."""
    for key in KEYS:
        default = _ROS_TYPES.get(key.kind, T.STRING) if key.default is None else key.default
        node.declare_parameter(key.name, default, descriptor(key))


def values(node: Node) -> dict[str, Any]:
    """Dotted key -> value of every declared config key that has a value."""
    found = {}
    for name in PARAMETERS:
        try:
            value = node.get_parameter(name).value
        except ParameterUninitializedException:
            continue
        if value is not None:
            found[name] = _plain(value)
    return found


def parameter_files(arguments: Sequence[str]) -> list[Path]:
    """The ``--params-file`` files of a node's command line (``ros2 run … --ros-args --params-file FILE``), in order:
    the files rcl read its parameters from."""
    files, inside = [], False
    for position, argument in enumerate(arguments):
        if argument == "--ros-args":
            inside = True
        elif argument == "--":
            inside = False
        elif inside and argument == "--params-file" and position + 1 < len(arguments):
            files.append(Path(arguments[position + 1]))
    return files


def folders_of(node: Node, files: Sequence[Path] = ()) -> dict[str, Path | None]:
    """Where the node's relative paths resolve, as ``kvark`` resolves them (``core.config.path_folders``): against
    the folder of the parameter file (of ``files``) that set them, else against ``config_folder()`` (parameters
    without a file: a launch file's dictionary, which resolved its own, or the defaults). Read once, at start."""
    return path_folders(files, node.get_fully_qualified_name(), config_folder())


def read_config(node: Node, folders: Mapping[str, Path | None]) -> EstimatorConfig:
    """The validated config of the node's parameters, relative paths resolved against ``folders`` (``folders_of``)."""
    return with_folders(config_from_parameters(values(node), f"parameters of {node.get_fully_qualified_name()}"),
                        folders)


def check_update(node: Node, parameters: list[Parameter]) -> SetParametersResult:
    """On-set callback: accept run-time keys with values the config accepts (a payload: a physical one);
    refuse the rest with a reason."""
    changes = {}
    for parameter in parameters:
        key = PARAMETERS.get(parameter.name)
        if key is None:
            continue                          # not ours (use_sim_time, QoS overrides, ...)
        if not key.runtime:
            return SetParametersResult(successful=False, reason=(
                f"{parameter.name} cannot change while the node runs (it shapes the model, the filter or the "
                f"node's interfaces); change it in the parameter file and restart the node. Run-time keys: "
                f"{', '.join(RUNTIME_KEYS)}"))
        changes[parameter.name] = _plain(parameter.value)
    if changes:
        current = values(node)
        current.update(changes)
        try:
            config = config_from_parameters(current, "parameter update")
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        problem = payload_problem(config.payload) if any(n.startswith(PAYLOAD_PREFIX) for n in changes) else None
        if problem is not None:
            return SetParametersResult(successful=False, reason=(
                f"parameter update: robot_model.payload is not a physical rigid body: {problem}"))
    return SetParametersResult(successful=True)
