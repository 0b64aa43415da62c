"""One frozen configuration shared by the ROS node, the trainer and the bag replay.

The YAML file is the node's parameter file (``kvark_estimator: ros__parameters: ...``, or ``/**/kvark_estimator:``
to match the node in any namespace), so the same file configures live and offline runs. Nested groups map to dotted
ROS parameter names (``filter.ewma_time``). The keys, their checks, defaults and meanings are the one table of
``kvark_ros.core.config_schema``; ``EstimatorConfig`` and its typed groups (``config.filter``, ``config.wrench``,
...) are generated from it into ``kvark_ros.core.settings`` and re-exported here, so a new key is a row there,
``make generated`` and the code that reads it.
Every key is validated here, in one place; a bad key or value raises ``ConfigError`` naming the key
and what is allowed.
"""
from __future__ import annotations

import fnmatch
import os
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping

from kvark_ros.core.config_schema import (KEYS, KEYS_BY_NAME, MEASUREMENTS, NODE_NAME, OBSERVER_NAMES, REMOVED_KEYS,
                                          RENAMED_KEYS, VB_VARIANTS, WRENCH_FRAMES, Key, vb_variant_problem)
from kvark_ros.core.files import read_yaml
from kvark_ros.core.hints import did_you_mean, nearest
from kvark_ros.core.estimation.payload import Payload, old_order_problem
from kvark_ros.core.settings import (SETTINGS_BY_GROUP, ContactSettings, DiagnosticsSettings, EstimatorConfig,
                                     FilterSettings, InputSettings, OutputSettings, TareSettings, WrenchSettings)

__all__ = ["NODE_NAME", "OBSERVER_NAMES", "WRENCH_FRAMES", "VB_VARIANTS", "MEASUREMENTS", "EXAMPLE_ROBOT_DATA_PREFIX",
           "ConfigError", "EstimatorConfig", "FilterSettings", "WrenchSettings", "InputSettings", "ContactSettings",
           "DiagnosticsSettings", "OutputSettings", "TareSettings", "flatten_parameters", "config_from_parameters",
           "parameter_defaults", "default_filter_settings", "load_config", "with_resolved_paths", "default_config_path",
           "parse_observers", "applies_to", "file_parameters", "path_folders", "with_folders", "resolved_path",
           "launch_parameters", "ANY_NAMESPACE"]

