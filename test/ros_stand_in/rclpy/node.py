"""Stand-in rclpy.node.Node (test suite, not ROS).

Parameters follow rclpy's rules (rclpy/node.py): declaring takes the override, else the
default; a ``Parameter.Type`` declares a statically typed parameter that stays uninitialised
without an override; the descriptor's read-only flag, type and range are checked before the
on-set callbacks; declaring calls the on-set and post-set callbacks once per parameter;
``set_parameters`` sets each parameter on its own and returns one result each.
Topics, services and timers live in ``ros_stand_in_core.GRAPH``.
"""
from __future__ import annotations

import copy

import inspect

import math
from typing import Any, Callable

import ros_stand_in_core as _core
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock
from rclpy.exceptions import (InvalidParameterTypeException, InvalidParameterValueException,
                              ParameterAlreadyDeclaredException, ParameterNotDeclaredException,
                              ParameterUninitializedException)
from rclpy.logging import get_logger
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile

PARAM_REL_TOL = 1e-6


class Publisher:
    def __init__(self, msg_type: type, topic: str, qos_profile: Any) -> None:
        self.msg_type, self.topic_name, self.qos_profile = msg_type, topic, qos_profile
        self.messages: list[Any] = []
        self.destroyed = False

    def get_subscription_count(self) -> int:
        """Subscriptions on this publisher's topic in the stand-in graph."""
        return len(_core.GRAPH.subscriptions.get(self.topic_name, ()))

    def publish(self, msg: Any) -> None:
        """A message, or its CDR bytes (rclpy's ``publish_raw``): the graph keeps and delivers the message."""
        if self.destroyed:
            raise RuntimeError(f"stand-in: publisher of {self.topic_name} was destroyed")
        if isinstance(msg, bytes):
            msg = _core.from_cdr(msg, self.msg_type)
        elif not isinstance(msg, self.msg_type):
            raise TypeError(f"Expected {self.msg_type}, got {type(msg)}")
        else:
            msg = copy.deepcopy(msg)        # rclpy serializes at publish: the caller may reuse its message
        self.messages.append(msg)
        _core.GRAPH.deliver(self.topic_name, msg)


class Subscription:
    def __init__(self, msg_type: type, topic: str, callback: Callable[..., None], qos_profile: Any,
                 raw: bool = False, callback_group: Any = None) -> None:
        self.msg_type, self.topic_name, self.callback, self.qos_profile = msg_type, topic, callback, qos_profile
        self.raw, self.callback_group = raw, callback_group
        # As rclpy decides (Subscription.callback setter): one argument, or the message and its info.
        try:
            inspect.signature(callback).bind(object())
            self.with_message_info = False
        except TypeError:
            try:
                inspect.signature(callback).bind(object(), object())
            except TypeError:
                raise RuntimeError("Subscription.__init__(): callback should be either be callable with one "
                                   "argument(to get only the message) or two (to get message and message info)")
            self.with_message_info = True


class Service:
    def __init__(self, srv_type: Any, name: str, callback: Callable[[Any, Any], Any]) -> None:
        self.srv_type, self.srv_name, self.callback = srv_type, name, callback


class Timer:
    def __init__(self, period_ns: int, callback: Callable[[], None]) -> None:
        self.timer_period_ns = period_ns
        self.callback = callback
        self.next_due_ns = _core.now_ns() + period_ns
        self.canceled = False

    def cancel(self) -> None:
        self.canceled = True

    def is_canceled(self) -> bool:
        return self.canceled


def _check_qos(qos_profile: Any) -> Any:
    if isinstance(qos_profile, int):
        return QoSProfile(depth=qos_profile)
    if not isinstance(qos_profile, QoSProfile):
        raise TypeError("Expected QoSProfile or int, but received {!r}".format(type(qos_profile)))
    return qos_profile


