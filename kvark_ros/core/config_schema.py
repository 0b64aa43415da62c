"""The one table of configuration keys: name, type, allowed values, default, run-time, meaning.

Everything else about a key comes from this table: validation (``kvark_ros.core.config``), the typed
settings groups the code reads (``config.filter.ewma_time``, generated into ``kvark_ros/core/settings.py``),
the ROS node's parameter descriptors, the key comments of ``config/*.yaml`` and of ``kvark init``'s files, and
the README's key table (``kvark config --keys``); ``core.config_sources`` writes the generated ones. Adding a key is
one ``Key`` row here, ``make generated`` (the tests fail until it ran) and the code that uses it.

Dotted names are the ROS parameter names and the YAML nesting (``filter.ewma_time`` is
``filter: {ewma_time: ...}``). ``group``/``attr`` say where the value lives in ``EstimatorConfig``:
``config.<attr>`` for top-level keys, ``config.<group>.<attr>`` for grouped ones.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable


from kvark_ros.core.observer_catalog import OBSERVER_NAMES

NODE_NAME = "kvark_estimator"              # the node's name: the top-level key of every config file
WRENCH_FRAMES = ("base", "end_effector")
VB_VARIANTS = ("paper", "huang", "smoothed", "window")
VB_WINDOW_SOURCES = ("estimate", "prior")
MEASUREMENTS = ("momentum", "difference")
TORQUE_SOURCES = ("effort_commands", "effort_commands_joint_state", "joint_states_effort")
OUTPUT_QOS = ("reliable", "sensor_data")
CONTACT_TEST_COVARIANCES = ("residual", "reported")
# How a joint's τ_m is measured; sets how wide ``kvark diagnose``'s priors are (gap/priors.py, docs/method.md §8).
TORQUE_MEASUREMENTS = ("link_torque_sensor", "motor_current", "commanded_effort")
# Whose wrench the node publishes: the environment's on the robot (τ_ext = Jᵀ F, kvark's), or the robot's on the
# environment (−F: Franka's O_F_ext_hat_K and K_F_ext_hat_K).
WRENCH_CONVENTIONS = ("acting_on_robot", "applied_by_robot")
# geometry_msgs/Inertia's and URDF's order of an inertia's six values.
INERTIA_ORDER = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
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

    kind: ``text``, ``path`` (text, may be empty), ``frame`` (a frame name, may be empty), ``names`` (list of
    distinct strings), ``number``, ``integer``, ``choice``, ``vector3``, ``vector6`` or ``per_joint`` (one number
    for every joint or one per joint; the config checks the count against the joints). ``low``/``high`` bound
    numbers and integers, ``low_open``/``high_open`` make an end exclusive; ``choices`` lists a choice's options.
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
                "frame": "a frame of the URDF fixed to its root link, or '' for the root link",
                "names": "a non-empty list of distinct joint names", "choice": f"one of {', '.join(self.choices)}",
                "vector3": "a list of 3 numbers",
                "vector6": f"a list of 6 numbers [{', '.join(INERTIA_ORDER)}]",
                "per_joint": "a list of 1 number (every joint) or one per joint"}[self.kind]

    @property
    def documented(self) -> str:
        """What the key accepts, as the generated README table, config comments and settings say it."""
        return OPEN_CHOICES.get(self.name, self.allowed)

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
            "frame": lambda v: isinstance(v, str),
            "names": lambda v: (isinstance(v, list) and len(v) > 0 and all(isinstance(x, str) and x for x in v)
                                and len(set(v)) == len(v)),
            "choice": lambda v: v in self.choices,
            "vector3": lambda v: isinstance(v, list) and len(v) == 3 and all(_is_number(x) for x in v),
            "vector6": lambda v: isinstance(v, list) and len(v) == 6 and all(_is_number(x) for x in v),
            "per_joint": lambda v: isinstance(v, list) and len(v) > 0 and all(_is_number(x) for x in v),
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
         "nominal model: URDF path, example-robot-data:panda / :ur5 / :ur10, or robot_description (the node takes "
         "the topic; kvark's commands need a file: keep the file the model was trained with)", attr="urdf"),
    _key("robot_model.joint_names", "names", None,
         "estimated joints, in output order; others are locked; messages are matched by these names", attr="joint_names"),
    _key("robot_model.ee_frame", "text", None, "wrench reference frame (origin and, for wrench.frame end_effector, axes)", attr="ee_frame"),
    _key("robot_model.flange_frame", "text", None, "frame a known payload attaches to", attr="flange_frame"),
    _key("robot_model.payload.mass", "number", 0.0, "known tool/payload at the flange added to the nominal model, kg (0: none)",
         runtime=True, **_unit(0.0, 1000.0), group="payload", attr="mass"),
    _key("robot_model.payload.com", "vector3", [0.0, 0.0, 0.0], "payload centre of mass in the flange frame, m",
         runtime=True, group="payload", attr="com"),
    _key("robot_model.payload.inertia", "vector6", [0.0] * 6,
         "payload inertia about its CoM in flange axes, kg m^2, in geometry_msgs/Inertia's and URDF's order (ixx "
         "ixy ixz iyy iyz izz)", runtime=True,
         group="payload", attr="inertia"),
    _key("residual_model.model_dir", "text", None,
         "trained model directory written by kvark train (~/reload_model reloads it)", attr="model_dir"),
    _key("robot_model.torque_measurement", "choice", "motor_current",
         "how τ_m is measured, for kvark diagnose's priors: link_torque_sensor (Panda, KUKA iiwa), motor_current "
         "(UR: gain × current) or commanded_effort (widest); default motor_current, what most ROS drivers' effort "
         "is", choices=TORQUE_MEASUREMENTS, attr="torque_measurement"),
    _key("model_augmentation", "path", "",
         "augmentation.yaml of kvark diagnose for kvark train; at estimation it must be the model directory's copy ('' = that copy)"),
    _key("observer", "choice", "kvark", "observer name (README, Observers)", choices=OBSERVER_NAMES),
    _key("wrench.frame", "choice", "base", "axes of the published wrench: base or end_effector (ee_frame)", runtime=True, choices=WRENCH_FRAMES),
    _key("wrench.base_frame", "frame", "",
         "frame_id and axes of the wrench for wrench.frame base: a frame fixed to the URDF's root link (UR: base, "
         "turned 180° about z from base_link), '' = the root link; the reference point stays the ee_frame origin"),
    _key("wrench.convention", "choice", "acting_on_robot",
         "sign of the published wrench: acting_on_robot (the environment's wrench on the robot, τ_ext = Jᵀ F) or "
         "applied_by_robot (its negative, as Franka's O_F_ext_hat_K); τ_ext keeps its sign", runtime=True,
         choices=WRENCH_CONVENTIONS),
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
    _key("filter.vb_window_source", "choice", "estimate",
         "window variant: the τ_ext estimate whose change the window statistic reads: estimate = the adaptive "
         "filter's own, prior = a twin filter on the same data held at the trained Σ_d0, as filtered (docs/method.md "
         "§4.6); prior suits motor-current arms, whose misfit the adaptive filter's own statistic feeds back",
         choices=VB_WINDOW_SOURCES),
    _key("filter.prior_bandwidth", "number", 20.0,
         "rad/s; momentum form, VB variants (kvark, gmr_gp, oracle): natural frequency of the τ_ext random walk "
         "prior in free motion; the VB and the onset detector raise it at contact (docs/method.md §4.12)",
         **_unit(0.0, 1e4, low_open=True)),
    _key("filter.onset_threshold", "number", 60.0,
         "contact-onset GLR threshold (χ²(1) statistic; 0 = off; momentum form)", **_unit(0.0, 1e6)),
    _key("filter.onset_window_time", "number", 0.02,
         "s back the contact onset may lie (time / t_s hypotheses, at least 2)", **_unit(0.001, 1.0)),
    _key("filter.onset_contact_bandwidth", "number", 100.0,
         "rad/s; at a contact onset accepted on more than one sample every joint's Σ_d rises to at least the τ_ext "
         "random walk of this natural frequency (50 = the fixed filters' own), which the window VB then forgets back "
         "to the prior; 0 = off (docs/method.md §4.7)", **_unit(0.0, 1e4)),
    _key("filter.measurement", "choice", "momentum", "form of the filter: p measured (momentum) or the paper's eq. 28 (difference)", choices=MEASUREMENTS),
    _key("filter.stiction_velocity", "number", 0.05,
         "rad/s; below it a joint counts as sticking: its interval widens to the trained static friction band "
         "(docs/method.md §4.11; 0 = off)", runtime=True, **_unit(0.0, 10.0)),
    _key("filter.interval_calibration", "choice", "trained",
         "kvark's reported covariance: trained (scaled by the model's factors from contact-free training data, "
         "filter.interval_floor applied, docs/method.md §4.13) or off (the filter's own P)",
         runtime=True, choices=("trained", "off")),
    _key("filter.interval_floor", "choice", "kf",
         "with interval_calibration trained: kf (each reported variance at least the steady state P_b of the "
         "fixed-Σ_d kf while the contact test holds a load, so under a load kvark's interval is never narrower "
         "than kf's; in free motion at least c_b² P_b, kf's interval as the contact-free training data show it; "
         "docs/method.md §4.13) or off (the calibrated c² P alone, sharper where free-motion training data tell "
         "the whole story)", runtime=True,
         choices=("kf", "off")),
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
    _key("input.effort_scale", "per_joint", [1.0],
         "τ_m = effort_scale · value + effort_offset per joint, applied to the values input.torque_source reads, "
         "live and offline: N·m/A for a motor current in A (UR's joint_states effort), 1 for N·m"),
    _key("input.effort_offset", "per_joint", [0.0], "N·m added after effort_scale (see it)"),
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
    _key("contact.test_covariance", "choice", "residual",
         "S of the contact test: residual = the filter's P plus the residual model's variance σ²_r(q̇) (docs/method.md "
         "§7.2), reported = K-VARK's reported covariance, the spread contact-free training data show τ̂ (interval "
         "factors, floor and static band, §4.13; other observers keep residual); the collision test keeps residual",
         runtime=True, choices=CONTACT_TEST_COVARIANCES),
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
    "filter.kernel": "the momentum-form K-VARK step is always compiled (core/estimation/compiled); "
                     "delete the key",
}
GROUPS: tuple[str, ...] = tuple(dict.fromkeys(key.group for key in KEYS if key.group))


# Choices that are another table's names: their type stays ``str`` and the generated text (README table, config
# comments, settings) names that table instead of listing it, so the table grows without regenerating; errors and
# ROS descriptors still list every name (``Key.allowed``).
OPEN_CHOICES = {"observer": "an observer of core/observer_catalog.py (kvark replay --help lists them)"}


def keys_table() -> str:
    """The README's table of configuration keys (Markdown), made from ``KEYS``."""
    rows = ["| key | allowed | default | run time | meaning |", "|---|---|---|---|---|"]
    for key in KEYS:
        default = "required" if key.default is None else f"`{key.default!r}`".replace("'", "")
        rows.append(f"| `{key.name}` | {key.documented} | {default} | {'yes' if key.runtime else 'no'} | "
                    f"{key.meaning} |")
    return "\n".join(rows)
