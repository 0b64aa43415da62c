"""The one table of configuration keys: name, type, allowed values, default, run-time, meaning.

Everything else about a key comes from this table: validation (``kvark_ros.core.config``), the typed
settings groups the code reads (``config.filter.ewma_time``, generated into ``kvark_ros/core/settings.py``),
the ROS node's parameter descriptors, the key comments of ``config/*.yaml`` and of ``kvark init``'s files, and
the README's key table (``kvark config --keys``). Adding a key is one ``Key`` row here, ``make generated``
(``python -m kvark_ros.core.config_schema --write-settings --write-configs``; the tests fail until it ran) and
the code that uses it.

Dotted names are the ROS parameter names and the YAML nesting (``filter.ewma_time`` is
``filter: {ewma_time: ...}``). ``group``/``attr`` say where the value lives in ``EstimatorConfig``:
``config.<attr>`` for top-level keys, ``config.<group>.<attr>`` for grouped ones.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import yaml

from kvark_ros.core.observer_catalog import OBSERVER_NAMES

NODE_NAME = "kvark_estimator"              # the node's name: the top-level key of every config file
WRENCH_FRAMES = ("base", "end_effector")
VB_VARIANTS = ("paper", "huang", "smoothed", "window")
MEASUREMENTS = ("momentum", "difference")
TORQUE_SOURCES = ("effort_commands", "effort_commands_joint_state", "joint_states_effort")
OUTPUT_QOS = ("reliable", "sensor_data")
# The VB readings each form of the filter implements (docs/method.md §4.5-4.6).
VB_VARIANTS_BY_MEASUREMENT = {"momentum": ("paper", "smoothed", "window"), "difference": ("paper", "huang")}


def vb_variant_problem(variant: str, measurement: str) -> str | None:
    """Why ``filter.vb_variant`` cannot run in ``filter.measurement``'s form, or None if it can."""
    allowed = VB_VARIANTS_BY_MEASUREMENT[measurement]
    if variant in allowed:
        return None
    other = next(form for form, variants in VB_VARIANTS_BY_MEASUREMENT.items() if variant in variants)
    return (f"'filter.vb_variant' {variant} is implemented for filter.measurement: {other} only; "
            f"allowed with {measurement}: {', '.join(allowed)}")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class Key:
    """One configuration key (module docstring).

    kind: ``text``, ``path`` (text, may be empty), ``names`` (list of distinct strings), ``number``,
    ``integer``, ``choice``, ``vector3`` or ``vector6``. ``low``/``high`` bound numbers and integers,
    ``low_open``/``high_open`` make an end exclusive; ``choices`` lists a choice's options.
    ``default`` None marks a required key.
    """

    name: str
    kind: str
    default: Any
    meaning: str
    runtime: bool = False
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[str, ...] = ()
    group: str | None = None
    attr: str = ""

    @property
    def allowed(self) -> str:
        """What the key accepts, as error messages and descriptors say it."""
        if self.kind in ("number", "integer"):
            kind = "a number" if self.kind == "number" else "an integer"
            low, high = (float(self.low), float(self.high)) if self.kind == "number" else (self.low, self.high)
            return f"{kind} in {'(' if self.low_open else '['}{low}, {high}{')' if self.high_open else ']'}"
        return {"text": "a non-empty string", "path": "a path, or '' for none",
                "names": "a non-empty list of distinct joint names", "choice": f"one of {', '.join(self.choices)}",
                "vector3": "a list of 3 numbers",
                "vector6": "a list of 6 numbers [ixx, iyy, izz, ixy, ixz, iyz]"}[self.kind]

    @property
    def documented(self) -> str:
        """What the key accepts, as the generated README table, config comments and settings say it."""
        return _OPEN_CHOICES.get(self.name, self.allowed)

    def check(self, value: Any) -> bool:
        """Whether ``value`` (as YAML or a ROS parameter gives it) is allowed."""
        if self.kind in ("number", "integer"):
            if not _is_number(value) or (self.kind == "integer" and not isinstance(value, int)):
                return False
            above = value > self.low if self.low_open else value >= self.low
            below = value < self.high if self.high_open else value <= self.high
            return above and below
        checks: dict[str, Callable[[Any], bool]] = {
            "text": lambda v: isinstance(v, str) and v.strip() != "",
            "path": lambda v: isinstance(v, str),
            "names": lambda v: (isinstance(v, list) and len(v) > 0 and all(isinstance(x, str) and x for x in v)
                                and len(set(v)) == len(v)),
            "choice": lambda v: v in self.choices,
            "vector3": lambda v: isinstance(v, list) and len(v) == 3 and all(_is_number(x) for x in v),
            "vector6": lambda v: isinstance(v, list) and len(v) == 6 and all(_is_number(x) for x in v),
        }
        return checks[self.kind](value)


