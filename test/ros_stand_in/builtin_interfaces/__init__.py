"""Stand-in for the ROS 2 package builtin_interfaces, owned by the kvark_ros test suite; not ROS (see ros_stand_in_core)."""
