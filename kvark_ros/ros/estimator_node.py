"""ROS 2 node ``kvark_estimator``: the ``Estimator`` of ``kvark replay``, live.

Run ``ros2 launch kvark_ros estimator.launch.py`` (or ``ros2 run kvark_ros estimator_node
--ros-args --params-file config/panda.yaml``). A thin adapter: every number comes from
``kvark_ros.core.estimator.Estimator.step``, the call ``kvark replay`` makes per sample.

Topics (DESIGN §5; relative names, remappable)
    in   ``joint_states`` (sensor_msgs/JointState), ``effort_commands`` (std_msgs/Float64MultiArray,
         or sensor_msgs/JointState with ``torque_source: effort_commands_joint_state``),
         ``robot_description`` (std_msgs/String, transient local). Sensor inputs use the
         sensor-data QoS with depth ``input.queue_depth``.
    out  ``~/external_joint_torque`` (JointState: effort = τ_ext in ``joint_names`` order, stamp of
         the input), ``~/external_wrench`` (WrenchStamped at the ``ee_frame`` origin; frame_id = the
         URDF root link for ``wrench.frame: base``, else ``ee_frame``), ``~/external_joint_torque_stddev``
         (Float64MultiArray, √diag P, labelled with the joint names), ``~/external_wrench_covariance``
         (Float64MultiArray, 6×6 row-major, fx fy fz tx ty tz), ``~/contact`` (Bool), ``/diagnostics``.
         The uncertainty topics are silent for observers that report no covariance.
    services ``~/reset`` and ``~/reload_model`` (std_srvs/Trigger).

Pairing joint states with commanded torque
    A Float64MultiArray has no stamp. The node stamps each command with the header stamp of the
    newest joint state received before it: a command belongs to the state it was computed from,
    which is how a control loop (read state, compute, publish) and our simulator's bags order
    them. A joint state is estimated as soon as its command arrives; a state that no command
    follows is paired, when the next state arrives, with the newest earlier command if that is no
    older than ``input.command_max_age`` (else it is skipped and counted). Fed a bag's messages in
    log order, this gives ``kvark replay``'s pairing (``kvark_ros.io.alignment``) sample for sample,
    and so the same τ_ext and wrench: the test suite checks it to 1e-9. It needs no clock
    agreement between the robot's stamps and this node (``ros2 bag play`` works without
    ``--clock``); it assumes commands arrive after the state they answer (the joint_states
    subscription is created first, so rclpy's executor takes the state first when both wait). With
    ``torque_source: joint_states_effort`` the effort field of ``joint_states`` is τ_m (drivers
    that report the full measured joint torque, e.g. franka_ros2) and nothing is paired.
    A joint state with a zero stamp (a driver that never fills it) is stamped with its receive
    time on the node clock, except the first one after start or a reset (simulated bags start at 0 s).

Robustness
    Joints are matched by name (any order, extra joints ignored; a message naming none of the
    joints, e.g. a gripper's, is ignored; a missing joint rejects the sample). NaN/Inf samples,
    stale commands, out-of-order stamps, gaps (filter reset) and backward time jumps (filter
    reset) are counted per reason and summarised on ``/diagnostics``; nothing is logged per
    message, nothing non-finite is published (the Estimator never returns a non-finite estimate).

Parameters
    The keys of ``config/panda.yaml`` (validated by ``kvark_ros.core.config.config_from_parameters``,
    the one place) plus ``torque_source``. Keys in ``RUNTIME_FIELDS`` may change while the node
    runs; the others are read-only. Numbers accept YAML integers (``1`` for ``1.0``) as the CLI does.
    Relative ``residual_model.model_dir`` / ``robot_model.urdf`` paths resolve against the
    package's share directory (then the source tree, then the working directory). The URDF
    comes from ``robot_model.urdf``; set it to ``robot_description`` to build from that topic
    instead (the topic is also used if it arrives while no estimator could be built).

Callbacks run in the default, mutually exclusive callback group: single-threaded executor.
"""
from __future__ import annotations

import array
import math
import sys
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import WrenchStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterException, ParameterUninitializedException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray, Header, MultiArrayDimension, MultiArrayLayout, String
from std_srvs.srv import Trigger

from kvark_ros.core.config import (MEASUREMENTS, NODE_NAME, OBSERVER_NAMES, VB_VARIANTS, WRENCH_FRAMES, ConfigError,
                                   EstimatorConfig, with_resolved_paths, config_from_parameters,
                                   parameter_defaults)
from kvark_ros.core.estimator import Estimator, Status
from kvark_ros.core.model_store import TrainedModel, load_model
from kvark_ros.core.robot_model import urdf_sha256
from kvark_ros.ros.contact import ContactDetector, contact_covariance