def _key(name: str, kind: str, default: Any, meaning: str, **options: Any) -> Key:
    """A Key whose group and attribute follow from its dotted name (``filter.ewma_time``)."""
    if "attr" not in options:
        group, _, attr = name.rpartition(".")
        options.update(group=group or None, attr=attr)
    return Key(name, kind, default, meaning, **options)


def _unit(low: float, high: float, **options: Any) -> dict[str, Any]:
    return {"low": low, "high": high, **options}


KEYS: tuple[Key, ...] = (
    _key("robot", "text", None, "robot name, written into models and reports"),
    _key("robot_model.urdf", "text", None,
         "nominal model: URDF path, example-robot-data:panda / :ur5, or robot_description (the node takes the topic)", attr="urdf"),
    _key("robot_model.joint_names", "names", None,
         "estimated joints, in output order; others are locked; messages are matched by these names", attr="joint_names"),
    _key("robot_model.ee_frame", "text", None, "wrench reference frame (origin and, for wrench.frame end_effector, axes)", attr="ee_frame"),
    _key("robot_model.flange_frame", "text", None, "frame a known payload attaches to", attr="flange_frame"),
    _key("robot_model.payload.mass", "number", 0.0, "known tool/payload at the flange added to the nominal model, kg (0: none)",
         runtime=True, **_unit(0.0, 1000.0), group="payload", attr="mass"),
    _key("robot_model.payload.com", "vector3", [0.0, 0.0, 0.0], "payload centre of mass in the flange frame, m",
         runtime=True, group="payload", attr="com"),
    _key("robot_model.payload.inertia", "vector6", [0.0] * 6,
         "payload inertia about its CoM, kg m^2 (ixx iyy izz ixy ixz iyz)", runtime=True,
         group="payload", attr="inertia"),
    _key("residual_model.model_dir", "text", None,
         "trained model directory written by kvark train (~/reload_model reloads it)", attr="model_dir"),
    _key("model_augmentation", "path", "",
         "augmentation.yaml of kvark diagnose for kvark train; at estimation it must be the model directory's copy ('' = that copy)"),
    _key("observer", "choice", "kvark", "observer name (README, Observers)", choices=OBSERVER_NAMES),
    _key("wrench.frame", "choice", "base", "axes of the published wrench: base or end_effector (ee_frame)", runtime=True, choices=WRENCH_FRAMES),
    _key("wrench.damping", "number", 0.05, "damping δ of the pseudo-inverse (paper v2 eq. 39)", runtime=True,
         **_unit(0.0, 10.0)),
    _key("wrench.prior_force", "number", 50.0, "N; scale of an unknown force: the wrench covariance carries its "
         "damping bias along directions the joints cannot sense (docs/method.md §1.4.1)", runtime=True,
         **_unit(0.0, 1e4)),
    _key("wrench.prior_moment", "number", 5.0, "N·m; the same for an unknown moment", runtime=True,
         **_unit(0.0, 1e4)),
    _key("filter.initial_covariance", "number", 1.0, "P₀ (τ block) = value · I, N²·m²", **_unit(0.0, 1e6, low_open=True)),
    _key("filter.vb_iterations", "integer", 1, "VB iterations M per sample", **_unit(1, 50)),
    _key("filter.vb_memory", "number", 0.2,
         "s; memory T of the inverse-Wishart statistics: forgetting ρ = 1 − t_s/T per sample of period t_s",
         **_unit(0.0, 1e6, low_open=True)),
    _key("filter.vb_variant", "choice", "window", "reading of the VB step (docs/method.md §4.5-4.6)", choices=VB_VARIANTS),
    _key("filter.vb_window_time", "number", 0.05,
         "s; window variant: length of a window of the τ_ext change (L = time / t_s samples, at least 5)",
         **_unit(0.001, 60.0)),
    _key("filter.vb_prior_dof", "number", 1.0, "window variant: prior strength ν₀ (in windows) of the IW prior around the trained Σ_d",
         **_unit(0.0, 1e6, low_open=True)),
    _key("filter.prior_bandwidth", "number", 30.0,
         "rad/s; momentum form, VB variants (kvark, gmr_gp, oracle): natural frequency of the τ_ext random walk "
         "prior in free motion; the VB and the onset detector raise it at contact (docs/method.md §4.12)",
         **_unit(0.0, 1e4, low_open=True)),
    _key("filter.onset_threshold", "number", 60.0,
         "contact-onset GLR threshold (χ²(1) statistic; 0 = off; momentum form)", **_unit(0.0, 1e6)),
    _key("filter.onset_window_time", "number", 0.02,
         "s back the contact onset may lie (time / t_s hypotheses, at least 2)", **_unit(0.001, 1.0)),
    _key("filter.measurement", "choice", "momentum", "form of the filter: p measured (momentum) or the paper's eq. 28 (difference)", choices=MEASUREMENTS),
    _key("filter.stiction_velocity", "number", 0.05,
         "rad/s; below it a joint counts as sticking: its interval widens to the trained static friction band "
         "(docs/method.md §4.11; 0 = off)", runtime=True, **_unit(0.0, 10.0)),
    _key("filter.interval_calibration", "choice", "trained",
         "kvark's reported covariance: trained (scaled by the model's factors from contact-free training data, "
         "docs/method.md §4.13) or off (the filter's own P)", runtime=True, choices=("trained", "off")),
    _key("filter.huang_tau", "number", 300.0, "prior strength τ of the huang variant",
         **_unit(0.0, 1e6, low_open=True)),
    _key("filter.ewma_time", "number", 0.2,
         "s; time constant T of the EWMA of the empirical noise (eq. 31): rate t_s/T per sample", runtime=True,
         **_unit(0.0, 1e6, low_open=True)),
    _key("filter.nis_time", "number", 0.2, "s; time constant of the running-mean NIS (A4): rate t_s/T per sample",
         runtime=True, **_unit(0.0, 1e6, low_open=True)),
    _key("input.max_gap", "number", 0.05, "s; a longer gap between joint states resets the filter", runtime=True,
         **_unit(0.0, 10.0, low_open=True)),
    _key("input.command_max_age", "number", 0.01, "s; oldest command a joint state may be paired with", runtime=True,
         **_unit(0.0, 1.0, low_open=True)),
    _key("input.torque_source", "choice", "effort_commands",
         "where τ_m comes from: effort_commands (Float64MultiArray; offline also JointState), "
         "effort_commands_joint_state (JointState effort on effort_commands), joint_states_effort "
         "(effort of joint_states, e.g. measured link-side torque)", choices=TORQUE_SOURCES),
    _key("input.joint_states_topic", "text", "joint_states",
         "sensor_msgs/JointState topic (q, q̇ and, for joint_states_effort, τ_m); bags match it with or without "
         "the leading /"),
    _key("input.effort_commands_topic", "text", "effort_commands", "commanded joint torque topic"),
    _key("input.wrench_topic", "text", "/ft_sensor/wrench",
         "offline ground truth: WrenchStamped of a wrist F/T sensor in the bag (replay --ground-truth ft)"),
    _key("input.external_torque_topic", "text", "/ground_truth/external_joint_torque",
         "offline ground truth: JointState effort = true τ_ext in the bag (replay --ground-truth topic)"),
    _key("input.queue_depth", "integer", 100, "subscription queue depth of the node (sensor-data QoS)", **_unit(1, 1000)),
    _key("contact.confidence", "number", 0.99, "confidence of the variance-aware χ² contact test", runtime=True,
         **_unit(0.5, 1.0, low_open=True, high_open=True)),
    _key("contact.collision_torque", "number", 8.5,
         "N·m; the collision flag is raised at once when a joint's |τ_ext| exceeds this by more than its "
         "interval (no debounce)", runtime=True, **_unit(0.0, 1000.0, low_open=True)),
    _key("contact.debounce", "number", 0.02, "s the contact test must hold before the flag changes",
         runtime=True, **_unit(0.0, 1.0)),
    _key("output.qos", "choice", "reliable",
         "QoS of the node's estimate topics: reliable, or sensor_data (best effort)", choices=OUTPUT_QOS),
    _key("tare.duration", "number", 1.0, "s of rest ~/tare averages τ_ext over", runtime=True,
         **_unit(0.0, 60.0, low_open=True)),
    _key("tare.max_speed", "number", 0.02, "rad/s; ~/tare refuses (and stops) while any joint moves faster",
         runtime=True, **_unit(0.0, 10.0, low_open=True)),
    _key("diagnostics.max_loss", "number", 0.01,
         "share of joint states lost (gaps in their stamps) above which /diagnostics warns", runtime=True,
         **_unit(0.0, 1.0)),
    _key("diagnostics.period", "number", 1.0, "s between /diagnostics messages", runtime=True,
         **_unit(0.0, 60.0, low_open=True)),
)
KEYS_BY_NAME: dict[str, Key] = {key.name: key for key in KEYS}
# Keys that counted samples until the rate-independent schema: the old name -> (new name, how to convert).
RENAMED_KEYS: dict[str, tuple[str, str]] = {
    "filter.vb_forgetting": ("filter.vb_memory", "T = t_s / (1 − ρ); 0.99 at 500 Hz is 0.2"),
    "filter.vb_window": ("filter.vb_window_time", "samples × t_s; 25 at 500 Hz is 0.05"),
    "filter.onset_window": ("filter.onset_window_time", "samples × t_s; 10 at 500 Hz is 0.02"),
    "filter.ewma_rate": ("filter.ewma_time", "T = t_s / rate; 0.01 at 500 Hz is 0.2"),
    "filter.nis_rate": ("filter.nis_time", "T = t_s / rate; 0.01 at 500 Hz is 0.2"),
    "torque_source": ("input.torque_source", "same values"),
}
# Keys that no longer exist: the old name -> why, for the one-line error of a config that still sets one.
REMOVED_KEYS: dict[str, str] = {
    "filter.kernel": "the momentum-form K-VARK step is always compiled (core/estimation/step_kernel.py); "
                     "delete the key",
}
GROUPS: tuple[str, ...] = tuple(dict.fromkeys(key.group for key in KEYS if key.group))


