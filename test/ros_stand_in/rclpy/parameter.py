"""Stand-in rclpy.parameter (test suite, not ROS): ``Parameter`` and its ``Type`` as in rclpy."""
from __future__ import annotations

import array
from enum import IntEnum
from typing import Any

from rcl_interfaces.msg import ParameterType

PARAMETER_SEPARATOR_STRING = "."


class Parameter:

    class Type(IntEnum):
        NOT_SET = ParameterType.PARAMETER_NOT_SET
        BOOL = ParameterType.PARAMETER_BOOL
        INTEGER = ParameterType.PARAMETER_INTEGER
        DOUBLE = ParameterType.PARAMETER_DOUBLE
        STRING = ParameterType.PARAMETER_STRING
        BYTE_ARRAY = ParameterType.PARAMETER_BYTE_ARRAY
        BOOL_ARRAY = ParameterType.PARAMETER_BOOL_ARRAY
        INTEGER_ARRAY = ParameterType.PARAMETER_INTEGER_ARRAY
        DOUBLE_ARRAY = ParameterType.PARAMETER_DOUBLE_ARRAY
        STRING_ARRAY = ParameterType.PARAMETER_STRING_ARRAY

        @classmethod
        def from_parameter_value(cls, value: Any) -> "Parameter.Type":
            if value is None:
                return cls.NOT_SET
            if isinstance(value, bool):
                return cls.BOOL
            if isinstance(value, int):
                return cls.INTEGER
            if isinstance(value, float):
                return cls.DOUBLE
            if isinstance(value, str):
                return cls.STRING
            if isinstance(value, (list, tuple, array.array)):
                for kind, python in ((cls.BYTE_ARRAY, bytes), (cls.BOOL_ARRAY, bool), (cls.INTEGER_ARRAY, int),
                                     (cls.DOUBLE_ARRAY, float), (cls.STRING_ARRAY, str)):
                    if all(isinstance(v, python) for v in value):
                        return kind
                raise TypeError(f"The given value is not a list of one of the allowed types '{value}'.")
            raise TypeError(f"The given value is not one of the allowed types '{value}'.")

        def check(self, value: Any) -> bool:
            T = Parameter.Type
            if self == T.NOT_SET:
                return value is None
            if self == T.BOOL:
                return isinstance(value, bool)
            if self == T.INTEGER:
                return isinstance(value, int)
            if self == T.DOUBLE:
                return isinstance(value, float)
            if self == T.STRING:
                return isinstance(value, str)
            if self == T.BYTE_ARRAY:
                return isinstance(value, (list, tuple)) and all(isinstance(v, bytes) and len(v) == 1 for v in value)
            if self == T.BOOL_ARRAY:
                return isinstance(value, (list, tuple)) and all(isinstance(v, bool) for v in value)
            if self == T.INTEGER_ARRAY:
                return isinstance(value, (list, tuple, array.array)) and all(isinstance(v, int) for v in value)
            if self == T.DOUBLE_ARRAY:
                return isinstance(value, (list, tuple, array.array)) and all(isinstance(v, float) for v in value)
            if self == T.STRING_ARRAY:
                return isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value)
            return False

    def __init__(self, name: str, type_: "Parameter.Type | None" = None, value: Any = None) -> None:
        if type_ is None:
            type_ = Parameter.Type.from_parameter_value(value)
        if not isinstance(type_, Parameter.Type):
            raise TypeError(f"type must be an instance of '{Parameter.Type!r}'")
        if not type_.check(value):
            raise ValueError(f"Type '{type_}' and value '{value}' do not agree")
        self._type_ = type_
        self._name = name
        self._value = value

    @property
    def name(self) -> str:
        return self._name

    @property
    def type_(self) -> "Parameter.Type":
        return self._type_

    @property
    def value(self) -> Any:
        return self._value

    def __repr__(self) -> str:
        return f"Parameter({self._name!r}, {self._type_.name}, {self._value!r})"
