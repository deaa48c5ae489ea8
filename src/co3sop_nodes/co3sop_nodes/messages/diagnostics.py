"""diagnostic_msgs/DiagnosticArray (ROS-free adapter; see backend.py)."""

from __future__ import annotations

from co3sop_nodes.messages.backend import MessageTypes
from co3sop_nodes.messages.std import header_msg


def diagnostics_msg(
    types: MessageTypes, stamp_ns: int, name: str, hardware_id: str, level: bytes, message: str, values: dict
):
    """One DiagnosticStatus (values as strings) in a DiagnosticArray, as /diagnostics carries; level as the
    binding spells it (DiagnosticStatus.OK)."""
    status = types.make(
        "diagnostic_msgs/msg/DiagnosticStatus",
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[types.make("diagnostic_msgs/msg/KeyValue", key=k, value=str(v)) for k, v in values.items()],
    )
    return types.make("diagnostic_msgs/msg/DiagnosticArray", header=header_msg(types, stamp_ns, ""), status=[status])
