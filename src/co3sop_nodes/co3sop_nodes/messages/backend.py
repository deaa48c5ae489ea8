"""How a message is built, whichever Python message classes build it (ROS-free).

The adapters in this package know each message's layout once; they build
messages through a `MessageTypes`, which hands out the classes and turns
arrays into what those classes take. Two exist: `RosbagsTypes` here (bags and
recordings, written and read with rosbags) and `RclpyTypes` in
`co3sop_nodes.ros.message_types` (the nodes). Both construct a message from
keyword arguments; they differ in how array fields are given: rosbags wants
numpy arrays for every array, rclpy wants bytes for uint8[] (assigned about
100x faster than a numpy array), a list or array.array for other sequences and
numpy for fixed-size arrays. Reading needs no backend: field names are the
same and every array supports the buffer protocol.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence

import numpy as np


class MessageTypes(ABC):
    """The message classes of one Python binding."""

    @abstractmethod
    def cls(self, msgtype: str) -> type:
        """'pkg/msg/Type' -> its class."""

    def make(self, msgtype: str, **fields):
        return self.cls(msgtype)(**fields)

    @abstractmethod
    def octets(self, data) -> object:
        """A uint8[] field's value from bytes or a uint8 buffer."""

    @abstractmethod
    def sequence(self, values: Sequence | np.ndarray, dtype: str) -> object:
        """An unbounded numeric sequence field's value (float32[], float64[], ...)."""

    def fixed(self, values: Sequence | np.ndarray, dtype: str) -> np.ndarray:
        """A fixed-size numeric array field's value (float64[9], ...): numpy in both bindings."""
        return np.asarray(values, dtype).reshape(-1)


class RosbagsTypes(MessageTypes):
    """rosbags' dataclasses from a typestore (co3sop_nodes.data.bags.typestore)."""

    def __init__(self, store):
        self.store = store

    def cls(self, msgtype: str) -> type:
        return self.store.types[msgtype]

    def octets(self, data) -> np.ndarray:
        return np.frombuffer(data, np.uint8)

    def sequence(self, values, dtype: str) -> np.ndarray:
        return np.asarray(values, dtype).reshape(-1)


def octets_of(field) -> memoryview:
    """A uint8[] field as read (bytes, array.array or numpy), as bytes without a copy."""
    return memoryview(field).cast("B")
