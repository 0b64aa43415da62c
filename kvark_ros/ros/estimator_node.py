"""ROS 2 node ``kvark_estimator``: the ``Estimator`` of ``kvark replay``, live.

Run ``ros2 launch kvark_ros estimator.launch.py`` (or ``ros2 run kvark_ros estimator_node
--ros-args --params-file config/panda.yaml``). A thin adapter: joint names are matched and states
paired with commands by ``kvark_ros.core.estimation.pairing`` and every number comes from
``kvark_ros.core.estimation.estimator.Estimator.step``, the same code ``kvark replay`` runs over a bag.

Topics, services and parameters: docs/ros.md. In: ``input.joint_states_topic``, ``input.effort_commands_topic``
(Float64MultiArray, or JointState with ``effort_commands_joint_state``), ``robot_description``; out: the stamped
estimate topics of ``kvark_ros.ros.publishers`` (QoS ``output.qos``) and ``/diagnostics`` (model, input, filter,
wrench, tare); services ``~/reset`` (also clears the tare), ``~/reload_model`` and ``~/tare`` (starts averaging
τ_ext at rest, ``core.estimation.tare``, and returns at once; its outcome is on ``/diagnostics``).

Pairing (``core.estimation.pairing``): each message is ordered by when it was published (its message info's
source timestamp, else the receive time), so an executor that falls behind still pairs command k with state k;
stamped commands by their header stamps. With ``joint_states_effort`` the effort of ``joint_states`` is τ_m and
nothing is paired. A zero stamp (a driver that never fills it) becomes the receive time, except the first one
after start or a reset (simulated bags start at 0 s).

Parameters (``kvark_ros.ros.parameters``): relative paths resolve against the folder of the ``--params-file``
that set them, as ``kvark`` resolves them against the config file's, else against the package's config folder.
τ_m read from a message goes through ``input.effort_scale``/``effort_offset`` (``core.estimation.inputs``, the
rule every command applies to a bag); the wrench through ``core.estimation.wrench_output`` (frame, sign). A
run-time payload goes through ``Estimator.configure`` between two samples; a non-physical one is refused.

Robustness: every rejected message is counted per reason on ``/diagnostics``; nothing is logged per message,
nothing non-finite is published. Lost input is measured from gaps in the joint-state stamps.

Threads (``kvark_ros.ros.input_loop``): ``main`` takes the inputs (raw CDR, decoded by layout:
``kvark_ros.io.cdr_messages``) on a wait loop of its own, every ready message at each wake, in publication
order, and estimates and publishes (serialised) on the same thread. Services, parameters, ``/diagnostics`` and
``robot_description`` run on rclpy's executor on a second thread, changing the node's state only under
``lock``: between two batches of samples. ``~/reload_model`` and a new ``robot_description`` build the
estimator on a worker thread, then swap it in, continuing the old filter's state when joints and observer
match (reloading the same model changes no output).
"""
from __future__ import annotations

import math
import sys
import threading
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger

from kvark_ros.core.config import NODE_NAME, ROBOT_DESCRIPTION, ConfigError
from kvark_ros.core.estimation.estimator import Estimate, Estimator
from kvark_ros.core.estimation.inputs import EffortCalibration
from kvark_ros.core.estimation.pairing import RESET, JointColumns, Reject, Sample, StreamPairer, stamp_seconds
from kvark_ros.core.estimation.tare import TareError
from kvark_ros.core.estimation.wrench_output import WrenchOutput
from kvark_ros.io.cdr_messages import Decoder
from kvark_ros.io.common import FLOAT64_ARRAY, JOINT_STATE
from kvark_ros.ros import input_loop, parameters
from kvark_ros.ros.builds import SWITCH_INTERVAL, Built, build, build_off_path, one_blas_thread
from kvark_ros.ros.diagnostics import NOT_READY, SERVICE_RESET, StatusBuilder, Windows
from kvark_ros.ros.input_loop import InputGroup, locked, publication_ns
from kvark_ros.ros.publishers import SUBSCRIBER_CHECK, EstimatePublishers, Stamp, qos_profile