T = Parameter.Type
URDF_FROM_TOPIC = "robot_description"
TORQUE_SOURCE = "torque_source"
TORQUE_SOURCES = ("effort_commands", "effort_commands_joint_state", "joint_states_effort")
WRENCH_AXES = ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z")


@dataclass(frozen=True)
class ParameterSpec:
    """How a config key is declared: type, meaning, whether it may change at run time, allowed values."""

    type: T
    description: str
    constraints: str
    runtime: bool = False
    limits: tuple[float, float] | None = None     # closed range for the descriptor; the config checks open ends


PARAMETERS: dict[str, ParameterSpec] = {
    "robot": ParameterSpec(T.STRING, "robot name, written into models and reports", "non-empty"),
    "robot_model.urdf": ParameterSpec(
        T.STRING, "nominal model: URDF file, example-robot-data:<robot>, or robot_description (the topic)",
        "non-empty"),
    "robot_model.joint_names": ParameterSpec(
        T.STRING_ARRAY, "estimated joints in output order; messages are matched by these names", "distinct names"),
    "robot_model.ee_frame": ParameterSpec(T.STRING, "frame whose origin is the wrench reference point", "URDF frame"),
    "robot_model.flange_frame": ParameterSpec(T.STRING, "frame a known payload is attached to", "URDF frame"),
    "robot_model.payload.mass": ParameterSpec(T.DOUBLE, "known payload at the flange, kg (0: none)", "[0, 1000]",
                                              limits=(0.0, 1000.0)),
    "robot_model.payload.com": ParameterSpec(T.DOUBLE_ARRAY, "payload centre of mass in the flange frame, m",
                                             "3 numbers"),
    "robot_model.payload.inertia": ParameterSpec(T.DOUBLE_ARRAY, "payload inertia about its CoM, kg m^2",
                                                 "6 numbers: ixx iyy izz ixy ixz iyz"),
    "residual_model.model_dir": ParameterSpec(T.STRING, "model directory written by kvark train (~/reload_model "
                                              "reloads it)", "directory with model.yaml"),
    "model_augmentation": ParameterSpec(T.STRING, "augmentation.yaml of kvark diagnose; must be the one the model "
                                        "was trained with ('' = the model directory's)", "path or ''"),
    "observer": ParameterSpec(T.STRING, "observer", f"one of {', '.join(OBSERVER_NAMES)}"),
    "wrench.frame": ParameterSpec(T.STRING, "axes of the published wrench", f"one of {', '.join(WRENCH_FRAMES)}",
                                  runtime=True),
    "wrench.damping": ParameterSpec(T.DOUBLE, "damping of the pseudo-inverse (paper v2 eq. 39)", "[0, 10]",
                                    runtime=True, limits=(0.0, 10.0)),
    "filter.initial_covariance": ParameterSpec(T.DOUBLE, "P0 = value * I, N^2 m^2", "(0, 1e6]", limits=(0.0, 1e6)),
    "filter.vb_iterations": ParameterSpec(T.INTEGER, "VB iterations per sample", "[1, 50]", limits=(1, 50)),
    "filter.vb_forgetting": ParameterSpec(T.DOUBLE, "forgetting of the inverse-Wishart prediction", "(0, 1]",
                                          limits=(0.0, 1.0)),
    "filter.vb_variant": ParameterSpec(T.STRING, "reading of the VB step", f"one of {', '.join(VB_VARIANTS)}"),
    "filter.vb_window": ParameterSpec(T.INTEGER, "samples per window of the window VB variant", "[5, 5000]",
                                      limits=(5, 5000)),
    "filter.vb_prior_dof": ParameterSpec(T.DOUBLE, "prior strength (windows) of the window VB variant", "(0, 1e6]",
                                         limits=(0.0, 1e6)),
    "filter.onset_threshold": ParameterSpec(T.DOUBLE, "contact-onset GLR threshold on 2 ln(Lambda), 0 = off "
                                            "(momentum form)", "[0, 1e6]", limits=(0.0, 1e6)),
    "filter.onset_window": ParameterSpec(T.INTEGER, "onset hypotheses kept per joint, samples", "[2, 500]",
                                         limits=(2, 500)),
    "filter.measurement": ParameterSpec(T.STRING, "form of the filter", f"one of {', '.join(MEASUREMENTS)}"),
    "filter.huang_tau": ParameterSpec(T.DOUBLE, "prior strength of the huang variant", "(0, 1e6]",
                                      limits=(0.0, 1e6)),
    "filter.ewma_rate": ParameterSpec(T.DOUBLE, "EWMA rate of the empirical noise (eq. 31)", "(0, 1]",
                                      runtime=True, limits=(0.0, 1.0)),
    "filter.nis_rate": ParameterSpec(T.DOUBLE, "running-mean NIS rate (A4)", "(0, 1]", runtime=True,
                                     limits=(0.0, 1.0)),
    "input.max_gap": ParameterSpec(T.DOUBLE, "a longer gap between joint states resets the filter, s", "(0, 10]",
                                   runtime=True, limits=(0.0, 10.0)),
    "input.command_max_age": ParameterSpec(T.DOUBLE, "oldest command a joint state is paired with, s", "(0, 1]",
                                           runtime=True, limits=(0.0, 1.0)),
    "input.queue_depth": ParameterSpec(T.INTEGER, "subscription queue depth (sensor-data QoS)", "[1, 1000]",
                                       limits=(1, 1000)),
    "contact.confidence": ParameterSpec(T.DOUBLE, "confidence of the chi-square contact test", "(0.5, 1)",
                                        runtime=True, limits=(0.5, 1.0)),
    "contact.debounce": ParameterSpec(T.DOUBLE, "the contact flag changes after the test held this long, s",
                                      "[0, 1]", runtime=True, limits=(0.0, 1.0)),
    "diagnostics.period": ParameterSpec(T.DOUBLE, "period of /diagnostics, s", "(0, 60]", runtime=True,
                                        limits=(0.0, 60.0)),
}
# Keys that may change at run time -> EstimatorConfig field. The Estimator, the observer and the
# node read these from the config on every sample, so replacing the config applies them.
RUNTIME_FIELDS = {
    "wrench.frame": "wrench_frame", "wrench.damping": "wrench_damping", "filter.ewma_rate": "ewma_rate",
    "filter.nis_rate": "nis_rate", "input.max_gap": "max_gap", "input.command_max_age": "command_max_age",
    "contact.confidence": "contact_confidence", "contact.debounce": "contact_debounce",
    "diagnostics.period": "diagnostics_period",
}


