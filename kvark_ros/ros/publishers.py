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
tick, so a new subscriber waits at most that long): a message built for nobody costs ~20 µs per
sample in Python.

QoS (``output.qos``): ``reliable`` (keep last ``input.queue_depth``) or ``sensor_data`` (best effort,
volatile, same depth), for every topic here; ``/diagnostics`` stays reliable (the node's own).
"""
from __future__ import annotations

import array
from typing import Any

import numpy as np
from geometry_msgs.msg import WrenchStamped
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray, MultiArrayDimension, MultiArrayLayout

from kvark_ros.core.estimation.estimator import Estimate

WRENCH_AXES = ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z")
SUBSCRIBER_CHECK = 100          # estimates between checks whether anyone subscribes to the uncertainty topics


def _doubles(values: np.ndarray) -> array.array:
    """float64[] message field from a numpy array (rclpy takes array.array('d'), not ndarray)."""
    return array.array("d", np.ascontiguousarray(values, dtype=np.float64).tobytes())


def qos_profile(kind: str, depth: int) -> QoSProfile:
    """``reliable`` (the estimate topics' default) or ``sensor_data`` (best effort, volatile: the inputs, and the
    estimate topics with ``output.qos: sensor_data``), keep last ``depth``."""
    if kind == "sensor_data":
        return QoSProfile(history=qos_profile_sensor_data.history, depth=depth,
                          reliability=qos_profile_sensor_data.reliability,
                          durability=qos_profile_sensor_data.durability)
    return QoSProfile(depth=depth)


def _wrench(message: WrenchStamped, stamp_msg: Any, frame_id: str, values: np.ndarray) -> WrenchStamped:
    """``message`` (reused: rclpy serializes at ``publish``) filled with one wrench (6,) N, N·m."""
    message.header.stamp = stamp_msg
    message.header.frame_id = frame_id
    force, torque = message.wrench.force, message.wrench.torque
    force.x, force.y, force.z, torque.x, torque.y, torque.z = values.tolist()
    return message


class EstimatePublishers:
    """The publishers of the estimate topics (module docstring) on ``node``, for ``joint_names``."""

    def __init__(self, node: Node, joint_names: tuple[str, ...], qos: QoSProfile) -> None:
        self.names = list(joint_names)
        n = len(self.names)
        self.uncertainty_wanted = self.base_wanted = self.ee_wanted = False
        self.published = 0
        self._stddev_layout = MultiArrayLayout(dim=[MultiArrayDimension(label=",".join(self.names), size=n,
                                                                         stride=n)])
        self._covariance_layout = MultiArrayLayout(dim=[
            MultiArrayDimension(label="row: " + ",".join(WRENCH_AXES), size=6, stride=36),
            MultiArrayDimension(label="column: " + ",".join(WRENCH_AXES), size=6, stride=6)])
        # No default QoS-event handlers on these eight publishers: rclpy adds each one's two (incompatible QoS,
        # incompatible type; they only log) to the executor's wait set at every wake-up, twice per sample, which
        # cost ~20 % of the node's CPU at 500 Hz. The input subscriptions keep theirs: there a wrong QoS loses data.
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
        # One message per topic, filled anew for every estimate (rclpy serializes at publish): the hot path
        # builds no message objects, and the joint names are set once.
        self._torque_msg = JointState(name=self.names)
        self._wrench_msgs = (WrenchStamped(), WrenchStamped(), WrenchStamped())    # wrench.frame, base, ee axes
        self._contact_msg, self._collision_msg = Bool(), Bool()

    def publish(self, estimate: Estimate, stamp_msg: Any, base_frame: str, ee_frame: str) -> None:
        """Every topic's message of one estimate, stamped with the input's stamp."""
        torque = self._torque_msg
        torque.header.stamp = stamp_msg
        torque.effort = _doubles(estimate.tau_ext)
        self.torque.publish(torque)
        axes = estimate.wrench_frame
        in_axes, in_base, in_ee = self._wrench_msgs
        wrench = _wrench(in_axes, stamp_msg, base_frame if axes == "base" else ee_frame, estimate.wrench)
        self.wrench.publish(wrench)
        if self.base_wanted:
            self.wrench_base.publish(wrench if axes == "base" else
                                     _wrench(in_base, stamp_msg, base_frame, estimate.wrench_in("base")))
        if self.ee_wanted:
            self.wrench_ee.publish(wrench if axes == "end_effector" else
                                   _wrench(in_ee, stamp_msg, ee_frame, estimate.wrench_in("end_effector")))
        if estimate.tau_cov is not None and self.uncertainty_wanted:
            stddev = np.sqrt(np.maximum(np.diag(estimate.tau_cov), 0.0))
            self.stddev.publish(Float64MultiArray(layout=self._stddev_layout, data=_doubles(stddev)))
            self.covariance.publish(Float64MultiArray(layout=self._covariance_layout,
                                                      data=_doubles(estimate.wrench_cov.ravel())))
        self._contact_msg.data, self._collision_msg.data = estimate.contact, estimate.collision
        self.contact.publish(self._contact_msg)
        self.collision.publish(self._collision_msg)
        self.published += 1
        if self.published % SUBSCRIBER_CHECK == 0:
            self.check_subscribers()

    def check_subscribers(self) -> None:
        """From now on publish the uncertainty and the fixed-axes wrench topics only if someone subscribes."""
        self.uncertainty_wanted = (self.stddev.get_subscription_count() > 0
                                   or self.covariance.get_subscription_count() > 0)
        self.base_wanted = self.wrench_base.get_subscription_count() > 0
        self.ee_wanted = self.wrench_ee.get_subscription_count() > 0
