"""The rclpy binding for the message adapters (co3sop_nodes.messages): generated classes found as
`ros2 bag play` finds them."""

from __future__ import annotations

import array
import importlib
from functools import cache

import numpy as np

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.messages.backend import MessageTypes

_TYPECODES = {"float32": "f", "float64": "d", "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q"}


@cache
def message_class(msgtype: str) -> type:
    """'pkg/msg/Type' -> the generated Python class."""
    package, _, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        raise DatasetError(f"message type {msgtype} is not installed: source the workspace that defines it") from None


class RclpyTypes(MessageTypes):
    def cls(self, msgtype: str) -> type:
        return message_class(msgtype)

    def octets(self, data) -> bytes:
        return data if isinstance(data, bytes) else bytes(memoryview(data).cast("B"))

    def sequence(self, values, dtype: str) -> array.array:
        return array.array(_TYPECODES[dtype], np.asarray(values, dtype).reshape(-1).tobytes())


RCLPY = RclpyTypes()
