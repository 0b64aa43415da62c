"""The node's estimate topics: one ``Estimate`` in, every output message out. A helper of the node.

Topics (under the node's private namespace ``~/``), every one with a header stamped with the input joint state's
stamp, so message_filters and a bag's alignment pair them by stamp:

- ``external_joint_torque`` (JointState, effort = τ_ext in N·m, tared), every estimate;
- ``external_wrench`` (WrenchStamped): the wrench at the ee_frame origin in ``wrench.frame`` axes, frame_id
  ``wrench.base_frame`` (default the URDF root link) for ``base``, else ``ee_frame``, in ``wrench.convention``'s
  sign (``core.estimation.wrench_output``), every estimate;
- ``contact_state`` (JointState named ``contact``, ``collision``; position 1.0 raised, 0.0 not): the debounced χ²
  contact test and the undebounced per-joint collision test, every estimate;
- ``external_wrench_in_base_frame`` and ``external_wrench_in_ee_frame`` (WrenchStamped), the same wrench in fixed
  axes, as franka_ros2's ``external_wrench_in_base_frame`` / ``…_in_stiffness_frame``;
- ``external_joint_torque_stddev_stamped`` (JointState, effort = σ_j = √P_jj in N·m) and
  ``external_wrench_with_covariance`` (geometry_msgs/TwistWithCovarianceStamped: twist.linear = force,
  twist.angular = torque, covariance = Σ_F row-major, same frame_id and axes as ``external_wrench``);
- deprecated, for one release: ``external_joint_torque_stddev`` and ``external_wrench_covariance``
  (Float64MultiArray) and ``contact`` and ``collision`` (Bool), which have no header.

All but the first three are published only while someone subscribes (``check_subscribers``: every
``SUBSCRIBER_CHECK`` estimates and every ``/diagnostics`` tick, so a new subscriber waits at most that long): a
message nobody reads would still cost its encoding and a middleware call per sample.

Every message is published serialised: a template per topic (``kvark_ros.io.cdr_messages``, made once, and again
for a new frame id) filled with the estimate's numbers, so no message object is built or converted per sample.

QoS (``output.qos``): ``reliable`` (keep last ``input.queue_depth``) or ``sensor_data`` (best effort, volatile, same
depth), for every topic here; ``/diagnostics`` stays reliable (the node's own).
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np
from geometry_msgs.msg import TwistWithCovarianceStamped, WrenchStamped
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray

from kvark_ros.core.estimation.estimator import Estimate
from kvark_ros.core.estimation.wrench_output import WrenchOutput
from kvark_ros.io.cdr_messages import (Template, bool_message, float64_array_template, joint_state_template,
                                       wrench_template, wrench_with_covariance_template)

WRENCH_AXES = ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z")
FLAGS = ("contact", "collision")     # the names of contact_state's two positions
SUBSCRIBER_CHECK = 100               # estimates between checks whether anyone subscribes to the optional topics
Stamp = tuple[int, int]              # a header stamp: (sec, nanosec)
# Topic -> message type of every estimate topic, the always-published first; DEPRECATED have no header.
TOPICS: dict[str, type] = {
    "external_joint_torque": JointState, "external_wrench": WrenchStamped, "contact_state": JointState,
    "external_wrench_in_base_frame": WrenchStamped, "external_wrench_in_ee_frame": WrenchStamped,
    "external_joint_torque_stddev_stamped": JointState, "external_wrench_with_covariance": TwistWithCovarianceStamped,
    "external_joint_torque_stddev": Float64MultiArray, "external_wrench_covariance": Float64MultiArray,
    "contact": Bool, "collision": Bool}
ALWAYS = ("external_joint_torque", "external_wrench", "contact_state")
DEPRECATED = ("external_joint_torque_stddev", "external_wrench_covariance", "contact", "collision")


def qos_profile(kind: str, depth: int) -> QoSProfile:
    """``reliable`` (the estimate topics' default) or ``sensor_data`` (best effort, volatile: the inputs, and the
    estimate topics with ``output.qos: sensor_data``), keep last ``depth``."""
    if kind == "sensor_data":
        return QoSProfile(history=qos_profile_sensor_data.history, depth=depth,
                          reliability=qos_profile_sensor_data.reliability,
                          durability=qos_profile_sensor_data.durability)
    return QoSProfile(depth=depth)


class EstimatePublishers:
    """The publishers of the estimate topics (module docstring) on ``node``, for ``joint_names``."""

    def __init__(self, node: Node, joint_names: tuple[str, ...], qos: QoSProfile) -> None:
        self.names = list(joint_names)
        n = len(self.names)
        self.published = 0
        # No default QoS-event handlers on these publishers: they only log, and each would be a waitable that
        # rclpy's executor adds to its wait set at every wake-up.
        events = PublisherEventCallbacks(use_default_callbacks=False)
        self.topics = {topic: node.create_publisher(kind, f"~/{topic}", qos, event_callbacks=events)
                       for topic, kind in TOPICS.items()}
        self.wanted = dict.fromkeys(TOPICS, False)
        self.wanted.update(dict.fromkeys(ALWAYS, True))
        self._publish: dict[str, Callable[[bytes], None]] = {topic: publisher.publish
                                                             for topic, publisher in self.topics.items()}
        self._torque = joint_state_template(self.names)
        flags = joint_state_template(FLAGS, field="position")
        # (contact, collision) -> contact_state with those positions, stamped per sample
        self._flags = {(contact, collision): replace(flags, raw=flags.fill({"position": (float(contact),
                                                                                         float(collision))}))
                       for contact in (False, True) for collision in (False, True)}
        self._stddev = float64_array_template([(",".join(self.names), n, n)], n)
        self._covariance = float64_array_template([("row: " + ",".join(WRENCH_AXES), 6, 36),
                                                   ("column: " + ",".join(WRENCH_AXES), 6, 6)], 36)
        self._bools = (bool_message(False), bool_message(True))
        # frame id -> template, made at a frame id's first use
        self._wrenches: dict[str, Template] = {}
        self._with_covariance: dict[str, Template] = {}
        self._uncertainty = self._fixed_axes = False     # whether any of them is wanted (check_subscribers)

    @staticmethod
    def _stamped(templates: dict[str, Template], make: Callable[[str], Template], frame_id: str) -> Template:
        template = templates.get(frame_id)
        if template is None:
            template = templates[frame_id] = make(frame_id)
        return template

    def _wrench(self, stamp: Stamp, frame_id: str, values: np.ndarray) -> bytes:
        """A WrenchStamped in ``frame_id``: ``values`` (6,) N, N·m."""
        return self._stamped(self._wrenches, wrench_template, frame_id).stamped(stamp[0], stamp[1], "wrench", values)

    def publish(self, estimate: Estimate, stamp: Stamp, output: WrenchOutput) -> None:
        """Every wanted topic's message of one estimate, stamped with the input's stamp; ``output`` gives the
        wrench's frame ids, axes and sign."""
        publish = self._publish
        sec, nanosec = stamp
        publish["external_joint_torque"](self._torque.stamped(sec, nanosec, "effort", estimate.tau_ext))
        frame_id, values = output.published(estimate)
        wrench = self._wrench(stamp, frame_id, values)
        publish["external_wrench"](wrench)
        flags = (bool(estimate.contact), bool(estimate.collision))
        publish["contact_state"](self._flags[flags].stamped(sec, nanosec))
        if self._fixed_axes:
            self._publish_fixed_axes(estimate, stamp, wrench, output)
        if self._uncertainty and estimate.tau_cov is not None:
            self._publish_uncertainty(estimate, stamp, frame_id, values, output)
        if self.wanted["contact"]:
            publish["contact"](self._bools[flags[0]])
        if self.wanted["collision"]:
            publish["collision"](self._bools[flags[1]])
        self.published += 1
        if self.published % SUBSCRIBER_CHECK == 0:
            self.check_subscribers()

    def _publish_fixed_axes(self, estimate: Estimate, stamp: Stamp, wrench: bytes, output: WrenchOutput) -> None:
        """The wrench in base and in ee_frame axes, on the topics someone subscribes to (``wrench``: the message of
        ``external_wrench``, in ``wrench.frame`` axes)."""
        for axes, topic in (("base", "external_wrench_in_base_frame"), ("end_effector", "external_wrench_in_ee_frame")):
            if self.wanted[topic]:
                self._publish[topic](wrench if axes == estimate.wrench_frame else
                                     self._wrench(stamp, *output.in_axes(estimate, axes)))

    def _publish_uncertainty(self, estimate: Estimate, stamp: Stamp, frame_id: str, wrench: np.ndarray,
                             output: WrenchOutput) -> None:
        """σ of τ_ext and the wrench with its covariance, on the topics someone subscribes to."""
        publish, wanted = self._publish, self.wanted
        stamped, arrays = wanted["external_joint_torque_stddev_stamped"], wanted["external_joint_torque_stddev"]
        if stamped or arrays:
            stddev = np.sqrt(np.maximum(np.diag(estimate.tau_cov), 0.0))
            if stamped:
                publish["external_joint_torque_stddev_stamped"](self._torque.stamped(stamp[0], stamp[1], "effort",
                                                                                     stddev))
            if arrays:
                publish["external_joint_torque_stddev"](self._stddev.fill({"data": stddev}))
        with_covariance, arrays = wanted["external_wrench_with_covariance"], wanted["external_wrench_covariance"]
        if with_covariance or arrays:
            covariance = output.covariance(estimate).ravel()
            if with_covariance:
                publish["external_wrench_with_covariance"](self._stamped(
                    self._with_covariance, wrench_with_covariance_template, frame_id).fill(
                    {"sec": stamp[0], "nanosec": stamp[1], "wrench": wrench, "covariance": covariance}))
            if arrays:
                publish["external_wrench_covariance"](self._covariance.fill({"data": covariance}))

    def check_subscribers(self) -> None:
        """From now on publish each optional topic only if someone subscribes to it."""
        for topic, publisher in self.topics.items():
            if topic not in ALWAYS:
                self.wanted[topic] = publisher.get_subscription_count() > 0
        wanted = self.wanted
        self._fixed_axes = wanted["external_wrench_in_base_frame"] or wanted["external_wrench_in_ee_frame"]
        self._uncertainty = any(wanted[topic] for topic in ("external_joint_torque_stddev_stamped",
                                                            "external_joint_torque_stddev",
                                                            "external_wrench_with_covariance",
                                                            "external_wrench_covariance"))