class Drop:
    """Why the node (not the Estimator) skipped a message; keys of the node's counts on /diagnostics."""

    NOT_READY = "dropped: no estimator (model not loaded or waiting for robot_description)"
    OTHER_JOINTS = "ignored: joint_states message names none of the configured joints"
    MISSING_JOINT = "rejected: a configured joint is missing from joint_states"
    MALFORMED = "rejected: joint_states without position/velocity, or lengths differ from its names"
    NO_EFFORT = "rejected: joint_states without effort (torque_source joint_states_effort)"
    OUT_OF_ORDER = "rejected: joint_states stamp not after the previous one"
    TIME_JUMP = "reset: joint_states stamp jumped backwards by more than input.max_gap"
    STALE = "rejected: no effort command within input.command_max_age"
    BAD_COMMAND = "rejected: effort command with the wrong length or joints"
    EARLY_COMMAND = "ignored: effort command before the first joint state"
    SERVICE_RESET = "reset: ~/reset service"


_NOT_PROBLEMS = {Status.OK, Status.WARMUP, Drop.OTHER_JOINTS, Drop.EARLY_COMMAND, Drop.SERVICE_RESET}
_RESETS = (Status.GAP_RESET, Status.DIVERGED_RESET, Drop.TIME_JUMP, Drop.SERVICE_RESET)
_LEVELS = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR)
_UNSEEN = object()
_BUILD_ERRORS = (ValueError, OSError, RuntimeError, KeyError, TypeError, np.linalg.LinAlgError)


def _doubles(values: np.ndarray) -> array.array:
    """float64[] message field from a numpy array (rclpy takes array.array('d'), not ndarray)."""
    return array.array("d", np.ascontiguousarray(values, dtype=np.float64).tobytes())


def _plain(value: Any) -> Any:
    """A parameter value as the config expects it: arrays as lists."""
    if isinstance(value, (array.array, tuple)):
        return list(value)
    return value


def _describe(exc: BaseException) -> str:
    return str(exc) or type(exc).__name__


def _package_roots() -> list[Path]:
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


def _root_link(estimator: Estimator) -> str:
    """Name of the URDF root link (the frame whose axes ``wrench.frame: base`` uses)."""
    for frame in estimator.robot.model.frames:
        if frame.parentJoint == 0 and str(frame.type) == "BODY":
            return frame.name
    return "base"


def _descriptor(spec: ParameterSpec) -> ParameterDescriptor:
    descriptor = ParameterDescriptor(description=spec.description, additional_constraints=spec.constraints,
                                     read_only=not spec.runtime)
    if spec.type in (T.DOUBLE, T.DOUBLE_ARRAY):
        descriptor.dynamic_typing = True      # YAML integers are numbers too; the config validates
    if spec.limits is not None:
        low, high = spec.limits
        if spec.type == T.INTEGER:
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=1)]
        else:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high),
                                                                  step=0.0)]
    return descriptor


