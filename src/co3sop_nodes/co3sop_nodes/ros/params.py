"""Node parameters declared with descriptors (`ros2 param describe` shows them), required ones without a
default, and run-time changes checked before they apply.

A node lists its parameters as `Param`s; `Parameters` declares them, reads
them, checks ranges and choices, and routes `ros2 param set` of the ones that
may change at run time to the function given to `on_change(apply)`: `apply`
raises Co3sopError to refuse the values (the reason goes back to the caller)
and otherwise takes them. Read-only ones (what
needs a restart, e.g. the checkpoint) are refused by rclpy itself.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType, SetParametersResult
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterUninitializedException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from co3sop_nodes.common.allocation import MAX_RESERVE
from co3sop_nodes.common.errors import Co3sopError, exception_line

_TYPES = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
    list: ParameterType.PARAMETER_STRING_ARRAY,
}


@dataclass(frozen=True)
class Param:
    name: str
    type: type  # bool, int, float, str, or list (of strings)
    description: str
    default: Any = None  # None: required (no default; the node refuses to start without it)
    runtime: bool = False  # may change while the node runs (else read-only)
    range: tuple[float, float] | None = None  # inclusive bounds of an int or float
    choices: tuple[str, ...] = ()

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(
            name=self.name, type=_TYPES[self.type], description=self.description, read_only=not self.runtime
        )
        if self.range is not None and self.type is int:
            d.integer_range = [IntegerRange(from_value=int(self.range[0]), to_value=int(self.range[1]), step=0)]
        elif self.range is not None:
            d.floating_point_range = [
                FloatingPointRange(from_value=float(self.range[0]), to_value=float(self.range[1]), step=0.0)
            ]
        if self.choices:
            d.additional_constraints = "one of: " + ", ".join(repr(c) for c in self.choices)
        return d


def memory_reserve(default_mb: int) -> Param:
    """`memory_reserve_mb`: the memory a node reserves at configure (`allocation.reserve_memory`)."""
    return Param(
        "memory_reserve_mb",
        int,
        "memory written at configure and kept for frames (MB), so that the first frames, the graph's busiest, do "
        "not page-fault it; 0: none",
        default_mb,
        range=(0, MAX_RESERVE >> 20),
    )


def parameters_help(params: Sequence[Param]) -> str:
    """Every parameter with its type, default (or 'required'), bounds or choices and description: the epilog of
    a node's --help."""
    lines = ["parameters (--ros-args -p NAME:=VALUE, or --params-file FILE; * may change at run time):"]
    for p in params:
        default = "required" if p.default is None else f"default {p.default!r}"
        bound = (lambda v: str(int(v))) if p.type is int else (lambda v: f"{v:g}")
        allowed = (
            f", one of {', '.join(map(repr, p.choices))}"
            if p.choices
            else f", in [{bound(p.range[0])}, {bound(p.range[1])}]"
            if p.range
            else ""
        )
        lines.append(f"  {p.name}{' *' if p.runtime else ''} ({p.type.__name__}, {default}{allowed})")
        lines.append(f"      {p.description}")
    return "\n".join(lines)


class Parameters:
    def __init__(self, node: Node, params: Sequence[Param]):
        self._node, self._params = node, {p.name: p for p in params}
        self._apply: Callable[[dict[str, Any]], None] | None = None
        for p in params:
            # a required one is declared by its type alone: unset until -p gives it
            try:
                node.declare_parameter(
                    p.name, Parameter.Type(_TYPES[p.type]) if p.default is None else p.default, p.descriptor()
                )
            except (InvalidParameterTypeException, InvalidParameterValueException) as exc:  # a bad -p or params file
                raise Co3sopError(f"parameter {p.name}: {exc}") from None
            self.check(p.name, self[p.name])
        node.add_on_set_parameters_callback(self._on_set)

    def __getitem__(self, name: str) -> Any:
        try:
            value = self._node.get_parameter(name).value
        except ParameterUninitializedException:
            raise Co3sopError(
                f"parameter {name} is required ({self._params[name].description}): pass -p {name}:=VALUE"
            ) from None
        return list(value) if self._params[name].type is list else value

    def on_change(self, apply: Callable[[dict[str, Any]], None]) -> None:
        """apply(changes) on every accepted `ros2 param set` from now on."""
        self._apply = apply

    def check(self, name: str, value: Any) -> None:
        p = self._params[name]
        if p.choices and value not in p.choices:
            raise Co3sopError(f"parameter {name}={value!r} is not one of {', '.join(repr(c) for c in p.choices)}")
        if (
            p.range is not None and not p.range[0] <= value <= p.range[1]
        ):  # also checked by rclpy on set; not on overrides
            raise Co3sopError(f"parameter {name}={value!r} is outside [{p.range[0]:g}, {p.range[1]:g}]")

    def _on_set(self, changes: list[Parameter]) -> SetParametersResult:
        ours = {c.name: c.value for c in changes if c.name in self._params}
        try:
            for name, value in ours.items():
                self.check(name, value)
            if ours and self._apply is not None:
                self._apply(ours)
        except Co3sopError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        except Exception as exc:
            self._node.get_logger().error(f"parameters {', '.join(ours)}: refused: {exception_line(exc)}")
            return SetParametersResult(successful=False, reason=f"refused: {exception_line(exc)}")
        return SetParametersResult(successful=True)