class Node:
    PARAM_REL_TOL = PARAM_REL_TOL

    def __init__(self, node_name: str, *, context: Any = None, cli_args: Any = None, namespace: str | None = None,
                 use_global_arguments: bool = True, enable_rosout: bool = True, start_parameter_services: bool = True,
                 parameter_overrides: list[Parameter] | None = None, allow_undeclared_parameters: bool = False,
                 automatically_declare_parameters_from_overrides: bool = False, enable_logger_service: bool = False
                 ) -> None:
        if not _core.CONTEXT.initialized:
            raise RuntimeError("stand-in: rclpy.init() has not been called")
        self._name = node_name
        ns = namespace or "/"
        self._namespace = ns if ns.startswith("/") else "/" + ns
        self._logger = get_logger(node_name)
        self._clock = Clock()
        self._parameters: dict[str, Parameter] = {}
        self._descriptors: dict[str, ParameterDescriptor] = {}
        self._on_set_parameters_callbacks: list[Callable] = []
        self._post_set_parameters_callbacks: list[Callable] = []
        self._allow_undeclared_parameters = allow_undeclared_parameters
        self._parameter_overrides: dict[str, Parameter] = {}
        if use_global_arguments:
            for name, value in _core.overrides_for(self.get_fully_qualified_name()).items():
                self._parameter_overrides[name] = Parameter(name, value=value)
        for parameter in parameter_overrides or []:
            self._parameter_overrides[parameter.name] = parameter
        self._publishers: list[Publisher] = []
        self._subscriptions: list[Subscription] = []
        self._services: list[Service] = []
        self._timers: list[Timer] = []
        self.destroyed = False
        self.declare_parameter("use_sim_time", False)

    @property
    def executor(self) -> Any:
        """The executor the node was added to: none in the stand-in."""
        return None

    # -- names, clock, logger

    def get_name(self) -> str:
        return self._name

    def get_namespace(self) -> str:
        return self._namespace

    def get_fully_qualified_name(self) -> str:
        return f"{self._namespace.rstrip('/')}/{self._name}"

    def get_clock(self) -> Clock:
        return self._clock

    def get_logger(self) -> Any:
        return self._logger

    def _resolve(self, name: str) -> str:
        return _core.resolve(name, self._namespace, self._name)

    # -- parameters

    def declare_parameter(self, name: str, value: Any = None, descriptor: ParameterDescriptor | None = None,
                          ignore_override: bool = False) -> Parameter:
        descriptor = ParameterDescriptor() if descriptor is None else descriptor
        return self.declare_parameters("", [(name, value, descriptor)], ignore_override)[0]

    def declare_parameters(self, namespace: str, parameters: list[tuple], ignore_override: bool = False
                           ) -> list[Parameter]:
        parameter_list: list[Parameter] = []
        descriptors: dict[str, ParameterDescriptor] = {}
        for entry in parameters:
            name = f"{namespace}.{entry[0]}" if namespace else entry[0]
            second = entry[1] if len(entry) > 1 else None
            descriptor = entry[2] if len(entry) > 2 else ParameterDescriptor()
            if not isinstance(descriptor, ParameterDescriptor):
                raise TypeError(f"Third element {descriptor} in parameters list is not a ParameterDescriptor.")
            value = None
            if isinstance(second, Parameter.Type):
                if second == Parameter.Type.NOT_SET:
                    raise ValueError(f"Cannot declare parameter {{{name}}} as statically typed of type NOT_SET")
                if descriptor.dynamic_typing:
                    raise ValueError(f"When declaring parameter {{{name}}} passing a descriptor with"
                                     "`dynamic_typing=True` is not allowed when the parameter type is provided")
                descriptor.type = int(second)
            else:
                value = second
                if not descriptor.dynamic_typing:
                    descriptor.type = int(Parameter.Type.from_parameter_value(value))
                    if descriptor.type == Parameter.Type.NOT_SET:
                        raise ValueError("Cannot declare a statically typed parameter with default value "
                                         "of type PARAMETER_NOT_SET")
            if not ignore_override and name in self._parameter_overrides:
                value = self._parameter_overrides[name].value
            parameter_list.append(Parameter(name, value=value))
            descriptors[name] = descriptor
        already = [p.name for p in parameter_list if p.name in self._parameters]
        if already:
            raise ParameterAlreadyDeclaredException(already)
        for parameter in parameter_list:
            result = self._set_atomically([parameter], descriptors, allow_not_set_type=True)
            if not result.successful:
                if result.reason.startswith("Wrong parameter type"):
                    raise InvalidParameterTypeException(
                        parameter, Parameter.Type(descriptors[parameter.name].type).name)
                raise InvalidParameterValueException(parameter.name, parameter.value, result.reason)
        return [self._parameters[p.name] for p in parameter_list]

    def has_parameter(self, name: str) -> bool:
        return name in self._parameters

    def get_parameter(self, name: str) -> Parameter:
        if name in self._parameters:
            parameter = self._parameters[name]
            if parameter.type_ != Parameter.Type.NOT_SET or self._descriptors[name].dynamic_typing:
                return parameter
            raise ParameterUninitializedException(name)
        if self._allow_undeclared_parameters:
            return Parameter(name, Parameter.Type.NOT_SET, None)
        raise ParameterNotDeclaredException(name)

    def get_parameters(self, names: list[str]) -> list[Parameter]:
        return [self.get_parameter(name) for name in names]

    def describe_parameter(self, name: str) -> ParameterDescriptor:
        if name not in self._descriptors:
            raise ParameterNotDeclaredException(name)
        return self._descriptors[name]

    def set_parameters(self, parameter_list: list[Parameter]) -> list[SetParametersResult]:
        results = []
        for parameter in parameter_list:
            if parameter.name not in self._parameters and not self._allow_undeclared_parameters:
                raise ParameterNotDeclaredException([parameter.name])
            results.append(self._set_atomically([parameter]))
        return results

    def set_parameters_atomically(self, parameter_list: list[Parameter]) -> SetParametersResult:
        undeclared = [p.name for p in parameter_list if p.name not in self._parameters]
        if undeclared and not self._allow_undeclared_parameters:
            raise ParameterNotDeclaredException(undeclared)
        return self._set_atomically(parameter_list)

    def add_on_set_parameters_callback(self, callback: Callable) -> None:
        self._on_set_parameters_callbacks.insert(0, callback)

    def remove_on_set_parameters_callback(self, callback: Callable) -> None:
        self._on_set_parameters_callbacks.remove(callback)

    def add_post_set_parameters_callback(self, callback: Callable) -> None:
        self._post_set_parameters_callbacks.insert(0, callback)

    def remove_post_set_parameters_callback(self, callback: Callable) -> None:
        self._post_set_parameters_callbacks.remove(callback)

    def _set_atomically(self, parameter_list: list[Parameter], descriptors: dict | None = None,
                        allow_not_set_type: bool = False) -> SetParametersResult:
        check_read_only = descriptors is None
        table = self._descriptors if descriptors is None else descriptors
        for parameter in parameter_list:
            if parameter.name in table:
                result = self._apply_descriptor(parameter, table[parameter.name], check_read_only)
                if not result.successful:
                    return result
        for callback in self._on_set_parameters_callbacks:
            result = callback(parameter_list)
            if not result.successful:
                return result
        for parameter in parameter_list:
            if not allow_not_set_type and parameter.type_ == Parameter.Type.NOT_SET:
                self._parameters.pop(parameter.name, None)
                self._descriptors.pop(parameter.name, None)
                continue
            if descriptors is not None:
                self._descriptors[parameter.name] = descriptors[parameter.name]
            elif parameter.name not in self._descriptors:
                self._descriptors[parameter.name] = ParameterDescriptor(dynamic_typing=True)
            self._parameters[parameter.name] = parameter
        for callback in self._post_set_parameters_callbacks:
            callback(parameter_list)
        return SetParametersResult(successful=True)

    def _apply_descriptor(self, parameter: Parameter, descriptor: ParameterDescriptor,
                          check_read_only: bool) -> SetParametersResult:
        descriptor.name = parameter.name
        if check_read_only and descriptor.read_only:
            return SetParametersResult(successful=False,
                                       reason=f"Trying to set a read-only parameter: {parameter.name}.")
        if descriptor.dynamic_typing:
            descriptor.type = int(parameter.type_)
        elif self.has_parameter(parameter.name) and parameter.type_ == Parameter.Type.NOT_SET:
            return SetParametersResult(successful=False, reason="Static parameter cannot be undeclared")
        elif parameter.type_ != Parameter.Type.NOT_SET and int(parameter.type_) != descriptor.type:
            return SetParametersResult(successful=False, reason=(
                f"Wrong parameter type, expected '{Parameter.Type(descriptor.type)}' got '{parameter.type_}'"))
        if parameter.type_ == Parameter.Type.INTEGER and descriptor.integer_range:
            limits = descriptor.integer_range[0]
            low, high = sorted((limits.from_value, limits.to_value))
            if not low <= parameter.value <= high:
                return SetParametersResult(successful=False, reason=(
                    f"Parameter {parameter.name} out of range. Min: {low}, Max: {high}, value: {parameter.value}"))
        if parameter.type_ == Parameter.Type.DOUBLE and descriptor.floating_point_range:
            limits = descriptor.floating_point_range[0]
            low, high = sorted((limits.from_value, limits.to_value))
            edge = any(math.isclose(parameter.value, x, rel_tol=self.PARAM_REL_TOL) for x in (low, high))
            if not edge and not low < parameter.value < high:
                return SetParametersResult(successful=False, reason=(
                    f"Parameter {parameter.name} out of range Min: {low}, Max: {high}, value: {parameter.value}"))
        return SetParametersResult(successful=True)

    # -- entities

    def create_publisher(self, msg_type: type, topic: str, qos_profile: Any, **options: Any) -> Publisher:
        publisher = Publisher(msg_type, self._resolve(topic), _check_qos(qos_profile))
        _core.GRAPH.publishers.setdefault(publisher.topic_name, []).append(publisher)
        self._publishers.append(publisher)
        return publisher

    def create_subscription(self, msg_type: type, topic: str, callback: Callable[[Any], None], qos_profile: Any,
                            *, callback_group: Any = None, raw: bool = False, **options: Any) -> Subscription:
        subscription = Subscription(msg_type, self._resolve(topic), callback, _check_qos(qos_profile), raw,
                                    callback_group)
        _core.GRAPH.subscriptions.setdefault(subscription.topic_name, []).append(subscription)
        self._subscriptions.append(subscription)
        return subscription

    def create_service(self, srv_type: Any, srv_name: str, callback: Callable[[Any, Any], Any],
                       **options: Any) -> Service:
        service = Service(srv_type, self._resolve(srv_name), callback)
        if service.srv_name in _core.GRAPH.services:
            raise RuntimeError(f"stand-in: service {service.srv_name} exists already")
        _core.GRAPH.services[service.srv_name] = service
        self._services.append(service)
        return service

    def create_timer(self, timer_period_sec: float, callback: Callable[[], None], callback_group: Any = None,
                     clock: Any = None, autostart: bool = True) -> Timer:
        timer = Timer(int(float(timer_period_sec) * 1e9), callback)
        _core.GRAPH.timers.append(timer)
        self._timers.append(timer)
        return timer

    def destroy_timer(self, timer: Timer) -> bool:
        timer.cancel()
        if timer in _core.GRAPH.timers:
            _core.GRAPH.timers.remove(timer)
        if timer in self._timers:
            self._timers.remove(timer)
            return True
        return False

    def destroy_node(self) -> None:
        for publisher in self._publishers:
            publisher.destroyed = True
        for subscription in self._subscriptions:
            subscriptions = _core.GRAPH.subscriptions.get(subscription.topic_name, [])
            if subscription in subscriptions:
                subscriptions.remove(subscription)
        for service in self._services:
            if _core.GRAPH.services.get(service.srv_name) is service:
                del _core.GRAPH.services[service.srv_name]
        for timer in list(self._timers):
            self.destroy_timer(timer)
        self._subscriptions, self._services = [], []
        self.destroyed = True
