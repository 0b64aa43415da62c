"""kvark_ros: sensorless external torque and wrench estimation with the K-VARK filter."""

__version__ = "0.1.0"
