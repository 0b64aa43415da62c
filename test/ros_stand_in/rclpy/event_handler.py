"""Stand-in rclpy.event_handler (test suite, not ROS): QoS event callbacks are accepted and never called."""
from __future__ import annotations


class PublisherEventCallbacks:
    def __init__(self, *, use_default_callbacks: bool = True, **callbacks: object) -> None:
        self.use_default_callbacks = use_default_callbacks


class SubscriptionEventCallbacks:
    def __init__(self, *, use_default_callbacks: bool = True, **callbacks: object) -> None:
        self.use_default_callbacks = use_default_callbacks