class EstimatorNode(Node):
    """The ``kvark_estimator`` node (module docstring). ``kwargs`` go to ``rclpy.node.Node``."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._declare_parameters()
        self._config = self._read_config()
        self._torque_source = self.get_parameter(TORQUE_SOURCE).value
        if self._torque_source not in TORQUE_SOURCES:
            raise ConfigError(f"parameters of {self.get_fully_qualified_name()}: key '{TORQUE_SOURCE}' has invalid "
                              f"value {self._torque_source!r}; allowed: one of {', '.join(TORQUE_SOURCES)}")
        config = self._config
        self._names = list(config.joint_names)
        self._n = config.n_joints
        self._columns: dict[tuple[str, ...], Any] = {}
        self._command_columns: dict[tuple[str, int], Any] = {}
        self._estimator: Estimator | None = None
        self._trained: TrainedModel | None = None
        self._residual: Any = None
        self._compensated = True
        self._urdf_xml: str | None = None          # newest robot_description received
        self._urdf_in_use = ""
        self._base_frame = "base"
        self._model_problem = "model not loaded yet"
        self._reload_problem: str | None = None
        self._told_about_description = False
        self._missing_detail = ""
        self._pending: tuple | None = None        # (stamp, stamp msg, q, qd) waiting for its command
        self._command: tuple[float, np.ndarray] | None = None   # (stamp of its joint state, τ_m)
        self._last_stamp: float | None = None
        self._counts: Counter[str] = Counter()
        self._archived: Counter[str] = Counter()  # Status counts of estimators replaced by a reload
        self._received = 0
        self._published = 0
        self._last_covariance: np.ndarray | None = None
        self._contact = ContactDetector(self._n, config.contact_confidence, config.contact_debounce)
        self._diag_time = self._now()
        self._diag_received = self._diag_published = 0
        self._diag_counts: Counter[str] = Counter()
        label = ",".join(self._names)
        self._stddev_layout = MultiArrayLayout(
            dim=[MultiArrayDimension(label=label, size=self._n, stride=self._n)], data_offset=0)
        self._covariance_layout = MultiArrayLayout(
            dim=[MultiArrayDimension(label="row: " + ",".join(WRENCH_AXES), size=6, stride=36),
                 MultiArrayDimension(label="column: " + ",".join(WRENCH_AXES), size=6, stride=6)], data_offset=0)

        sensor_qos = QoSProfile(history=qos_profile_sensor_data.history, depth=config.queue_depth,
                                reliability=qos_profile_sensor_data.reliability,
                                durability=qos_profile_sensor_data.durability)
        output_qos = QoSProfile(depth=config.queue_depth)
        self._pub_torque = self.create_publisher(JointState, "~/external_joint_torque", output_qos)
        self._pub_wrench = self.create_publisher(WrenchStamped, "~/external_wrench", output_qos)
        self._pub_stddev = self.create_publisher(Float64MultiArray, "~/external_joint_torque_stddev", output_qos)
        self._pub_covariance = self.create_publisher(Float64MultiArray, "~/external_wrench_covariance", output_qos)
        self._pub_contact = self.create_publisher(Bool, "~/contact", output_qos)
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))
        self.create_subscription(JointState, "joint_states", self._on_joint_state, sensor_qos)
        if self._torque_source == "effort_commands":
            self.create_subscription(Float64MultiArray, "effort_commands", self._on_command_array, sensor_qos)
        elif self._torque_source == "effort_commands_joint_state":
            self.create_subscription(JointState, "effort_commands", self._on_command_state, sensor_qos)
        self.create_subscription(String, "robot_description", self._on_robot_description,
                                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_service(Trigger, "~/reload_model", self._on_reload_model)
        self._timer = self.create_timer(config.diagnostics_period, self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        if config.urdf == URDF_FROM_TOPIC:
            self._model_problem = "waiting for the URDF on robot_description"
            self.get_logger().info("waiting for robot_description to build the estimator")
        else:
            problem = self._load(None)
            if problem is not None:
                self._model_problem = problem
                self.get_logger().error(f"no estimator: {problem} (fix it, then call ~/reload_model)")
        self.get_logger().info(
            f"observer {config.observer}, {self._n} joints, model {config.model_dir}, "
            f"torque from {self._torque_source}; outputs under {self.get_fully_qualified_name()}/")

    # ------------------------------------------------------------------ parameters

    def _declare_parameters(self) -> None:
        defaults = parameter_defaults()           # the config's defaults; None marks a required key
        for name, spec in PARAMETERS.items():
            default = defaults[name]
            self.declare_parameter(name, spec.type if default is None else default, _descriptor(spec))
        self.declare_parameter(TORQUE_SOURCE, TORQUE_SOURCES[0], ParameterDescriptor(
            description="where τ_m comes from: effort_commands (Float64MultiArray), effort_commands_joint_state "
                        "(JointState effort on effort_commands), joint_states_effort (effort of joint_states)",
            additional_constraints=f"one of {', '.join(TORQUE_SOURCES)}", read_only=True))

    def _parameter_values(self) -> dict[str, Any]:
        """Dotted key -> value of every declared config key that has a value."""
        values = {}
        for name in PARAMETERS:
            try:
                value = self.get_parameter(name).value
            except ParameterUninitializedException:
                continue
            if value is not None:
                values[name] = _plain(value)
        return values

    def _read_config(self) -> EstimatorConfig:
        config = config_from_parameters(self._parameter_values(), f"parameters of {self.get_fully_qualified_name()}")
        for root in _package_roots():
            config = with_resolved_paths(config, root)
        return config

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """On-set callback: accept run-time keys with values the config accepts; refuse the rest with a reason."""
        changes = {}
        for parameter in parameters:
            if parameter.name == TORQUE_SOURCE:
                return SetParametersResult(successful=False, reason=(
                    f"{TORQUE_SOURCE} cannot change while the node runs; restart the node with the new value"))
            spec = PARAMETERS.get(parameter.name)
            if spec is None:
                continue                          # not ours (use_sim_time, QoS overrides, ...)
            if not spec.runtime:
                return SetParametersResult(successful=False, reason=(
                    f"{parameter.name} cannot change while the node runs (it shapes the model, the filter or the "
                    f"node's interfaces); change it in the parameter file and restart the node. Run-time keys: "
                    f"{', '.join(RUNTIME_FIELDS)}"))
            changes[parameter.name] = _plain(parameter.value)
        if changes:
            values = self._parameter_values()
            values.update(changes)
            try:
                config_from_parameters(values, "parameter update")
            except ConfigError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        """Post-set callback: rebuild the frozen config with the new run-time values and apply it."""
        names = [p.name for p in parameters if p.name in RUNTIME_FIELDS]
        if not names:
            return
        candidate = config_from_parameters(self._parameter_values(), "parameter update")
        updates = {RUNTIME_FIELDS[name]: getattr(candidate, RUNTIME_FIELDS[name]) for name in names}
        self._apply_config(replace(self._config, **updates))
        self.get_logger().info("parameters changed: " + ", ".join(f"{n}={getattr(candidate, RUNTIME_FIELDS[n])}"
                                                                  for n in names))

    def _apply_config(self, config: EstimatorConfig) -> None:
        previous, self._config = self._config, config
        if self._estimator is not None:
            self._estimator.config = config
            if hasattr(self._estimator.observer, "config"):
                self._estimator.observer.config = config
        self._contact.configure(config.contact_confidence, config.contact_debounce)
        if config.diagnostics_period != previous.diagnostics_period:
            self.destroy_timer(self._timer)
            self._timer = self.create_timer(config.diagnostics_period, self._publish_diagnostics)

    # ------------------------------------------------------------------ the estimator

    def _build(self, urdf_xml: str | None) -> tuple[Estimator, TrainedModel]:
        config = self._config
        # The URDF file's sha256 must be the one the model was trained with; a robot_description
        # string differs in formatting from the file, so only its joint names are checked.
        trained = load_model(config.model_dir, config.joint_names,
                             urdf_sha256(config.urdf) if urdf_xml is None else None)
        return Estimator.from_config(config, trained, urdf=urdf_xml), trained

    def _load(self, urdf_xml: str | None) -> str | None:
        """Build and install a new estimator; the problem as text if that failed (the old one stays)."""
        try:
            estimator, trained = self._build(urdf_xml)
        except _BUILD_ERRORS as exc:
            return _describe(exc)
        if self._estimator is not None:
            self._archived.update(self._estimator.counts)
        self._estimator, self._trained = estimator, trained
        self._residual = trained.residual
        self._compensated = bool(estimator.observer.uses_residual_model)
        self._urdf_in_use = "robot_description topic" if urdf_xml is not None else self._config.urdf
        self._base_frame = _root_link(estimator)
        self._model_problem = ""
        self._reload_problem = None
        self._reset_inputs()
        return None

    def _reset_inputs(self) -> None:
        """Forget pending samples, the last command and the contact state (not the counts)."""
        self._pending = None
        self._command = None
        self._last_stamp = None
        self._last_covariance = None
        self._contact.reset()

    def _urdf_for_reload(self) -> str | None:
        if self._config.urdf == URDF_FROM_TOPIC or self._urdf_in_use == "robot_description topic":
            if self._urdf_xml is None:
                raise ValueError("no URDF received on robot_description yet")
            return self._urdf_xml
        return None

    # ------------------------------------------------------------------ inputs

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds / 1e9

    def _columns_for(self, names: tuple[str, ...]) -> Any:
        """Index of each configured joint in ``names``; None if it names none of them; text if some are missing."""
        position = {name: i for i, name in enumerate(names)}
        missing = [name for name in self._names if name not in position]
        if len(missing) == self._n:
            return None
        if missing:
            return f"joint {missing[0]!r} missing from a message naming {list(names)}"
        return np.array([position[name] for name in self._names], dtype=np.intp)

    def _on_joint_state(self, msg: JointState) -> None:
        key = tuple(msg.name)
        index = self._columns.get(key, _UNSEEN)
        if index is _UNSEEN:
            index = self._columns[key] = self._columns_for(key)
            if len(self._columns) > 64:
                self._columns.clear()
        if index is None:
            self._counts[Drop.OTHER_JOINTS] += 1
            return
        self._received += 1                       # the input rate counts messages about our joints
        if isinstance(index, str):
            self._counts[Drop.MISSING_JOINT] += 1
            self._missing_detail = index
            return
        if self._estimator is None:
            self._counts[Drop.NOT_READY] += 1
            return
        count = len(key)
        position, velocity = msg.position, msg.velocity
        if len(position) != count or len(velocity) != count:
            self._counts[Drop.MALFORMED] += 1
            return
        stamp_msg = msg.header.stamp
        if stamp_msg.sec == 0 and stamp_msg.nanosec == 0 and self._last_stamp is not None:
            # An unstamped driver: use the receive time. (A first stamp of 0 is taken as it is:
            # simulated bags start at 0 s.)
            now = self.get_clock().now()
            stamp_msg, stamp = now.to_msg(), now.nanoseconds / 1e9
        else:
            # Exactly as the bag reader turns header stamps into seconds (integer ns / 1e9).
            stamp = (stamp_msg.sec * 1_000_000_000 + stamp_msg.nanosec) / 1e9
        q = np.asarray(position, dtype=np.float64)[index]
        qd = np.asarray(velocity, dtype=np.float64)[index]
        previous = self._last_stamp
        if previous is not None and stamp <= previous:
            if previous - stamp <= self._config.max_gap:
                self._counts[Drop.OUT_OF_ORDER] += 1
                return
            self._time_jump()
        if self._torque_source == "joint_states_effort":
            effort = msg.effort
            if len(effort) != count:
                self._counts[Drop.NO_EFFORT] += 1
                return
            self._last_stamp = stamp
            self._estimate(stamp, stamp_msg, q, qd, np.asarray(effort, dtype=np.float64)[index])
            return
        if self._pending is not None:
            self._complete_pending()
        self._last_stamp = stamp
        self._pending = (stamp, stamp_msg, q, qd)

    def _time_jump(self) -> None:
        """Stamps went back by more than input.max_gap (bag loop, simulator reset): start over."""
        if self._pending is not None:
            self._complete_pending()
        self._estimator.reset()
        self._reset_inputs()
        self._counts[Drop.TIME_JUMP] += 1

    def _complete_pending(self) -> None:
        """No command followed the pending state: pair it with the newest earlier one if fresh enough."""
        stamp, stamp_msg, q, qd = self._pending
        self._pending = None
        command = self._command
        if command is None or stamp - command[0] > self._config.command_max_age:
            self._counts[Drop.STALE] += 1
            return
        self._estimate(stamp, stamp_msg, q, qd, command[1])

    def _store_command(self, tau_m: np.ndarray) -> None:
        """A command belongs to the newest joint state; estimate that state now if it is waiting."""
        if self._last_stamp is None:
            self._counts[Drop.EARLY_COMMAND] += 1
            return
        self._command = (self._last_stamp, tau_m)
        if self._pending is not None:
            stamp, stamp_msg, q, qd = self._pending
            self._pending = None
            self._estimate(stamp, stamp_msg, q, qd, tau_m)

    def _on_command_array(self, msg: Float64MultiArray) -> None:
        data = msg.data
        dims = msg.layout.dim
        index = None
        if len(dims) == 1 and dims[0].label:
            key = (dims[0].label, len(data))
            index = self._command_columns.get(key, _UNSEEN)
            if index is _UNSEEN:
                labels = tuple(dims[0].label.split(","))
                index = self._command_columns[key] = self._columns_for(labels) if len(labels) == len(data) else False
            if index is None or isinstance(index, str):
                self._counts[Drop.BAD_COMMAND] += 1
                return
        if isinstance(index, np.ndarray):
            tau_m = np.asarray(data, dtype=np.float64)[index]
        elif len(data) == self._n:                # unlabelled: in joint_names order, as ros2_control sends it
            tau_m = np.array(data, dtype=np.float64)
        else:
            self._counts[Drop.BAD_COMMAND] += 1
            return
        self._store_command(tau_m)

    def _on_command_state(self, msg: JointState) -> None:
        key = tuple(msg.name)
        index = self._columns.get(key, _UNSEEN)
        if index is _UNSEEN:
            index = self._columns[key] = self._columns_for(key)
        if index is None or isinstance(index, str) or len(msg.effort) != len(key):
            self._counts[Drop.BAD_COMMAND] += 1
            return
        self._store_command(np.asarray(msg.effort, dtype=np.float64)[index])

    def _on_robot_description(self, msg: String) -> None:
        xml = msg.data
        if not xml.strip() or xml == self._urdf_xml:
            return
        self._urdf_xml = xml
        if self._config.urdf != URDF_FROM_TOPIC and self._estimator is not None:
            if not self._told_about_description:
                self._told_about_description = True
                self.get_logger().info(f"robot_description received; keeping robot_model.urdf {self._config.urdf} "
                                       f"(set robot_model.urdf: {URDF_FROM_TOPIC} to build from the topic)")
            return
        problem = self._load(xml)
        if problem is None:
            self.get_logger().info("estimator built from robot_description")
        else:
            self._model_problem = f"cannot build the estimator from robot_description: {problem}"
            self.get_logger().error(self._model_problem)

    # ------------------------------------------------------------------ outputs

    def _estimate(self, stamp: float, stamp_msg: Any, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> None:
        estimator = self._estimator
        estimate = estimator.step(stamp, q, qd, tau_m)
        if estimate is None:
            status = estimator.status
            if status == Status.GAP_RESET or status == Status.DIVERGED_RESET:
                self._contact.reset()
            return
        tau, covariance = estimate.tau_ext, estimate.tau_cov
        self._pub_torque.publish(JointState(header=Header(stamp=stamp_msg), name=self._names, effort=_doubles(tau)))
        fx, fy, fz, tx, ty, tz = estimate.wrench.tolist()
        wrench = WrenchStamped()
        wrench.header.stamp = stamp_msg
        wrench.header.frame_id = self._base_frame if self._config.wrench_frame == "base" else self._config.ee_frame
        force, torque = wrench.wrench.force, wrench.wrench.torque
        force.x, force.y, force.z, torque.x, torque.y, torque.z = fx, fy, fz, tx, ty, tz
        self._pub_wrench.publish(wrench)
        if covariance is not None:
            stddev = np.sqrt(np.maximum(np.diag(covariance), 0.0))
            self._pub_stddev.publish(Float64MultiArray(layout=self._stddev_layout, data=_doubles(stddev)))
            self._pub_covariance.publish(Float64MultiArray(layout=self._covariance_layout,
                                                           data=_doubles(estimate.wrench_cov.ravel())))
        mean, variance = self._residual.predict(qd)
        test = contact_covariance(covariance, mean, variance, self._compensated)
        self._pub_contact.publish(Bool(data=self._contact.update(stamp, tau, test)))
        self._last_covariance = covariance
        self._published += 1

    # ------------------------------------------------------------------ services

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self._estimator is None:
            response.success = False
            response.message = f"no estimator to reset: {self._model_problem}"
            return response
        self._estimator.reset()
        self._reset_inputs()
        self._counts[Drop.SERVICE_RESET] += 1
        response.success = True
        response.message = "filter reset; the next joint state starts a new estimate"
        return response

    def _on_reload_model(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            urdf_xml = self._urdf_for_reload()
        except ValueError as exc:
            problem = _describe(exc)
        else:
            problem = self._load(urdf_xml)
        if problem is None:
            self._reload_problem = None
            response.success = True
            response.message = f"model reloaded from {self._config.model_dir} (observer {self._config.observer})"
            self.get_logger().info(response.message)
            return response
        kept = "previous model kept" if self._estimator is not None else "no estimator"
        self._reload_problem = problem
        if self._estimator is None:
            self._model_problem = problem
        response.success = False
        response.message = f"reload failed, {kept}: {problem}"
        self.get_logger().warning(response.message)
        return response

    # ------------------------------------------------------------------ diagnostics

    def _all_counts(self) -> Counter[str]:
        counts = Counter(self._counts)
        counts.update(self._archived)
        if self._estimator is not None:
            counts.update(self._estimator.counts)
        return counts

    def _status(self, level: int, name: str, message: str, values: dict[str, Any]) -> DiagnosticStatus:
        return DiagnosticStatus(level=_LEVELS[level], name=f"{self.get_name()}: {name}", message=message,
                                hardware_id=self._config.robot,
                                values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])

    def _model_status(self) -> DiagnosticStatus:
        config = self._config
        values = {"model_dir": config.model_dir, "observer": config.observer, "urdf": self._urdf_in_use or config.urdf,
                  "joints": ",".join(self._names), "torque_source": self._torque_source}
        if self._estimator is None:
            return self._status(2, "model", f"no estimator: {self._model_problem}", values)
        info = self._trained.info
        values.update({"trained_samples": info.get("samples", "?"), "trained_with": info.get("kvark_ros_version", "?"),
                       "residual_compensated": self._compensated})
        if self._reload_problem is not None:
            return self._status(1, "model", f"last reload failed, previous model kept: {self._reload_problem}", values)
        return self._status(0, "model", "model loaded", values)

    def _input_status(self, window: float, received: int, published: int, counts: Counter[str],
                      fresh: dict[str, int]) -> DiagnosticStatus:
        rate_in = received / window if window > 0 else math.nan
        rate_out = published / window if window > 0 else math.nan
        values: dict[str, Any] = {"input_rate_hz": f"{rate_in:.1f}", "output_rate_hz": f"{rate_out:.1f}",
                                  "window_s": f"{window:.3f}", "joint_states_received": self._received,
                                  "estimates_published": self._published}
        values.update({key: f"{total} (+{fresh.get(key, 0)})" for key, total in sorted(counts.items())})
        if self._missing_detail:
            values["last_missing_joint"] = self._missing_detail
        problems = {key: number for key, number in fresh.items() if key not in _NOT_PROBLEMS}
        summary = "; ".join(f"{number} × {key}" for key, number in sorted(problems.items(), key=lambda kv: -kv[1]))
        if received == 0:
            return self._status(1, "input", f"no joint_states in the last {window:.1f} s", values)
        if published < 0.9 * received:
            return self._status(1, "input", f"output {rate_out:.0f} Hz below input {rate_in:.0f} Hz"
                                + (f": {summary}" if summary else ""), values)
        if problems:
            return self._status(1, "input", f"input {rate_in:.0f} Hz, output {rate_out:.0f} Hz; {summary}", values)
        return self._status(0, "input", f"input {rate_in:.0f} Hz, output {rate_out:.0f} Hz", values)

    def _filter_status(self, counts: Counter[str], fresh: dict[str, int]) -> DiagnosticStatus:
        contact = self._contact
        values: dict[str, Any] = {key: counts.get(key, 0) for key in _RESETS}
        values.update({"contact": contact.flag, "contact_statistic": f"{contact.statistic:.3g}",
                       "contact_threshold": f"{contact.threshold:.3g}", "contact_confidence": contact.confidence,
                       "contact_covariance_not_positive_definite": contact.invalid_covariances})
        covariance = self._last_covariance
        healthy = True
        if covariance is None:
            values["P"] = "no estimate yet" if self._estimator is None or self._estimator.observer.reports_covariance \
                else "observer reports no covariance"
        else:
            try:
                np.linalg.cholesky(covariance)
                healthy = bool(np.isfinite(covariance).all())
            except np.linalg.LinAlgError:
                healthy = False
            values["P"] = "finite, positive definite" if healthy else "NOT positive definite"
        if not healthy:
            return self._status(2, "filter", "covariance P is not finite positive definite", values)
        resets = {key: fresh[key] for key in _RESETS if fresh.get(key)}
        if resets.get(Status.DIVERGED_RESET) or resets.get(Drop.TIME_JUMP) or resets.get(Status.GAP_RESET):
            text = "; ".join(f"{number} × {key}" for key, number in resets.items())
            return self._status(1, "filter", text, values)
        return self._status(0, "filter", "contact" if contact.flag else "no contact", values)

    def _publish_diagnostics(self) -> None:
        now = self.get_clock().now()
        seconds = now.nanoseconds / 1e9
        window = seconds - self._diag_time
        received, published = self._received - self._diag_received, self._published - self._diag_published
        counts = self._all_counts()
        fresh = {key: total - self._diag_counts.get(key, 0) for key, total in counts.items()
                 if total > self._diag_counts.get(key, 0)}
        self._diag_time, self._diag_received, self._diag_published = seconds, self._received, self._published
        self._diag_counts = counts
        message = DiagnosticArray()
        message.header.stamp = now.to_msg()
        message.status = [self._model_status(), self._input_status(window, received, published, counts, fresh),
                          self._filter_status(counts, fresh)]
        self._pub_diagnostics.publish(message)


def main(args: list[str] | None = None) -> int:
    """``ros2 run kvark_ros estimator_node``: spin the node until Ctrl-C or shutdown."""
    rclpy.init(args=args)
    try:
        node = EstimatorNode()
    except (ConfigError, ParameterException) as exc:
        print(f"[{NODE_NAME}] error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
