"""One frozen configuration shared by the ROS node, the trainer and the bag replay.

The YAML file is the node's parameter file (``kvark_estimator: ros__parameters: ...``), so the
same file configures live and offline runs. Nested groups map to dotted ROS parameter names
(``filter.ewma_rate``). Every key is validated here, in one place; a bad key or value raises
``ConfigError`` naming the key and what is allowed.
"""
from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Mapping


from kvark_ros.core.files import read_yaml
from kvark_ros.core.robot_model import EXAMPLE_ROBOT_DATA_PREFIX, Payload

NODE_NAME = "kvark_estimator"
OBSERVER_NAMES = ("kvark", "kf", "kmp_kf", "kmp_kf_ewma", "kmp_kf_nis", "gmr_gp", "gpadkf", "nnadkf",
                  "momentum", "kfmo", "sh_akfmo", "vbkfmo_q", "eso", "oracle")
WRENCH_FRAMES = ("base", "end_effector")
VB_VARIANTS = ("paper", "huang", "smoothed", "window")
MEASUREMENTS = ("momentum", "difference")


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message names the key and the fix."""


@dataclass(frozen=True)
class EstimatorConfig:
    """Validated estimator settings. Units SI; see ``config/panda.yaml`` for each key's meaning."""

    robot: str
    urdf: str
    joint_names: tuple[str, ...]
    ee_frame: str
    flange_frame: str
    payload: Payload | None
    model_dir: str
    model_augmentation: str
    observer: str
    wrench_frame: str
    wrench_damping: float
    initial_covariance: float
    vb_iterations: int
    vb_forgetting: float
    vb_variant: str
    vb_window: int
    vb_prior_dof: float
    onset_threshold: float
    onset_window: int
    measurement: str
    huang_tau: float
    ewma_rate: float
    nis_rate: float
    max_gap: float
    command_max_age: float
    queue_depth: int
    contact_confidence: float
    contact_debounce: float
    diagnostics_period: float

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _number(low: float, high: float, low_open: bool = False, high_open: bool = False) -> tuple[Callable, str]:
    """A check for a finite number in a range, and the range as text for error messages."""
    text = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"

    def check(value: Any) -> bool:
        if not _is_number(value):
            return False
        above = value > low if low_open else value >= low
        below = value < high if high_open else value <= high
        return above and below

    return check, f"a number in {text}"


def _integer(low: int, high: int) -> tuple[Callable, str]:
    return (lambda v: isinstance(v, int) and not isinstance(v, bool) and low <= v <= high,
            f"an integer in [{low}, {high}]")


def _choice(options: tuple[str, ...]) -> tuple[Callable, str]:
    return (lambda v: v in options), f"one of {', '.join(options)}"


_TEXT = ((lambda v: isinstance(v, str) and v.strip() != ""), "a non-empty string")
_NAMES = ((lambda v: isinstance(v, list) and len(v) > 0 and all(isinstance(x, str) and x for x in v)
           and len(set(v)) == len(v)), "a non-empty list of distinct joint names")
_VECTOR3 = ((lambda v: isinstance(v, list) and len(v) == 3 and all(_is_number(x) for x in v)),
            "a list of 3 numbers")
_VECTOR6 = ((lambda v: isinstance(v, list) and len(v) == 6 and all(_is_number(x) for x in v)),
            "a list of 6 numbers [ixx, iyy, izz, ixy, ixz, iyz]")

