"""Typed settings of the configuration: one frozen dataclass per group of keys, and ``EstimatorConfig``.

Generated from config_schema.KEYS by `python -m kvark_ros.tools.generate_sources --write-settings` (or
`make generated`); do not edit: change the key table and regenerate (the tests check this file).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from kvark_ros.core.estimation.payload import Payload

__all__ = ["WrenchSettings", "FilterSettings", "InputSettings", "ContactSettings", "OutputSettings", "TareSettings",
           "DiagnosticsSettings", "EstimatorConfig", "SETTINGS_BY_GROUP"]


@dataclass(frozen=True)
class WrenchSettings:
    """The ``wrench`` keys of the config (config_schema.KEYS)."""

    frame: Literal["base", "end_effector"] = "base"
    """axes of the published wrench: base or end_effector (ee_frame). Allowed: one of base, end_effector. Can be changed
    while the node runs."""
    base_frame: str = ""
    """frame_id and axes of the wrench for wrench.frame base: a frame fixed to the URDF's root link (UR: base, turned
    180° about z from base_link), '' = the root link; the reference point stays the ee_frame origin. Allowed: a frame of
    the URDF fixed to its root link, or '' for the root link."""
    convention: Literal["acting_on_robot", "applied_by_robot"] = "acting_on_robot"
    """sign of the published wrench: acting_on_robot (the environment's wrench on the robot, τ_ext = Jᵀ F) or
    applied_by_robot (its negative, as Franka's O_F_ext_hat_K); τ_ext keeps its sign. Allowed: one of acting_on_robot,
    applied_by_robot. Can be changed while the node runs."""
    damping: float = 0.05
    """damping δ of the pseudo-inverse (paper v2 eq. 39). Allowed: a number in [0.0, 10.0]. Can be changed while the
    node runs."""
    prior_force: float = 50.0
    """N; scale of an unknown force: the wrench covariance carries its damping bias along directions the joints cannot
    sense (docs/method.md §1.4.1). Allowed: a number in [0.0, 10000.0]. Can be changed while the node runs."""
    prior_moment: float = 5.0
    """N·m; the same for an unknown moment. Allowed: a number in [0.0, 10000.0]. Can be changed while the node runs."""


@dataclass(frozen=True)
class FilterSettings:
    """The ``filter`` keys of the config (config_schema.KEYS)."""

    initial_covariance: float = 1.0
    """P₀ (τ block) = value · I, N²·m². Allowed: a number in (0.0, 1000000.0]."""
    vb_iterations: int = 1
    """VB iterations M per sample. Allowed: an integer in [1, 50]."""
    vb_memory: float = 0.2
    """s; memory T of the inverse-Wishart statistics: forgetting ρ = 1 − t_s/T per sample of period t_s. Allowed: a
    number in (0.0, 1000000.0]."""
    vb_variant: Literal["paper", "huang", "smoothed", "window"] = "window"
    """reading of the VB step (docs/method.md §4.5-4.6). Allowed: one of paper, huang, smoothed, window."""
    vb_window_time: float = 0.05
    """s; window variant: length of a window of the τ_ext change (L = time / t_s samples, at least 5). Allowed: a number
    in [0.001, 60.0]."""
    vb_prior_dof: float = 1.0
    """window variant: prior strength ν₀ (in windows) of the IW prior around the trained Σ_d. Allowed: a number in (0.0,
    1000000.0]."""
    vb_window_source: Literal["estimate", "prior"] = "estimate"
    """window variant: the τ_ext estimate whose change the window statistic reads: estimate = the adaptive filter's own,
    prior = a twin filter on the same data held at the trained Σ_d0, as filtered (docs/method.md §4.6); prior suits
    motor-current arms, whose misfit the adaptive filter's own statistic feeds back. Allowed: one of estimate, prior."""
    prior_bandwidth: float = 20.0
    """rad/s; momentum form, VB variants (kvark, gmr_gp, oracle): natural frequency of the τ_ext random walk prior in
    free motion; the VB and the onset detector raise it at contact (docs/method.md §4.12). Allowed: a number in (0.0,
    10000.0]."""
    onset_threshold: float = 60.0
    """contact-onset GLR threshold (χ²(1) statistic; 0 = off; momentum form). Allowed: a number in [0.0, 1000000.0]."""
    onset_window_time: float = 0.02
    """s back the contact onset may lie (time / t_s hypotheses, at least 2). Allowed: a number in [0.001, 1.0]."""
    onset_contact_bandwidth: float = 100.0
    """rad/s; at a contact onset accepted on more than one sample every joint's Σ_d rises to at least the τ_ext random
    walk of this natural frequency (50 = the fixed filters' own), which the window VB then forgets back to the prior; 0
    = off (docs/method.md §4.7). Allowed: a number in [0.0, 10000.0]."""
    measurement: Literal["momentum", "difference"] = "momentum"
    """form of the filter: p measured (momentum) or the paper's eq. 28 (difference). Allowed: one of momentum,
    difference."""
    stiction_velocity: float = 0.05
    """rad/s; below it a joint counts as sticking: its interval widens to the trained static friction band
    (docs/method.md §4.11; 0 = off). Allowed: a number in [0.0, 10.0]. Can be changed while the node runs."""
    interval_calibration: Literal["trained", "off"] = "trained"
    """kvark's reported covariance: trained (scaled by the model's factors from contact-free training data,
    filter.interval_floor applied, docs/method.md §4.13) or off (the filter's own P). Allowed: one of trained, off. Can
    be changed while the node runs."""
    interval_floor: Literal["kf", "off"] = "kf"
    """with interval_calibration trained: kf (each reported variance at least the steady state P_b of the fixed-Σ_d kf
    while the contact test holds a load, so under a load kvark's interval is never narrower than kf's; in free motion at
    least c_b² P_b, kf's interval as the contact-free training data show it; docs/method.md §4.13) or off (the
    calibrated c² P alone, sharper where free-motion training data tell the whole story). Allowed: one of kf, off. Can
    be changed while the node runs."""
    huang_tau: float = 300.0
    """prior strength τ of the huang variant. Allowed: a number in (0.0, 1000000.0]."""
    ewma_time: float = 0.2
    """s; time constant T of the EWMA of the empirical noise (eq. 31): rate t_s/T per sample. Allowed: a number in (0.0,
    1000000.0]. Can be changed while the node runs."""
    nis_time: float = 0.2
    """s; time constant of the running-mean NIS (A4): rate t_s/T per sample. Allowed: a number in (0.0, 1000000.0]. Can
    be changed while the node runs."""


@dataclass(frozen=True)
class InputSettings:
    """The ``input`` keys of the config (config_schema.KEYS)."""

    max_gap: float = 0.05
    """s; a longer gap between joint states resets the filter. Allowed: a number in (0.0, 10.0]. Can be changed while
    the node runs."""
    command_max_age: float = 0.01
    """s; oldest command a joint state may be paired with. Allowed: a number in (0.0, 1.0]. Can be changed while the
    node runs."""
    torque_source: Literal["effort_commands", "effort_commands_joint_state", "joint_states_effort"] = "effort_commands"
    """where τ_m comes from: effort_commands (Float64MultiArray; offline also JointState), effort_commands_joint_state
    (JointState effort on effort_commands), joint_states_effort (effort of joint_states, e.g. measured link-side
    torque). Allowed: one of effort_commands, effort_commands_joint_state, joint_states_effort."""
    effort_scale: tuple[float, ...] = (1.0,)
    """τ_m = effort_scale · value + effort_offset per joint, applied to the values input.torque_source reads, live and
    offline: N·m/A for a motor current in A (UR's joint_states effort), 1 for N·m. Allowed: a list of 1 number (every
    joint) or one per joint."""
    effort_offset: tuple[float, ...] = (0.0,)
    """N·m added after effort_scale (see it). Allowed: a list of 1 number (every joint) or one per joint."""
    joint_states_topic: str = "joint_states"
    """sensor_msgs/JointState topic (q, q̇ and, for joint_states_effort, τ_m); bags match it with or without the leading
    /. Allowed: a non-empty string."""
    effort_commands_topic: str = "effort_commands"
    """commanded joint torque topic. Allowed: a non-empty string."""
    wrench_topic: str = "/ft_sensor/wrench"
    """offline ground truth: WrenchStamped of a wrist F/T sensor in the bag (replay --ground-truth ft). Allowed: a
    non-empty string."""
    external_torque_topic: str = "/ground_truth/external_joint_torque"
    """offline ground truth: JointState effort = true τ_ext in the bag (replay --ground-truth topic). Allowed: a
    non-empty string."""
    queue_depth: int = 100
    """subscription queue depth of the node (sensor-data QoS). Allowed: an integer in [1, 1000]."""


@dataclass(frozen=True)
class ContactSettings:
    """The ``contact`` keys of the config (config_schema.KEYS)."""

    confidence: float = 0.99
    """confidence of the variance-aware χ² contact test. Allowed: a number in (0.5, 1.0). Can be changed while the node
    runs."""
    collision_torque: float = 8.5
    """N·m; the collision flag is raised at once when a joint's |τ_ext| exceeds this by more than its interval (no
    debounce). Allowed: a number in (0.0, 1000.0]. Can be changed while the node runs."""
    debounce: float = 0.02
    """s the contact test must hold before the flag changes. Allowed: a number in [0.0, 1.0]. Can be changed while the
    node runs."""
    test_covariance: Literal["residual", "reported"] = "residual"
    """S of the contact test: residual = the filter's P plus the residual model's variance σ²_r(q̇) (docs/method.md
    §7.2), reported = K-VARK's reported covariance, the spread contact-free training data show τ̂ (interval factors,
    floor and static band, §4.13; other observers keep residual); the collision test keeps residual. Allowed: one of
    residual, reported. Can be changed while the node runs."""


@dataclass(frozen=True)
class OutputSettings:
    """The ``output`` keys of the config (config_schema.KEYS)."""

    qos: Literal["reliable", "sensor_data"] = "reliable"
    """QoS of the node's estimate topics: reliable, or sensor_data (best effort). Allowed: one of reliable,
    sensor_data."""


@dataclass(frozen=True)
class TareSettings:
    """The ``tare`` keys of the config (config_schema.KEYS)."""

    duration: float = 1.0
    """s of rest ~/tare averages τ_ext over. Allowed: a number in (0.0, 60.0]. Can be changed while the node runs."""
    max_speed: float = 0.02
    """rad/s; ~/tare refuses (and stops) while any joint moves faster. Allowed: a number in (0.0, 10.0]. Can be changed
    while the node runs."""


@dataclass(frozen=True)
class DiagnosticsSettings:
    """The ``diagnostics`` keys of the config (config_schema.KEYS)."""

    max_loss: float = 0.01
    """share of joint states lost (gaps in their stamps) above which /diagnostics warns. Allowed: a number in [0.0,
    1.0]. Can be changed while the node runs."""
    period: float = 1.0
    """s between /diagnostics messages. Allowed: a number in (0.0, 60.0]. Can be changed while the node runs."""


@dataclass(frozen=True)
class EstimatorConfig:
    """Validated estimator settings (config_schema.KEYS). Units SI; see config/panda.yaml."""

    robot: str
    """robot name, written into models and reports. Allowed: a non-empty string."""
    urdf: str
    """nominal model: URDF path, example-robot-data:panda / :ur5 / :ur10, or robot_description (the node takes the
    topic; kvark's commands need a file: keep the file the model was trained with). Allowed: a non-empty string."""
    joint_names: tuple[str, ...]
    """estimated joints, in output order; others are locked; messages are matched by these names. Allowed: a non-empty
    list of distinct joint names."""
    ee_frame: str
    """wrench reference frame (origin and, for wrench.frame end_effector, axes). Allowed: a non-empty string."""
    flange_frame: str
    """frame a known payload attaches to. Allowed: a non-empty string."""
    model_dir: str
    """trained model directory written by kvark train (~/reload_model reloads it). Allowed: a non-empty string."""
    torque_measurement: Literal["link_torque_sensor", "motor_current", "commanded_effort"] = "motor_current"
    """how τ_m is measured, for kvark diagnose's priors: link_torque_sensor (Panda, KUKA iiwa), motor_current (UR: gain
    × current) or commanded_effort (widest); default motor_current, what most ROS drivers' effort is. Allowed: one of
    link_torque_sensor, motor_current, commanded_effort."""
    model_augmentation: str = ""
    """augmentation.yaml of kvark diagnose for kvark train; at estimation it must be the model directory's copy ('' =
    that copy). Allowed: a path, or '' for none."""
    observer: str = "kvark"
    """observer name (README, Observers). Allowed: an observer of core/observer_catalog.py (kvark replay --help lists
    them)."""
    payload: Payload | None = None
    """the robot_model.payload.* keys: the known payload at the flange, or None when its mass is 0"""
    wrench: WrenchSettings = field(default_factory=WrenchSettings)
    """the wrench.* keys"""
    filter: FilterSettings = field(default_factory=FilterSettings)
    """the filter.* keys"""
    input: InputSettings = field(default_factory=InputSettings)
    """the input.* keys"""
    contact: ContactSettings = field(default_factory=ContactSettings)
    """the contact.* keys"""
    output: OutputSettings = field(default_factory=OutputSettings)
    """the output.* keys"""
    tare: TareSettings = field(default_factory=TareSettings)
    """the tare.* keys"""
    diagnostics: DiagnosticsSettings = field(default_factory=DiagnosticsSettings)
    """the diagnostics.* keys"""

    @property
    def n_joints(self) -> int:
        """Number of estimated joints (``robot_model.joint_names``)."""
        return len(self.joint_names)


# Group name -> its settings class (robot_model.payload.* becomes ``EstimatorConfig.payload`` instead).
SETTINGS_BY_GROUP: dict[str, type] = {
    "wrench": WrenchSettings,
    "filter": FilterSettings,
    "input": InputSettings,
    "contact": ContactSettings,
    "output": OutputSettings,
    "tare": TareSettings,
    "diagnostics": DiagnosticsSettings,
}
