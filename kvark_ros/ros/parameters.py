"""The node's ROS parameters: declared from the config key table, read back into one frozen config.

Every key of ``kvark_ros.core.config_schema`` becomes a parameter with a descriptor made from its row
(meaning, allowed values, range, read-only unless the key may change at run time); the node-only
``torque_source`` says where τ_m comes from. Validation is the config's own
(``config_from_parameters``): one set of rules for the YAML file, the CLI and the node.
"""
from __future__ import annotations

import array
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter

from kvark_ros.core.config import ConfigError, EstimatorConfig, config_from_parameters, with_resolved_paths
from kvark_ros.core.config_schema import KEYS, KEYS_BY_NAME, Key

T = Parameter.Type
TORQUE_SOURCE = "torque_source"
TORQUE_SOURCES = ("effort_commands", "effort_commands_joint_state", "joint_states_effort")
PARAMETERS: dict[str, Key] = KEYS_BY_NAME
RUNTIME_KEYS = tuple(key.name for key in KEYS if key.runtime)
_ROS_TYPES = {"number": T.DOUBLE, "integer": T.INTEGER, "names": T.STRING_ARRAY, "vector3": T.DOUBLE_ARRAY,
              "vector6": T.DOUBLE_ARRAY}


def _plain(value: Any) -> Any:
    """A parameter value as the config expects it: arrays as lists."""
    return list(value) if isinstance(value, (array.array, tuple)) else value


def package_roots() -> list[Path]:
    """Where relative config paths are looked up: the installed share directory, then the source tree."""
    roots = []
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
        try:
            roots.append(Path(get_package_share_directory("kvark_ros")))
        except PackageNotFoundError:
            pass
    except ImportError:
        pass
    source = Path(__file__).resolve().parents[2]
    if (source / "config").is_dir():
        roots.append(source)
    return roots


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
    node.declare_parameter(TORQUE_SOURCE, TORQUE_SOURCES[0], ParameterDescriptor(
        description="where τ_m comes from: effort_commands (Float64MultiArray), effort_commands_joint_state "
                    "(JointState effort on effort_commands), joint_states_effort (effort of joint_states)",
        additional_constraints=f"one of {', '.join(TORQUE_SOURCES)}", read_only=True))


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


def read_config(node: Node) -> EstimatorConfig:
    """The validated config of the node's parameters, relative paths resolved (module docstring)."""
    config = config_from_parameters(values(node), f"parameters of {node.get_fully_qualified_name()}")
    for root in package_roots():
        config = with_resolved_paths(config, root)
    return config


def torque_source(node: Node) -> str:
    """The node-only ``torque_source`` parameter, checked."""
    source = node.get_parameter(TORQUE_SOURCE).value
    if source not in TORQUE_SOURCES:
        raise ConfigError(f"parameters of {node.get_fully_qualified_name()}: key '{TORQUE_SOURCE}' has invalid "
                          f"value {source!r}; allowed: one of {', '.join(TORQUE_SOURCES)}")
    return source


def check_update(node: Node, parameters: list[Parameter]) -> SetParametersResult:
    """On-set callback: accept run-time keys with values the config accepts; refuse the rest with a reason."""
    changes = {}
    for parameter in parameters:
        if parameter.name == TORQUE_SOURCE:
            return SetParametersResult(successful=False, reason=(
                f"{TORQUE_SOURCE} cannot change while the node runs; restart the node with the new value"))
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
            config_from_parameters(current, "parameter update")
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
    return SetParametersResult(successful=True)
