"""Stand-in rclpy.impl.implementation_singleton (test suite, not ROS): rclpy's C layer is not faked.

The node's input loop waits on it (``kvark_ros.ros.input_loop``); here the graph calls the input subscriptions'
callbacks directly and the loop is never started (tests that spin the node run it under real rclpy).
"""
rclpy_implementation = None
