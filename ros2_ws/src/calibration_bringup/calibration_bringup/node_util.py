"""Small helpers shared by the recorder and the player nodes (message classes, parameters)."""
from __future__ import annotations

import importlib

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node


def message_class(type_name: str) -> type:
    """The Python class of ``pkg/msg/Type``.

    Raises
    ------
    ImportError
        If the package or type is not installed.
    """
    pkg, _, name = type_name.partition('/msg/')
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError) as exc:
        raise ImportError(f'message type {type_name!r} is not installed: {exc}') from exc


def string_list(node: Node, name: str) -> list[str]:
    """A string-array parameter declared without a default (unset = empty), blanks dropped.

    rclpy cannot declare an empty list as a string array (``[]`` becomes a byte array that
    refuses strings later), so such parameters are declared by type and may be unset.
    """
    try:
        value = node.get_parameter(name).value
    except ParameterUninitializedException:
        return []
    return [s for s in (value or []) if s]


def float_range(desc: str, lo: float, hi: float) -> ParameterDescriptor:
    """A descriptor with a description and a floating-point range."""
    return ParameterDescriptor(description=desc,
                               floating_point_range=[FloatingPointRange(from_value=lo, to_value=hi)])


def int_range(desc: str, lo: int, hi: int) -> ParameterDescriptor:
    """A descriptor with a description and an integer range."""
    return ParameterDescriptor(description=desc, integer_range=[IntegerRange(from_value=lo, to_value=hi)])