URDF_FROM_TOPIC = ROBOT_DESCRIPTION
__all__ = ["EstimatorNode", "main", "Drop", "SUBSCRIBER_CHECK", "ConfigError"]


class Drop(Reject):
    """Why a message gave no estimate: the pairing's reasons and the node's own."""

    NOT_READY = NOT_READY
    SERVICE_RESET = SERVICE_RESET


class EstimatorNode(Node):
    """The ``kvark_estimator`` node (module docstring). ``parameter_files``: the ``--params-file`` files of its command
    line (relative paths resolve against the one that set them); ``kwargs`` go to ``rclpy.node.Node``."""

    def __init__(self, parameter_files: Sequence[Path] = (), **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.lock = threading.Lock()                 # held by the input thread per batch, by the others per change
        parameters.declare(self)
        self._path_folders = parameters.folders_of(self, tuple(parameter_files))
        self._config = config = parameters.read_config(self, self._path_folders)
        self._torque_source = config.input.torque_source
        effort = EffortCalibration.from_config(config)
        self._effort = None if effort.identity else effort      # τ_m = scale · value + offset, if not the value
        self._n = config.n_joints
        self._columns = JointColumns(config.joint_names)
        self._counts: Counter[str] = Counter()      # the node's and the pairing's reasons
        self._pairer = StreamPairer(config.input.command_max_age, config.input.max_gap, counts=self._counts)
        self._stamped_commands = self._torque_source == "effort_commands_joint_state"
        self._estimator: Estimator | None = None
        self._wrench_output: WrenchOutput | None = None   # the estimator's wrench frames, axes and sign
        self._urdf_xml: str | None = None            # newest robot_description received
        self._urdf_in_use = ""
        self._model_problem = "model not loaded yet"
        self._reload_problem: str | None = None
        self._told_about_description = False
        self._missing_detail = ""
        self._archived: Counter[str] = Counter()     # Status counts of estimators replaced by a reload
        self._received = 0
        self._last: Estimate | None = None          # newest estimate, for /diagnostics
        self._windows = Windows(self.get_clock().now().nanoseconds / 1e9)
        self._statuses = StatusBuilder(self.get_fully_qualified_name(), config.robot)

        sensor_qos = qos_profile("sensor_data", config.input.queue_depth)
        self._outputs = EstimatePublishers(self, config.joint_names,
                                           qos_profile(config.output.qos, config.input.queue_depth))
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))
        # The inputs arrive as CDR bytes (module docstring: Threads), with no QoS event handlers (input_loop).
        self.input_group = InputGroup()
        self._states = Decoder(JOINT_STATE)
        self._state_fields = ("sec", "nanosec", "position", "velocity") + (
            ("effort",) if self._torque_source == "joint_states_effort" else ())
        self._commands = Decoder(FLOAT64_ARRAY if self._torque_source == "effort_commands" else JOINT_STATE)
        inputs = [(JointState, config.input.joint_states_topic, self._joint_state)]
        if self._torque_source != "joint_states_effort":
            inputs.append((Float64MultiArray, config.input.effort_commands_topic, self._command_array)
                          if self._torque_source == "effort_commands" else
                          (JointState, config.input.effort_commands_topic, self._command_state))
        no_events = SubscriptionEventCallbacks(use_default_callbacks=False)
        self.inputs = [self.create_subscription(kind, topic, callback, sensor_qos, callback_group=self.input_group,
                                                event_callbacks=no_events, raw=True)
                       for kind, topic, callback in inputs]
        # The model builds (coroutines awaiting a worker thread) in a group of their own: a callback group is busy
        # until its coroutine returns, so in the node's default group a build would hold up the services.
        builds = MutuallyExclusiveCallbackGroup()
        self.create_subscription(String, "robot_description", self._on_robot_description,
                                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL),
                                 callback_group=builds)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_service(Trigger, "~/reload_model", self._on_reload_model, callback_group=builds)
        self.create_service(Trigger, "~/tare", self._on_tare)
        self._timer = self.create_timer(config.diagnostics.period, self._publish_diagnostics)
        self.add_on_set_parameters_callback(lambda changed: parameters.check_update(self, changed))
        self.add_post_set_parameters_callback(self._apply_parameters)

        if config.urdf == URDF_FROM_TOPIC:
            self._model_problem = "waiting for the URDF on robot_description"
            self.get_logger().info("waiting for robot_description to build the estimator")
        else:
            problem = self._swap_in(build(self._config, None), None)
            if problem is not None:
                self._model_problem = problem
                self.get_logger().error(f"no estimator: {problem} (fix it, then call ~/reload_model)")
        self._outputs.check_subscribers()
        self.get_logger().info(
            f"observer {config.observer}, {self._n} joints, model {config.model_dir}, "
            f"torque from {self._torque_source}; outputs under {self.get_fully_qualified_name()}/")

    @locked
    def _apply_parameters(self, changed: list[Parameter]) -> None:
        """Post-set callback: the config with the new run-time values, applied to everything that uses them
        (a payload through ``Estimator.configure``: the model changes between two samples)."""
        names = [p.name for p in changed if p.name in parameters.RUNTIME_KEYS]
        if not names:
            return
        config = parameters.read_config(self, self._path_folders)   # read-only keys: refused by the on-set callback
        previous, self._config = self._config, config
        if self._estimator is not None:
            self._estimator.configure(config)
            self._wrench_output.configure(config)
        self._pairer.command_max_age, self._pairer.max_gap = config.input.command_max_age, config.input.max_gap
        if config.diagnostics.period != previous.diagnostics.period:
            self.destroy_timer(self._timer)
            self._timer = self.create_timer(config.diagnostics.period, self._publish_diagnostics)
        self.get_logger().info("parameters changed: " + ", ".join(
            f"{n}={self.get_parameter(n).value}" for n in names))

    @locked
    def _swap_in(self, new: Built | str, urdf_xml: str | None) -> str | None:
        """Put a built estimator in use between two samples, continuing the old one's filter state where joints
        and observer match; ``new`` a problem: return it (the old estimator stays)."""
        if isinstance(new, str):
            return new
        built, output = new
        old = self._estimator
        if old is not None:
            self._archived.update(old.counts)
            try:
                built.continue_from(old)
            except ValueError:
                self._pairer.reset()              # another observer or other joints: start over
        if built.config != self._config:
            built.configure(self._config)         # run-time parameters set while it was being built
            output.configure(self._config)
        self._estimator, self._wrench_output = built, output
        self._urdf_in_use = "robot_description topic" if urdf_xml is not None else self._config.urdf
        self._model_problem = ""
        self._reload_problem = None
        return None

    def _urdf_for_reload(self) -> str | None:
        if self._config.urdf == URDF_FROM_TOPIC or self._urdf_in_use == "robot_description topic":
            if self._urdf_xml is None:
                raise ValueError("no URDF received on robot_description yet")
            return self._urdf_xml
        return None

    def _order_key(self, info: dict, stamp: float | None) -> float:
        """When the message was published (s): with stamped commands the header stamp (an unstamped one is
        at the newest state's), else the middleware's source timestamp (or receive time, or now)."""
        if self._stamped_commands and stamp is not None:
            return stamp if stamp > 0.0 or self._pairer.last_stamp is None else self._pairer.last_stamp
        published = publication_ns(info)
        return (self.get_clock().now().nanoseconds if published is None else published) / 1e9

    def _decoded(self, decoder: Decoder, raw: bytes, reason: str, names: tuple[str, ...]) -> tuple[Any, dict] | None:
        """(first message of its layout, the numbers ``names``) of ``raw``; None for bytes that are no message
        (``reason``)."""
        try:
            return decoder.decode(raw, names)
        except ValueError:
            self._counts[reason] += 1
            return None

    def _joint_state(self, raw: bytes, info: dict) -> None:
        if (decoded := self._decoded(self._states, raw, Drop.MALFORMED, self._state_fields)) is None:
            return
        message, numbers = decoded
        index = self._columns.index(message.name)
        if index is None:
            self._counts[Drop.OTHER_JOINTS] += 1
            return
        self._received += 1                       # the input rate counts messages about our joints
        if isinstance(index, str):
            self._counts[index] += 1
            self._missing_detail = self._columns.problem
            return
        if self._estimator is None:
            self._counts[Drop.NOT_READY] += 1
            return
        count = len(message.name)
        position, velocity = numbers["position"], numbers["velocity"]
        if len(position) != count or len(velocity) != count:
            self._counts[Drop.MALFORMED] += 1
            return
        tag: Stamp = (int(numbers["sec"][0]), int(numbers["nanosec"][0]))
        if tag == (0, 0) and self._pairer.last_stamp is not None:
            now = self.get_clock().now().nanoseconds          # an unstamped driver: the receive time
            tag, stamp = divmod(now, 1_000_000_000), now / 1e9
        else:
            stamp = stamp_seconds(*tag)
        q, qd = position[index], velocity[index]
        if self._torque_source == "joint_states_effort":
            effort = numbers["effort"]
            tau_m = self._tau_m(effort[index]) if len(effort) == count else None
            self._estimate_all(self._pairer.stamped_state(Sample(stamp, q, qd, tau_m, tag)))
        else:
            key = self._order_key(info, stamp)
            self._estimate_all(self._pairer.state(key, Sample(stamp, q, qd, None, tag)))

    def _command_array(self, raw: bytes, info: dict) -> None:
        if (decoded := self._decoded(self._commands, raw, Drop.BAD_COMMAND, ("data",))) is None:
            return
        data, dims = decoded[1]["data"], decoded[0].layout.dim
        index = None
        if len(dims) == 1 and dims[0].label:
            labels = dims[0].label.split(",")
            if len(labels) == len(data):
                index = self._columns.index(labels)
                if not isinstance(index, np.ndarray):
                    self._counts[Drop.BAD_COMMAND] += 1
                    return
        if index is not None:
            tau_m = data[index]
        elif len(data) == self._n:                # unlabelled: in joint_names order, as ros2_control sends it
            tau_m = data.copy()
        else:
            self._counts[Drop.BAD_COMMAND] += 1
            return
        self._estimate_all(self._pairer.command(self._order_key(info, None), self._tau_m(tau_m)))

    def _command_state(self, raw: bytes, info: dict) -> None:
        if (decoded := self._decoded(self._commands, raw, Drop.BAD_COMMAND, ("sec", "nanosec", "effort"))) is None:
            return
        message, numbers = decoded
        index = self._columns.index(message.name)
        if not isinstance(index, np.ndarray) or len(numbers["effort"]) != len(message.name):
            self._counts[Drop.BAD_COMMAND] += 1
            return
        key = self._order_key(info, stamp_seconds(int(numbers["sec"][0]), int(numbers["nanosec"][0])))
        self._estimate_all(self._pairer.command(key, self._tau_m(numbers["effort"][index])))

    def _tau_m(self, values: np.ndarray) -> np.ndarray:
        """τ_m (n,) N·m of the effort values a message holds: ``input.effort_scale``/``effort_offset`` applied."""
        return values if self._effort is None else self._effort.apply(values)

    async def _on_robot_description(self, msg: String) -> None:
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
        problem = self._swap_in(await build_off_path(self.executor, self._config, xml), xml)
        if problem is None:
            self.get_logger().info("estimator built from robot_description")
        else:
            self._model_problem = f"cannot build the estimator from robot_description: {problem}"
            self.get_logger().error(self._model_problem)

    def _estimate_all(self, samples: list) -> None:
        """Estimate and publish every paired sample in order; a RESET item restarts the filter first."""
        for sample in samples:
            if sample is RESET:
                self._estimator.reset()
            else:
                estimate = self._estimator.step(sample.stamp, sample.q, sample.qd, sample.tau_m)
                if estimate is not None:
                    self._outputs.publish(estimate, sample.tag, self._wrench_output)
                    self._last = estimate

    @locked
    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self._estimator is None:
            response.success = False
            response.message = f"no estimator to reset: {self._model_problem}"
            return response
        self._estimator.reset()
        self._estimator.clear_tare()
        self._pairer.reset()
        self._counts[Drop.SERVICE_RESET] += 1
        response.success = True
        response.message = "filter reset and tare cleared; the next joint state starts a new estimate"
        return response

    @locked
    def _on_tare(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Start averaging τ_ext at rest and return (module docstring); refused without an estimator or in motion."""
        response.success = False
        if self._estimator is None:
            response.message = f"no estimator to tare: {self._model_problem}"
            return response
        try:
            self._estimator.start_tare()
        except TareError as exc:
            response.message = f"tare refused: {exc}"
        else:
            response.success = True
            response.message = (f"averaging τ_ext for {self._config.tare.duration:g} s at rest, then subtracting it; "
                                f"progress and offset on /diagnostics ({self.get_fully_qualified_name()}: tare)")
        self.get_logger().info(response.message)
        return response

    async def _on_reload_model(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Build the model off the input path, swap it in between two samples, then reply (module docstring)."""
        try:
            urdf_xml = self._urdf_for_reload()
        except ValueError as exc:
            problem: str | None = str(exc)
        else:
            problem = self._swap_in(await build_off_path(self.executor, self._config, urdf_xml), urdf_xml)
        if problem is None:
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

    def _all_counts(self) -> Counter[str]:
        """Every reason counted since start: the node's, the pairing's and every estimator's."""
        counts = Counter(self._counts)
        counts.update(self._archived)
        if self._estimator is not None:
            counts.update(self._estimator.counts)
        return counts

    @locked
    def _publish_diagnostics(self) -> None:
        self._outputs.check_subscribers()
        now = self.get_clock().now()
        estimator, lost, period = self._estimator, self._pairer.lost, self._pairer.period
        window = self._windows.next(now.nanoseconds / 1e9, self._received, self._outputs.published,
                                    self._all_counts(), lost, self._config.diagnostics.max_loss)
        reporting = estimator is None or estimator.observer.reports_covariance
        message = DiagnosticArray()
        message.header.stamp = now.to_msg()
        message.status = [
            self._statuses.model(self._config, self._urdf_in_use, estimator, self._model_problem,
                                 self._reload_problem, math.nan if period is None else 1.0 / period),
            self._statuses.input(window, {"joint_states_received": self._received, "joint_states_lost": lost,
                                          "estimates_published": self._outputs.published}, self._missing_detail),
            self._statuses.filter(window, estimator, None if self._last is None else self._last.tau_cov,
                                  "no estimate yet" if reporting else "observer reports no covariance"),
            self._statuses.wrench(self._last, estimator),
            self._statuses.tare(estimator.tare if estimator is not None else None)]
        self._pub_diagnostics.publish(message)


def main(args: list[str] | None = None) -> int:
    """``ros2 run kvark_ros estimator_node``: spin the node until Ctrl-C or shutdown."""
    one_blas_thread()
    rclpy.init(args=args)
    try:
        node = EstimatorNode(parameters.parameter_files(sys.argv if args is None else args))
    except (ConfigError, ParameterException) as exc:
        print(f"[{NODE_NAME}] error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    except (KeyboardInterrupt, RuntimeError):
        # Ctrl-C or SIGTERM while the node starts (loading the model, compiling its kernels on a cold cache): rclpy's
        # handler has shut the context down and the next rcl call raises RCLError. A stop, not a fault.
        if rclpy.ok():
            rclpy.try_shutdown()
            raise
        return 0
    sys.setswitchinterval(SWITCH_INTERVAL)
    try:
        input_loop.spin(node)                     # inputs here, services on a thread of their own (module docstring)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # rclpy's signal handler shuts the context down from its own thread; a wait set built at that moment
        # raises RCLError "the given context is not valid" (ros2/rclpy#398): a SIGTERM or Ctrl-C, not a fault.
        if rclpy.ok():
            raise
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