def keys_table() -> str:
    """The README's table of configuration keys (Markdown), made from ``KEYS``."""
    rows = ["| key | allowed | default | run time | meaning |", "|---|---|---|---|---|"]
    for key in KEYS:
        default = "required" if key.default is None else f"`{key.default!r}`".replace("'", "")
        rows.append(f"| `{key.name}` | {key.documented} | {default} | {'yes' if key.runtime else 'no'} | "
                    f"{key.meaning} |")
    return "\n".join(rows)


# Generated sources: the typed settings module and the key comments of the config files (module docstring).
SETTINGS_PATH = Path(__file__).with_name("settings.py")
CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
REGENERATE = "make generated (python -m kvark_ros.core.config_schema --write-settings --write-configs)"
COMMENT_WIDTH = 110                        # generated comment lines of a config file
_SOURCE_WIDTH = 120
# Choices that are another table's names: their type stays ``str`` and the generated text (README table, config
# comments, settings) names that table instead of listing it, so the table grows without regenerating; errors and
# ROS descriptors still list every name (``Key.allowed``).
_OPEN_CHOICES = {"observer": "an observer of core/observer_catalog.py (kvark replay --help lists them)"}


def settings_class(group: str) -> str:
    """The settings dataclass of a group of keys: ``FilterSettings`` for ``filter.*``."""
    return "".join(part.title() for part in group.split("_")) + "Settings"


