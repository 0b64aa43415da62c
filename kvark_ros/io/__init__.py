"""ROS 2 bag input/output (rosbags only, no rclpy).

Read and write runs as ROS 2 bags (MCAP or sqlite3): :mod:`runs` holds the run
data types and :class:`BagError`, :mod:`writer` the atomic bag writer (a topic's
messages serialised at once: :class:`Messages`), :mod:`reader` :func:`read_run`,
:mod:`info` :func:`bag_info`; :mod:`cdr_arrays` and :mod:`mcap_bulk` decode,
encode, read and write many messages at once for them. Import the public names
from this package.
"""

from kvark_ros.io.common import load_message_types
from kvark_ros.io.info import bag_info
from kvark_ros.io.reader import read_run
from kvark_ros.io.runs import (
    BagError,
    CommandSeries,
    JointStateSeries,
    SIMULATOR_SOURCE,
    SOURCE_KEY,
    RecordedRun,
    TopicNames,
    WrenchSeries,
)
from kvark_ros.io.writer import (
    BagWriter,
    Messages,
    bool_messages,
    float64_array_messages,
    joint_state_messages,
    wrench_messages,
    write_run,
    write_run_messages,
)

__all__ = [
    "BagError",
    "BagWriter",
    "Messages",
    "CommandSeries",
    "JointStateSeries",
    "RecordedRun",
    "SIMULATOR_SOURCE",
    "SOURCE_KEY",
    "TopicNames",
    "WrenchSeries",
    "bag_info",
    "bool_messages",
    "float64_array_messages",
    "joint_state_messages",
    "load_message_types",
    "read_run",
    "wrench_messages",
    "write_run",
    "write_run_messages",
]
