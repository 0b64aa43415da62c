"""Private pieces shared by the bag reader and writer.

Path and array types, the message type names a run uses, nanoseconds per
second (bags store integer nanosecond stamps) and the one typestore.
"""

from __future__ import annotations

import os
from functools import cache
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.typesys import Stores, get_typestore

PathLike = str | os.PathLike[str]
FloatArray = npt.NDArray[np.float64]

JOINT_STATE = "sensor_msgs/msg/JointState"
FLOAT64_ARRAY = "std_msgs/msg/Float64MultiArray"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
# The stamped message of common_interfaces that holds a 6-vector and its 6×6 covariance: the node's wrench with its
# covariance (geometry_msgs has no WrenchWithCovarianceStamped).
TWIST_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/TwistWithCovarianceStamped"
BOOL = "std_msgs/msg/Bool"

NS_PER_SECOND = 1_000_000_000   # bags store integer nanosecond stamps


@cache
def typestore() -> Any:
    """The single Jazzy typestore: message classes, CDR (de)serialisation."""
    return get_typestore(Stores.ROS2_JAZZY)


def load_message_types() -> None:
    """Build the typestore now (about 0.05 s, once per process) rather than inside the first bag's reading."""
    typestore()