# dotted key -> (check, allowed text, default or None when required)
_SCHEMA: dict[str, tuple[Callable, str, Any]] = {
    "robot": (*_TEXT, None),
    "robot_model.urdf": (*_TEXT, None),
    "robot_model.joint_names": (*_NAMES, None),
    "robot_model.ee_frame": (*_TEXT, None),
    "robot_model.flange_frame": (*_TEXT, None),
    "robot_model.payload.mass": (*_number(0.0, 1000.0), 0.0),
    "robot_model.payload.com": (*_VECTOR3, [0.0, 0.0, 0.0]),
    "robot_model.payload.inertia": (*_VECTOR6, [0.0] * 6),
    "residual_model.model_dir": (*_TEXT, None),
    "model_augmentation": ((lambda v: isinstance(v, str)), "a path to augmentation.yaml, or '' for none", ""),
    "observer": (*_choice(OBSERVER_NAMES), "kvark"),
    "wrench.frame": (*_choice(WRENCH_FRAMES), "base"),
    "wrench.damping": (*_number(0.0, 10.0), 0.05),
    "filter.initial_covariance": (*_number(0.0, 1e6, low_open=True), 1.0),
    "filter.vb_iterations": (*_integer(1, 50), 1),
    "filter.vb_forgetting": (*_number(0.0, 1.0, low_open=True), 0.99),
    "filter.vb_variant": (*_choice(VB_VARIANTS), "window"),
    "filter.vb_window": (*_integer(5, 5000), 25),
    "filter.vb_prior_dof": (*_number(0.0, 1e6, low_open=True), 1.0),
    "filter.onset_threshold": (*_number(0.0, 1e6), 60.0),
    "filter.onset_window": (*_integer(2, 500), 10),
    "filter.measurement": (*_choice(MEASUREMENTS), "momentum"),
    "filter.huang_tau": (*_number(0.0, 1e6, low_open=True), 300.0),
    "filter.ewma_rate": (*_number(0.0, 1.0, low_open=True), 0.01),
    "filter.nis_rate": (*_number(0.0, 1.0, low_open=True), 0.01),
    "input.max_gap": (*_number(0.0, 10.0, low_open=True), 0.05),
    "input.command_max_age": (*_number(0.0, 1.0, low_open=True), 0.01),
    "input.queue_depth": (*_integer(1, 1000), 10),
    "contact.confidence": (*_number(0.5, 1.0, low_open=True, high_open=True), 0.99),
    "contact.debounce": (*_number(0.0, 1.0), 0.02),
    "diagnostics.period": (*_number(0.0, 60.0, low_open=True), 1.0),
}


