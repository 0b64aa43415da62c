"""Stand-in rclpy.exceptions (test suite, not ROS); messages follow rclpy's."""
from typing import Any


class ParameterException(Exception):
    def __init__(self, error_msg: str, parameters: Any, *args: Any) -> None:
        Exception.__init__(self, f"{error_msg}: {parameters}", *args)


class ParameterNotDeclaredException(ParameterException):
    def __init__(self, parameters: Any, *args: Any) -> None:
        ParameterException.__init__(self, "Invalid access to undeclared parameter(s)", parameters, *args)


class ParameterAlreadyDeclaredException(ParameterException):
    def __init__(self, parameters: Any, *args: Any) -> None:
        ParameterException.__init__(self, "Parameter(s) already declared", parameters, *args)


class ParameterUninitializedException(ParameterException):
    def __init__(self, parameter_name: str, *args: Any) -> None:
        Exception.__init__(self, f"The parameter '{parameter_name}' is not initialized", *args)


class ParameterImmutableException(ParameterException):
    def __init__(self, parameters: Any, *args: Any) -> None:
        ParameterException.__init__(self, "Attempted to modify read-only parameter", parameters, *args)


class InvalidParameterTypeException(ParameterException):
    def __init__(self, desired_parameter: Any, expected_type: str, *args: Any) -> None:
        Exception.__init__(self, f"Trying to set parameter '{desired_parameter.name}' to "
                                 f"'{desired_parameter.value}' of type '{desired_parameter.type_.name}', "
                                 f"expecting type '{expected_type}'", *args)


class InvalidParameterValueException(ParameterException):
    def __init__(self, parameter: str, value: Any, reason: str, *args: Any) -> None:
        Exception.__init__(self, "Invalid parameter value ({value}) for parameter. Reason: {reason}".format(
            value=value, reason=reason), *args)
        self.parameter = parameter