def describe(key: Key, default: bool = True) -> str:
    """A key's comment: its meaning, what it accepts, its default (``default``) and whether it changes at run time."""
    text = f"{key.meaning}. Allowed: {key.documented}."
    if default:
        text += " Required." if key.default is None else f" Default: {flow_value(key.default)}."
    return text + (" Can be changed while the node runs." if key.runtime else "")


def _annotation(key: Key) -> str:
    """The type of a key's value in its settings class, as source (lists become tuples)."""
    if key.kind == "choice" and key.name not in _OPEN_CHOICES:
        return f"Literal[{', '.join(json.dumps(choice) for choice in key.choices)}]"
    return {"number": "float", "integer": "int", "names": "tuple[str, ...]", "vector3": "tuple[float, float, float]",
            "vector6": "tuple[float, float, float, float, float, float]"}.get(key.kind, "str")


def _python(value: Any) -> str:
    """A default as Python source (lists become tuples, as the config holds them)."""
    if isinstance(value, list):
        return repr(tuple(value))
    return json.dumps(value, ensure_ascii=False) if isinstance(value, str) else repr(value)


def _field(name: str, annotation: str, default: str | None, doc: str) -> list[str]:
    """One dataclass field with its docstring, wrapped to the source width."""
    line = f"    {name}: {annotation}" + ("" if default is None else f" = {default}")
    if len(line) > _SOURCE_WIDTH and "[" in annotation:
        head, _, rest = line.partition("[")
        items = textwrap.wrap(rest, _SOURCE_WIDTH - len(head) - 1, break_on_hyphens=False, break_long_words=False)
        line = f"\n{' ' * (len(head) + 1)}".join([f"{head}[{items[0]}", *items[1:]])
    if '"""' in doc or "\\" in doc or doc.endswith('"'):
        raise ValueError(f"{name}: a meaning with a backslash or ending in a quote cannot be a docstring: {doc}")
    text = textwrap.wrap(f'"""{doc}"""', _SOURCE_WIDTH - 4, break_on_hyphens=False, break_long_words=False)
    return [line, *(f"    {part}" for part in text)]


