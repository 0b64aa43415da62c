"""ROS 2 bag input/output (rosbags only, no rclpy).

Read and write runs as ROS 2 bags (MCAP or sqlite3): :mod:`runs` holds the run
data types and :class:`BagError`, :mod:`writer` the atomic bag writer,
:mod:`reader` :func:`read_run`, :mod:`info` :func:`bag_info`. Import the
public names from this package.
"""

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
from kvark_ros.io.writer import BagWriter, write_run, write_run_messages

__all__ = [
    "BagError",
    "BagWriter",
    "CommandSeries",
    "JointStateSeries",
    "RecordedRun",
    "SIMULATOR_SOURCE",
    "SOURCE_KEY",
    "TopicNames",
    "WrenchSeries",
    "bag_info",
    "read_run",
    "write_run",
    "write_run_messages",
]
