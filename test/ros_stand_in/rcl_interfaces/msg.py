"""Stand-in rcl_interfaces messages (test suite, not ROS)."""
from ros_stand_in_core import Message


class ParameterType:
    PARAMETER_NOT_SET = 0
    PARAMETER_BOOL = 1
    PARAMETER_INTEGER = 2
    PARAMETER_DOUBLE = 3
    PARAMETER_STRING = 4
    PARAMETER_BYTE_ARRAY = 5
    PARAMETER_BOOL_ARRAY = 6
    PARAMETER_INTEGER_ARRAY = 7
    PARAMETER_DOUBLE_ARRAY = 8
    PARAMETER_STRING_ARRAY = 9


class FloatingPointRange(Message):
    FIELDS = {"from_value": "float64", "to_value": "float64", "step": "float64"}


class IntegerRange(Message):
    FIELDS = {"from_value": "int64", "to_value": "int64", "step": "uint64"}


class ParameterDescriptor(Message):
    FIELDS = {"name": "string", "type": "uint8", "description": "string", "additional_constraints": "string",
              "read_only": "bool", "dynamic_typing": "bool",
              "floating_point_range": [FloatingPointRange], "integer_range": [IntegerRange]}


class SetParametersResult(Message):
    FIELDS = {"successful": "bool", "reason": "string"}