def _fields(keys: list[Key]) -> list[str]:
    """The fields of a settings class, one a key, in the table's order."""
    lines: list[str] = []
    for position, key in enumerate(keys):
        if key.default is None and any(k.default is not None for k in keys[:position]):
            raise ValueError(f"required key {key.name} follows a key with a default in its group: move its row up")
        default = None if key.default is None else _python(key.default)
        lines += _field(key.attr, _annotation(key), default, describe(key, default=False))
    return lines


def settings_source() -> str:
    """The source of ``kvark_ros/core/settings.py``: a frozen dataclass per group of KEYS and ``EstimatorConfig``."""
    groups = [group for group in GROUPS if group != "payload"]
    lines = ['"""Typed settings of the configuration: one frozen dataclass per group of keys, and ``EstimatorConfig``.',
             "",
             "Generated from config_schema.KEYS by `python -m kvark_ros.core.config_schema --write-settings` (or",
             "`make generated`); do not edit: change the key table and regenerate (the tests check this file).",
             '"""', "from __future__ import annotations", "", "from dataclasses import dataclass, field",
             "from typing import Literal", "", "from kvark_ros.core.estimation.payload import Payload", ""]
    names = ", ".join(json.dumps(name) for name in [*map(settings_class, groups), "EstimatorConfig",
                                                    "SETTINGS_BY_GROUP"])
    lines += textwrap.wrap(f"__all__ = [{names}]", _SOURCE_WIDTH, subsequent_indent=" " * 11)
    for group in groups:
        lines += ["", "", "@dataclass(frozen=True)", f"class {settings_class(group)}:",
                  f'    """The ``{group}`` keys of the config (config_schema.KEYS)."""', ""]
        lines += _fields([key for key in KEYS if key.group == group])
    lines += ["", "", "@dataclass(frozen=True)", "class EstimatorConfig:",
              '    """Validated estimator settings (config_schema.KEYS). Units SI; see config/panda.yaml."""', ""]
    lines += _fields([key for key in KEYS if key.group is None])
    lines += _field("payload", "Payload | None", "None", "the robot_model.payload.* keys: the known payload at the "
                    "flange, or None when its mass is 0")
    for group in groups:
        lines += _field(group, settings_class(group), f"field(default_factory={settings_class(group)})",
                        f"the {group}.* keys")
    lines += ["", "    @property", "    def n_joints(self) -> int:",
              '        """Number of estimated joints (``robot_model.joint_names``)."""',
              "        return len(self.joint_names)", "", "",
              "# Group name -> its settings class (robot_model.payload.* becomes ``EstimatorConfig.payload`` instead).",
              "SETTINGS_BY_GROUP: dict[str, type] = {"]
    lines += [f'    "{group}": {settings_class(group)},' for group in groups] + ["}"]
    return "\n".join(lines) + "\n"


