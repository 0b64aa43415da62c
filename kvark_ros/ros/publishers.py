"""The node's estimate topics: one ``Estimate`` in, every output message out. A helper of the node.

Topics (under the node's private namespace ``~/``), one message each per estimate unless noted:

- ``external_joint_torque`` (JointState, effort = τ_ext in N·m, tared);
- ``external_wrench`` (WrenchStamped): the wrench at the ee_frame origin in ``wrench.frame`` axes
  (frame_id the URDF root link for ``base``, else ``ee_frame``), as in earlier releases and in
  ``kvark replay``'s bags;
- ``external_wrench_in_base_frame`` (frame_id = the root link: base axes) and
  ``external_wrench_in_ee_frame`` (frame_id = ``ee_frame``: its axes), the same wrench in fixed axes,
  as franka_ros2's ``external_wrench_in_base_frame`` / ``…_in_stiffness_frame``; the one in
  ``wrench.frame`` axes is the ``external_wrench`` message itself;
- ``external_joint_torque_stddev`` and ``external_wrench_covariance`` (Float64MultiArray, the latter in
  ``wrench.frame`` axes);
- ``contact`` (the debounced χ² test) and ``collision`` (the undebounced per-joint test), Bool.

The two fixed-axes wrench topics and the uncertainty topics are published only while someone
subscribes (``check_subscribers``: every ``SUBSCRIBER_CHECK`` estimates and every ``/diagnostics``
tick, so a new subscriber waits at most that long): a message nobody reads would still cost its encoding
and a middleware call per sample.

Every message is published serialised: a template per topic (``kvark_ros.io.cdr_messages``, made once, and
again for a new frame id) filled with the estimate's numbers, so no message object is built or converted per
sample.

QoS (``output.qos``): ``reliable`` (keep last ``input.queue_depth``) or ``sensor_data`` (best effort,
volatile, same depth), for every topic here; ``/diagnostics`` stays reliable (the node's own).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from geometry_msgs.msg import WrenchStamped
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray

from kvark_ros.core.estimation.estimator import Estimate
from kvark_ros.io.cdr_messages import (Template, bool_message, float64_array_template, joint_state_template,
                                       wrench_template)

WRENCH_AXES = ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z")
SUBSCRIBER_CHECK = 100          # estimates between checks whether anyone subscribes to the uncertainty topics
Stamp = tuple[int, int]         # a header stamp: (sec, nanosec)


def qos_profile(kind: str, depth: int) -> QoSProfile:
    """``reliable`` (the estimate topics' default) or ``sensor_data`` (best effort, volatile: the inputs, and the
    estimate topics with ``output.qos: sensor_data``), keep last ``depth``."""
    if kind == "sensor_data":
        return QoSProfile(history=qos_profile_sensor_data.history, depth=depth,
                          reliability=qos_profile_sensor_data.reliability,
                          durability=qos_profile_sensor_data.durability)
    return QoSProfile(depth=depth)


class EstimatePublishers:
    """The publishers of the estimate topics (module docstring) on ``node``, for ``joint_names`` and ``ee_frame``."""

    def __init__(self, node: Node, joint_names: tuple[str, ...], ee_frame: str, qos: QoSProfile) -> None:
        self.names = list(joint_names)
        n = len(self.names)
        self.uncertainty_wanted = self.base_wanted = self.ee_wanted = False
        self.published = 0
        # No default QoS-event handlers on these eight publishers: they only log, and each would be a waitable
        # that rclpy's executor adds to its wait set at every wake-up.
        events = PublisherEventCallbacks(use_default_callbacks=False)

        def create(kind: type, topic: str, profile: QoSProfile) -> Any:
            return node.create_publisher(kind, topic, profile, event_callbacks=events)

        self.torque = create(JointState, "~/external_joint_torque", qos)
        self.wrench = create(WrenchStamped, "~/external_wrench", qos)
        self.wrench_base = create(WrenchStamped, "~/external_wrench_in_base_frame", qos)
        self.wrench_ee = create(WrenchStamped, "~/external_wrench_in_ee_frame", qos)
        self.stddev = create(Float64MultiArray, "~/external_joint_torque_stddev", qos)
        self.covariance = create(Float64MultiArray, "~/external_wrench_covariance", qos)
        self.contact = create(Bool, "~/contact", qos)
        self.collision = create(Bool, "~/collision", qos)
        self._torque = joint_state_template(self.names)
        self._stddev = float64_array_template([(",".join(self.names), n, n)], n)
        self._covariance = float64_array_template([("row: " + ",".join(WRENCH_AXES), 6, 36),
                                                   ("column: " + ",".join(WRENCH_AXES), 6, 6)], 36)
        # frame id -> template: ee_frame's now, the root link's (known once a model is built) at its first use
        self._wrenches: dict[str, Template] = {ee_frame: wrench_template(ee_frame)}
        self._flags = (bool_message(False), bool_message(True))

    def _wrench(self, stamp: Stamp, frame_id: str, values: np.ndarray) -> bytes:
        """A WrenchStamped in ``frame_id``: ``values`` (6,) N, N·m."""
        template = self._wrenches.get(frame_id)
        if template is None:
            template = self._wrenches[frame_id] = wrench_template(frame_id)
        return template.fill({"sec": stamp[0], "nanosec": stamp[1], "wrench": values})

    def publish(self, estimate: Estimate, stamp: Stamp, base_frame: str, ee_frame: str) -> None:
        """Every topic's message of one estimate, stamped with the input's stamp."""
        self.torque.publish(self._torque.fill({"sec": stamp[0], "nanosec": stamp[1], "effort": estimate.tau_ext}))
        axes = estimate.wrench_frame
        wrench = self._wrench(stamp, base_frame if axes == "base" else ee_frame, estimate.wrench)
        self.wrench.publish(wrench)
        if self.base_wanted:
            self.wrench_base.publish(wrench if axes == "base" else
                                     self._wrench(stamp, base_frame, estimate.wrench_in("base")))
        if self.ee_wanted:
            self.wrench_ee.publish(wrench if axes == "end_effector" else
                                   self._wrench(stamp, ee_frame, estimate.wrench_in("end_effector")))
        if estimate.tau_cov is not None and self.uncertainty_wanted:
            stddev = np.sqrt(np.maximum(np.diag(estimate.tau_cov), 0.0))
            self.stddev.publish(self._stddev.fill({"data": stddev}))
            self.covariance.publish(self._covariance.fill({"data": estimate.wrench_cov.ravel()}))
        self.contact.publish(self._flags[bool(estimate.contact)])
        self.collision.publish(self._flags[bool(estimate.collision)])
        self.published += 1
        if self.published % SUBSCRIBER_CHECK == 0:
            self.check_subscribers()

    def check_subscribers(self) -> None:
        """From now on publish the uncertainty and the fixed-axes wrench topics only if someone subscribes."""
        self.uncertainty_wanted = (self.stddev.get_subscription_count() > 0
                                   or self.covariance.get_subscription_count() > 0)
        self.base_wanted = self.wrench_base.get_subscription_count() > 0
        self.ee_wanted = self.wrench_ee.get_subscription_count() > 0