def flatten_parameters(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested YAML groups to dotted ROS parameter names (payload vectors stay lists)."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten_parameters(value, f"{name}."))
        else:
            flat[name] = value
    return flat


def config_from_parameters(parameters: Mapping[str, Any], source: str = "configuration") -> EstimatorConfig:
    """Validate dotted parameters (as the ROS node holds them) into an ``EstimatorConfig``."""
    values: dict[str, Any] = {}
    unknown = sorted(set(parameters) - set(_SCHEMA))
    if unknown:
        raise ConfigError(f"{source}: unknown key '{unknown[0]}'; allowed keys: {', '.join(_SCHEMA)}")
    for key, (check, allowed, default) in _SCHEMA.items():
        if key not in parameters:
            if default is None:
                raise ConfigError(f"{source}: missing required key '{key}' ({allowed})")
            values[key] = default
            continue
        value = parameters[key]
        if isinstance(value, tuple):
            value = list(value)
        if isinstance(value, int) and not isinstance(value, bool) and "number" in allowed:
            value = float(value)
        if not check(value):
            raise ConfigError(f"{source}: key '{key}' has invalid value {value!r}; allowed: {allowed}")
        values[key] = value
    if values["filter.vb_variant"] == "huang" and values["filter.measurement"] == "momentum":
        raise ConfigError(f"{source}: key 'filter.vb_variant' huang is implemented for "
                          "filter.measurement: difference only; allowed with momentum: paper, smoothed, window")
    if values["filter.vb_variant"] in ("smoothed", "window") and values["filter.measurement"] == "difference":
        raise ConfigError(f"{source}: key 'filter.vb_variant' {values['filter.vb_variant']} is implemented for "
                          "filter.measurement: momentum only; allowed with difference: paper, huang")
    mass = values["robot_model.payload.mass"]
    payload = None if mass == 0.0 else Payload(
        mass, tuple(values["robot_model.payload.com"]), tuple(values["robot_model.payload.inertia"]))
    return EstimatorConfig(
        robot=values["robot"],
        urdf=values["robot_model.urdf"],
        joint_names=tuple(values["robot_model.joint_names"]),
        ee_frame=values["robot_model.ee_frame"],
        flange_frame=values["robot_model.flange_frame"],
        payload=payload,
        model_dir=values["residual_model.model_dir"],
        model_augmentation=values["model_augmentation"],
        observer=values["observer"],
        wrench_frame=values["wrench.frame"],
        wrench_damping=values["wrench.damping"],
        initial_covariance=values["filter.initial_covariance"],
        vb_iterations=values["filter.vb_iterations"],
        vb_forgetting=values["filter.vb_forgetting"],
        vb_variant=values["filter.vb_variant"],
        vb_window=values["filter.vb_window"],
        vb_prior_dof=values["filter.vb_prior_dof"],
        onset_threshold=values["filter.onset_threshold"],
        onset_window=values["filter.onset_window"],
        measurement=values["filter.measurement"],
        huang_tau=values["filter.huang_tau"],
        ewma_rate=values["filter.ewma_rate"],
        nis_rate=values["filter.nis_rate"],
        max_gap=values["input.max_gap"],
        command_max_age=values["input.command_max_age"],
        queue_depth=values["input.queue_depth"],
        contact_confidence=values["contact.confidence"],
        contact_debounce=values["contact.debounce"],
        diagnostics_period=values["diagnostics.period"],
    )


def parameter_defaults() -> dict[str, Any]:
    """Dotted key -> default (``None`` for required keys), for declaring ROS parameters."""
    return {key: default for key, (_, _, default) in _SCHEMA.items()}


def load_config(path: str | os.PathLike, **overrides: Any) -> EstimatorConfig:
    """Read ``kvark_estimator: ros__parameters:`` from a YAML file and validate it.

    ``overrides`` replace dotted keys (``observer="kf"``); relative ``model_dir`` and URDF
    paths are resolved against the YAML file's folder's parent (the package root), then the
    working directory.
    """
    source = str(path)
    document = read_yaml(path, ConfigError, "config file", "pass an existing config such as config/panda.yaml",
                         "pass a YAML file such as config/panda.yaml")
    try:
        parameters = document[NODE_NAME]["ros__parameters"]
    except (TypeError, KeyError) as exc:
        raise ConfigError(f"{source}: expected a top-level '{NODE_NAME}: ros__parameters:' mapping") from exc
    if not isinstance(parameters, Mapping):
        raise ConfigError(f"{source}: '{NODE_NAME}.ros__parameters' must be a mapping")
    flat = flatten_parameters(parameters)
    flat.update({key.replace("__", "."): value for key, value in overrides.items()})
    config = config_from_parameters(flat, source)
    root = Path(path).resolve().parent.parent
    return with_resolved_paths(config, root)


def with_resolved_paths(config: EstimatorConfig, root: Path) -> EstimatorConfig:
    """Relative file paths in the config are relative to the package root holding config/."""
    def resolve(text: str) -> str:
        if text.startswith(("<", EXAMPLE_ROBOT_DATA_PREFIX)) or os.path.isabs(text):
            return text
        candidate = root / text
        return str(candidate) if candidate.exists() else text

    return replace(config, urdf=resolve(config.urdf), model_dir=resolve(config.model_dir),
                   model_augmentation=resolve(config.model_augmentation) if config.model_augmentation else "")


def default_config_path(robot: str) -> Path:
    """``config/<robot>.yaml`` from the source tree, or from share/kvark_ros when installed."""
    candidates = [Path(__file__).resolve().parents[2] / "config" / f"{robot}.yaml",
                  Path(sys.prefix) / "share" / "kvark_ros" / "config" / f"{robot}.yaml"]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise ConfigError(f"no config for robot '{robot}' (looked in {', '.join(map(str, candidates))}); "
                      "pass --config FILE")