def flow_value(value: Any, column: int = 0) -> str:
    """A value in YAML flow style, strings quoted only when needed; a list longer than the comment width
    continues on lines indented to its opening bracket (``column``: the bracket's column)."""
    text = yaml.safe_dump([value], default_flow_style=True, allow_unicode=True, width=10**6).strip()[1:-1]
    if not isinstance(value, list) or column + len(text) <= COMMENT_WIDTH:
        return text
    lines = textwrap.wrap(text[1:-1], COMMENT_WIDTH - column - 2, break_on_hyphens=False, break_long_words=False)
    return "[" + f"\n{' ' * (column + 1)}".join(lines) + "]"


def comment_lines(text: str, name: str) -> list[str]:
    """``text`` as wrapped comment lines for the key or group ``name`` (without its indentation)."""
    width = COMMENT_WIDTH - 2 * (name.count(".") + 2) - 2
    return [f"# {line}" for line in textwrap.wrap(text, width, break_on_hyphens=False, break_long_words=False)]


@dataclass
class ConfigDocument:
    """What a config file holds besides the key table's text (the table gives every key's first comment lines).

    ``header``: comment lines above ``kvark_estimator:``; ``values``: dotted key -> value (absent: its default);
    ``notes``: dotted key -> this file's comment lines below the table's, after a lone ``#``; ``prose``: dotted key
    or group -> comment lines above it, set apart from a key's comment by a blank line ('' = after the last key).
    Lines are stripped of their indentation.
    """

    header: list[str] = field(default_factory=list)
    values: dict[str, Any] = field(default_factory=dict)
    notes: dict[str, list[str]] = field(default_factory=dict)
    prose: dict[str, list[str]] = field(default_factory=dict)


def _key_tree() -> dict[str, Any]:
    """KEYS nested as the YAML nests them (group -> ... -> Key), in the table's order."""
    tree: dict[str, Any] = {}
    for key in KEYS:
        *groups, leaf = key.name.split(".")
        node = tree
        for group in groups:
            node = node.setdefault(group, {})
        node[leaf] = key
    return tree


def config_text(document: ConfigDocument) -> str:
    """The config file: the header, then every key of KEYS in the table's order, each with the table's comment
    (``describe``) and the document's notes, prose and value. ``kvark init`` and ``--write-configs`` write this."""
    unknown = sorted(set(document.values) - set(KEYS_BY_NAME))
    if unknown:
        raise ValueError(f"unknown key '{unknown[0]}'")
    lines = [*document.header, f"{NODE_NAME}:", "  ros__parameters:"]

    def emit(node: dict[str, Any], path: str, depth: int) -> None:
        indent = "  " * depth
        for position, (name, item) in enumerate(node.items()):
            dotted = f"{path}{name}"
            prose = [f"{indent}{line}" if line else "" for line in document.prose.get(dotted, [])]
            lines.extend([""] * (depth == 2 and position > 0) + prose)
            if isinstance(item, dict):
                lines.append(f"{indent}{name}:")
                emit(item, f"{dotted}.", depth + 1)
                continue
            value = document.values.get(dotted, item.default)
            if value is None:
                raise ValueError(f"required key '{dotted}' has no value")
            lines.extend([""] * bool(prose) + [f"{indent}{line}" for line in comment_lines(describe(item), dotted)])
            notes = document.notes.get(dotted, [])
            lines.extend([f"{indent}#"] * bool(notes) + [f"{indent}{line}" for line in notes])
            lines.append(f"{indent}{name}: {flow_value(value, len(indent) + len(name) + 2)}")

    emit(_key_tree(), "", 2)
    tail = document.prose.get("", [])
    return "\n".join(lines + [""] * bool(tail) + tail) + "\n"


def _trim(lines: list[str]) -> list[str]:
    """Lines without leading and trailing blank ones."""
    marks = [index for index, line in enumerate(lines) if line]
    return lines[marks[0]:marks[-1] + 1] if marks else []


_ENTRY = re.compile(r"^( *)([A-Za-z_][A-Za-z0-9_]*):(.*)$")