EXAMPLE_ROBOT_DATA_PREFIX = "example-robot-data:"
ROBOT_DESCRIPTION = "robot_description"       # robot_model.urdf: the node takes the URDF from this topic
SECTION = "ros__parameters"
ANY_NAMESPACE = f"/**/{NODE_NAME}"            # a file's key for the node in any namespace (rcl's wildcard)
PATH_KEYS = ("robot_model.urdf", "residual_model.model_dir", "model_augmentation")


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message names the key and the fix."""


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


def _value(key: Key, parameters: Mapping[str, Any], source: str) -> Any:
    """The checked value of one key (its default when absent)."""
    if key.name not in parameters:
        if key.default is None:
            raise ConfigError(f"{source}: missing required key '{key.name}' ({key.allowed})")
        value = key.default
    else:
        value = parameters[key.name]
        if isinstance(value, tuple):
            value = list(value)
        if isinstance(value, int) and not isinstance(value, bool) and key.kind == "number":
            value = float(value)
        if not key.check(value):
            hint = did_you_mean(value, key.choices) if key.kind == "choice" and isinstance(value, str) else ""
            raise ConfigError(f"{source}: key '{key.name}' has invalid value {value!r}; allowed: {key.allowed}{hint}")
    return tuple(value) if isinstance(value, list) else value


def _nearest_key(name: str) -> str:
    """The fix for an unknown key: the key of the same last part (``ee_frame`` is ``robot_model.ee_frame``), else
    the nearest by dotted name, else by last part, else where to find every key."""
    leaves = {key.name.rpartition(".")[2]: key.name for key in KEYS}
    leaf = name.rpartition(".")[2]
    found = leaves.get(leaf) or nearest(name, KEYS_BY_NAME)
    if found is None:
        leaf = nearest(leaf, leaves)
        found = None if leaf is None else leaves[leaf]
    return "`kvark config --keys` lists every key" if found is None else f"did you mean '{found}'?"


def config_from_parameters(parameters: Mapping[str, Any], source: str = "configuration") -> EstimatorConfig:
    """Validate dotted parameters (as the ROS node holds them) into an ``EstimatorConfig``."""
    unknown = sorted(set(parameters) - set(KEYS_BY_NAME))
    renamed = [name for name in unknown if name in RENAMED_KEYS]
    if renamed:
        new, how = RENAMED_KEYS[renamed[0]]
        raise ConfigError(f"{source}: key '{renamed[0]}' is now '{new}' (seconds, independent of the sample rate; "
                          f"{how})")
    removed = [name for name in unknown if name in REMOVED_KEYS]
    if removed:
        raise ConfigError(f"{source}: key '{removed[0]}' was removed: {REMOVED_KEYS[removed[0]]}")
    if unknown:
        raise ConfigError(f"{source}: unknown key '{unknown[0]}'; {_nearest_key(unknown[0])}")
    values = {key.name: _value(key, parameters, source) for key in KEYS}
    problem = vb_variant_problem(values["filter.vb_variant"], values["filter.measurement"])
    if problem is not None:
        raise ConfigError(f"{source}: key {problem}")
    top = {key.attr: values[key.name] for key in KEYS if key.group is None}
    groups = {group: settings(**{key.attr: values[key.name] for key in KEYS if key.group == group})
              for group, settings in SETTINGS_BY_GROUP.items()}
    n = len(values["robot_model.joint_names"])
    for name in ("input.effort_scale", "input.effort_offset"):
        if len(values[name]) not in (1, n):
            raise ConfigError(f"{source}: key '{name}' has {len(values[name])} values; give 1 (every joint) or {n} "
                              f"(one per robot_model.joint_names)")
    mass, inertia = values["robot_model.payload.mass"], values["robot_model.payload.inertia"]
    problem = old_order_problem(inertia) if mass > 0.0 else None
    if problem is not None:
        raise ConfigError(f"{source}: key 'robot_model.payload.inertia' {problem}")
    payload = None if mass == 0.0 else Payload.from_message_order(mass, values["robot_model.payload.com"], inertia)
    return EstimatorConfig(**top, payload=payload, **groups)


def applies_to(key: str, node: str | None = None) -> bool:
    """Whether a parameter file's top-level ``key`` applies to the node ``node`` (fully qualified, e.g.
    ``/lbr/kvark_estimator``) as rcl matches them: a key is a fully qualified name with or without the leading
    ``/``, ``*`` standing for one name and ``**`` for any number (``/**/kvark_estimator``, ``/**``). ``node`` None:
    a ``kvark_estimator`` in any namespace (the commands, which run no node)."""
    pattern = [token for token in str(key).strip("/").split("/") if token]
    if node is None:
        return bool(pattern) and (pattern[-1] == "**" or fnmatch.fnmatchcase(NODE_NAME, pattern[-1]))
    return _matches(pattern, [token for token in node.strip("/").split("/") if token])


def _matches(pattern: list[str], names: list[str]) -> bool:
    if not pattern:
        return not names
    if pattern[0] == "**":
        return any(_matches(pattern[1:], names[k:]) for k in range(len(names) + 1))
    return bool(names) and fnmatch.fnmatchcase(names[0], pattern[0]) and _matches(pattern[1:], names[1:])


def file_parameters(document: Any, source: str, node: str | None = None) -> dict[str, Any]:
    """The dotted parameters a parameter file gives ``node`` (``applies_to``): the ``ros__parameters`` of every
    top-level key that applies, later keys overriding earlier ones as rcl applies them. ConfigError when none
    applies or one is not a mapping."""
    flat: dict[str, Any] = {}
    found = False
    for key, section in (document.items() if isinstance(document, Mapping) else ()):
        if not applies_to(key, node):
            continue
        parameters = section.get(SECTION) if isinstance(section, Mapping) else None
        if not isinstance(parameters, Mapping):
            raise ConfigError(f"{source}: '{key}.{SECTION}' must be a mapping")
        flat.update(flatten_parameters(parameters))
        found = True
    if not found:
        raise ConfigError(f"{source}: expected a top-level '{NODE_NAME}: {SECTION}:' mapping (or '{ANY_NAMESPACE}:' "
                          "for the node in any namespace)")
    return flat


def parse_observers(text: str, with_oracle: bool = False) -> list[str]:
    """``--observers`` of the CLI: ``all`` or comma-separated names; ``all`` takes the oracle only
    ``with_oracle`` (it needs a plant file). Unknown names raise ``ConfigError``."""
    names = [n for n in OBSERVER_NAMES if n != "oracle" or with_oracle] if text == "all" else text.split(",")
    unknown = [name for name in names if name not in OBSERVER_NAMES]
    if unknown:
        raise ConfigError(f"unknown observer {unknown[0]!r}; known: {', '.join(OBSERVER_NAMES)}")
    return names


def default_filter_settings() -> FilterSettings:
    """The ``filter.*`` keys at their defaults (what training calibrates with when given no config)."""
    return FilterSettings()


def parameter_defaults() -> dict[str, Any]:
    """Dotted key -> default (``None`` for required keys), for declaring ROS parameters."""
    return {key.name: key.default for key in KEYS}


def load_config(path: str | os.PathLike, **overrides: Any) -> EstimatorConfig:
    """Read ``kvark_estimator: ros__parameters:`` (every key that applies: ``file_parameters``) from a YAML file and
    validate it.

    ``overrides`` replace dotted keys (``observer="kf"``); relative ``model_dir``, URDF and
    ``model_augmentation`` paths are resolved against the YAML file's own folder (one rule, wherever
    the command runs: ``config/panda.yaml`` names ``../models/panda``).
    """
    source = str(path)
    flat = file_parameters(_read_document(path), source)
    flat.update({key.replace("__", "."): value for key, value in overrides.items()})
    config = config_from_parameters(flat, source)
    return with_resolved_paths(config, Path(path).resolve().parent)


def _read_document(path: str | os.PathLike) -> Any:
    """The YAML document of a config file; ConfigError naming the fix when it is missing or not YAML."""
    return read_yaml(path, ConfigError, "config file", "pass an existing config such as config/panda.yaml",
                     "pass a YAML file such as config/panda.yaml")


def resolved_path(text: str, folder: Path | None) -> str:
    """A path value made absolute against ``folder`` (None: kept); a URDF string, example-robot-data, the topic and
    '' are no file."""
    if (folder is None or not text or text.startswith(("<", EXAMPLE_ROBOT_DATA_PREFIX)) or text == ROBOT_DESCRIPTION
            or os.path.isabs(text)):
        return text
    return os.path.normpath(folder / text)


def with_folders(config: EstimatorConfig, folders: Mapping[str, Path | None]) -> EstimatorConfig:
    """The config with each of ``PATH_KEYS`` resolved against its folder in ``folders``."""
    return replace(config, urdf=resolved_path(config.urdf, folders["robot_model.urdf"]),
                   model_dir=resolved_path(config.model_dir, folders["residual_model.model_dir"]),
                   model_augmentation=resolved_path(config.model_augmentation, folders["model_augmentation"]))


def with_resolved_paths(config: EstimatorConfig, folder: Path) -> EstimatorConfig:
    """Relative file paths of the config made absolute against ``folder``, the config file's folder."""
    return with_folders(config, dict.fromkeys(PATH_KEYS, folder))


def launch_parameters(path: str | os.PathLike) -> dict[str, Any]:
    """The dotted parameters a config file gives the node (``file_parameters``: every key of it that applies, in any
    namespace) with relative paths made absolute against the file's folder, as ``kvark`` resolves them: the
    parameter dictionary the launch file passes, which applies under any namespace."""
    parameters = file_parameters(_read_document(path), str(path))
    folder = Path(path).resolve().parent
    for key in PATH_KEYS:
        if isinstance(parameters.get(key), str):
            parameters[key] = resolved_path(parameters[key], folder)
    return parameters


def path_folders(files: Sequence[str | os.PathLike], node: str, fallback: Path | None) -> dict[str, Path | None]:
    """For each of ``PATH_KEYS``, the folder a node's relative path resolves against (``with_folders``), as ``kvark``
    resolves it: that of the last of the parameter ``files`` (``--params-file``, in the order given) that sets it for
    ``node``, the file rcl took the value from; ``fallback`` where no file sets it (a launch file's dictionary, a
    default). A node reads it once at its start: its files do not change under it, and parsing them at every
    run-time parameter change held up the samples."""
    folders: dict[str, Path | None] = dict.fromkeys(PATH_KEYS, fallback)
    for file in files:
        try:
            given = file_parameters(_read_document(file), str(file), node)
        except ConfigError:
            continue                  # rcl read it, or refused the node's start: nothing of ours from it
        folders.update({key: Path(file).resolve().parent for key in PATH_KEYS if key in given})
    return folders


def default_config_path(robot: str) -> Path:
    """``config/<robot>.yaml`` from the source tree, or from share/kvark_ros when installed."""
    candidates = [Path(__file__).resolve().parents[2] / "config" / f"{robot}.yaml",
                  Path(sys.prefix) / "share" / "kvark_ros" / "config" / f"{robot}.yaml"]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise ConfigError(f"no config for robot '{robot}' (looked in {', '.join(map(str, candidates))}); "
                      "pass --config FILE")
