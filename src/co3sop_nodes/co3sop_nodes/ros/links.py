"""A node's V2X links as the node itself sees them, on /diagnostics: how many publishers each of its V2X
subscriptions (an ego's neighbours' features, a vehicle's egos' request maps) has matched, and how many subscribers
each of its V2X publishers (a vehicle's features) has: a message sent before its writer matched a reader never
reaches that reader (volatile durability), whatever the reader's own view.

A launcher's own view of the graph says a subscription exists, not that the publisher's participant has matched it:
over a slow or shared link DDS discovery may take seconds more. The status `<node's status> links` is published
every discovery period while the node is active (as diagnostic_updater publishes at 1 Hz), so a launcher that
subscribes late still gets it; `demo` plays the bag once every link is up.
"""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticStatus

from co3sop_nodes.messages import diagnostics_msg
from co3sop_nodes.ros.message_types import RCLPY

SUFFIX = " links"
KEY = "matched_publishers"
SENT_KEY = "matched_subscribers"


def publish_links(
    node, publisher, status: str, frame_id: str, subscriptions: dict, publishers: dict | None = None
) -> None:
    """Publishes status `status + SUFFIX`: topic -> publishers matched, for every subscription (topic -> rclpy
    Subscription), and topic -> subscribers matched, for every publisher given (topic -> rclpy Publisher)."""
    values = {KEY: ",".join(f"{topic}:{sub.get_publisher_count()}" for topic, sub in sorted(subscriptions.items()))}
    if publishers:
        values[SENT_KEY] = ",".join(f"{t}:{pub.get_subscription_count()}" for t, pub in sorted(publishers.items()))
    stamp = node.get_clock().now().nanoseconds
    publisher.publish(
        diagnostics_msg(RCLPY, stamp, status + SUFFIX, frame_id, DiagnosticStatus.OK, "V2X links", values)
    )


def _counts(report: dict[str, str], key: str) -> dict[str, int]:
    return {t: int(n) for t, _, n in (x.rpartition(":") for x in report.get(key, "").split(",") if x)}


def matched_publishers(report: dict[str, str]) -> dict[str, int]:
    """topic -> publishers matched, from a links status's values."""
    return _counts(report, KEY)


def matched_subscribers(report: dict[str, str]) -> dict[str, int]:
    """topic -> subscribers matched by the node's publisher, from a links status's values."""
    return _counts(report, SENT_KEY)