def parse_config_text(text: str, source: str = "config") -> ConfigDocument:
    """A config file's header, values, notes and prose (``ConfigDocument``); its table comments are dropped: the
    comment lines just above a key up to a lone ``#`` (all of them without one). Inline comments are dropped too."""
    lines = text.splitlines()
    try:
        start = lines.index(f"{NODE_NAME}:")
        parameters = yaml.safe_load(text)[NODE_NAME]["ros__parameters"]
    except (ValueError, TypeError, KeyError, yaml.YAMLError) as exc:
        raise ValueError(f"{source}: not a config file ('{NODE_NAME}: ros__parameters:' expected)") from exc
    document = ConfigDocument(header=_trim(lines[:start]), values=_flatten(parameters))
    unknown = sorted(set(document.values) - set(KEYS_BY_NAME))
    if unknown:
        raise ValueError(f"{source}: unknown key '{unknown[0]}'")
    pending: list[str] = []
    path: list[tuple[int, str]] = []
    value_indent: int | None = None
    for line in lines[start + 1:]:
        stripped = line.strip()
        indent = len(line) - len(line.lstrip())
        match = _ENTRY.match(line)
        if not stripped or stripped.startswith("#"):
            pending.append(stripped)
        elif match and (value_indent is None or indent <= value_indent) and stripped != "ros__parameters:":
            path = [(depth, name) for depth, name in path if depth < indent] + [(indent, match.group(2))]
            dotted = ".".join(name for _, name in path)
            before, pending = _trim(pending), []
            if dotted not in KEYS_BY_NAME:                        # a group
                value_indent = None
                document.prose.update({dotted: before} if before else {})
                continue
            value_indent = indent
            split = len(before) - before[::-1].index("") if "" in before else 0
            prose, block = _trim(before[:split]), before[split:]
            document.prose.update({dotted: prose} if prose else {})
            if "#" in block:
                document.notes[dotted] = block[block.index("#") + 1:]
    if _trim(pending):
        document.prose[""] = _trim(pending)
    return document


def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """Nested groups to dotted names (as ``config.flatten_parameters``)."""
    if not isinstance(tree, dict):
        return {}
    flat: dict[str, Any] = {}
    for name, value in tree.items():
        flat.update(_flatten(value, f"{prefix}{name}.") if isinstance(value, dict) else {f"{prefix}{name}": value})
    return flat


def regenerated_config_text(text: str, source: str = "config") -> str:
    """A config file with every key's table comment as KEYS says now; its values, notes and prose kept."""
    return config_text(parse_config_text(text, source))


def _write(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` unless it holds it already; say which."""
    if (path.read_text() if path.exists() else None) != text:
        path.write_text(text)
        print(f"wrote {path}")
    else:
        print(f"{path}: up to date")


def readme_with_keys_table(text: str) -> str:
    """``text`` (the README) with its table of keys (the lines from the table's header row) made ``keys_table()``."""
    header = keys_table().splitlines()[0]
    if header not in text:
        raise ValueError(f"the README has no table of keys (a line {header!r})")
    start = text.index(header)
    end = text.find("\n\n", start)
    end = len(text.rstrip("\n")) if end < 0 else end
    return text[:start] + keys_table() + text[end:]


def main(argv: list[str] | None = None) -> int:
    """``python -m kvark_ros.core.config_schema``: write the sources generated from the key table."""
    parser = argparse.ArgumentParser(prog="python -m kvark_ros.core.config_schema",
                                     description="Write what the key table generates (after changing KEYS).")
    parser.add_argument("--write-settings", action="store_true", help=f"write {SETTINGS_PATH.name} (typed settings)")
    parser.add_argument("--write-configs", nargs="*", metavar="FILE",
                        help="rewrite the key comments of config files, keeping their values, notes and prose "
                             f"(default: {CONFIG_DIR}/*.yaml)")
    parser.add_argument("--write-readme", type=Path, metavar="README",
                        help="replace the table of keys in this README.md by `kvark config --keys`")
    args = parser.parse_args(argv)
    if not args.write_settings and args.write_configs is None and args.write_readme is None:
        parser.error("give --write-settings, --write-configs and/or --write-readme")
    if args.write_settings:
        _write(SETTINGS_PATH, settings_source())
    if args.write_configs is not None:
        for path in map(Path, args.write_configs or sorted(CONFIG_DIR.glob("*.yaml"))):
            _write(path, regenerated_config_text(path.read_text(), str(path)))
    if args.write_readme is not None:
        _write(args.write_readme, readme_with_keys_table(args.write_readme.read_text()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
