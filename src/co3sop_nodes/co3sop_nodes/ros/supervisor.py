"""Drives and watches a graph from outside, as a lifecycle manager does: lifecycle states and transitions
over the nodes' own services, graph events (who subscribes to what), and the frames each node reports on
/diagnostics. The demo and the integration tests decide everything through it, never by reading logs.

It runs its own rclpy context and executor thread, so it lives beside other rclpy users in one process.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from collections.abc import Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from co3sop_nodes.common import topics
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.ros import links
from co3sop_nodes.ros.dds import DIAGNOSTICS_QOS, configure_environment


def _qualified(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


TRANSITIONS = {
    "configure": Transition.TRANSITION_CONFIGURE,
    "activate": Transition.TRANSITION_ACTIVATE,
    "deactivate": Transition.TRANSITION_DEACTIVATE,
    "cleanup": Transition.TRANSITION_CLEANUP,
}
SHUTDOWN = {
    "unconfigured": Transition.TRANSITION_UNCONFIGURED_SHUTDOWN,
    "inactive": Transition.TRANSITION_INACTIVE_SHUTDOWN,
    "active": Transition.TRANSITION_ACTIVE_SHUTDOWN,
}


class Supervisor:
    def __init__(self, name: str = "supervisor", alive: Callable[[], str | None] = lambda: None):
        """`alive()` returns why the watched graph cannot go on (e.g. a node process exited), or None: waits fail at once on it."""
        configure_environment()
        self._alive = alive
        self._context = Context()
        # not the launcher's command line: its node parameters (x:=y) are for the nodes it starts, not remaps
        rclpy.init(args=[], context=self._context)
        self.node = rclpy.create_node(name, context=self._context)
        self._lock = threading.Lock()
        self._clients: dict[str, object] = {}  # service name -> its client (see _call)
        self._diagnostics: dict[str, list[dict[str, str]]] = defaultdict(list)  # status name -> values of each report
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, DIAGNOSTICS_QOS)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self._executor.spin()
        except Exception:
            pass

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        with self._lock:
            for status in msg.status:
                self._diagnostics[status.name].append({kv.key: kv.value for kv in status.values})

    def close(self) -> None:
        self._executor.shutdown(timeout_sec=2)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self._context)
        self._thread.join(5)

    def __enter__(self) -> Supervisor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- waiting ---

    def wait(self, what: str, ready: Callable[[], bool], timeout: float, seen: Callable[[], str] | None = None) -> None:
        """Until `ready()`; Co3sopError naming `what` after `timeout` s (and what came instead: `seen()`) or as soon
        as the graph cannot go on."""
        deadline = time.monotonic() + timeout
        while not ready():
            if (why := self._alive()) is not None:
                raise Co3sopError(f"{why} (while waiting for {what})")
            if time.monotonic() > deadline:
                raise Co3sopError(f"waited {timeout:g} s for {what}, in vain" + (f": {seen()}" if seen else ""))
            time.sleep(0.05)

    def _call(self, service_type, service: str, request, timeout: float, resend: float | None = None):
        """The answer of `service` to `request`. One client per service for the supervisor's life: a server may
        answer before it has matched a new client's response reader, and that answer is lost (rmw logs "failed to
        send response"); `resend` s without an answer send the request again (for requests that may be repeated)."""
        client = self._clients.get(service)
        if client is None:
            client = self._clients[service] = self.node.create_client(service_type, service)
        self.wait(f"service {service}", client.service_is_ready, timeout)
        deadline = time.monotonic() + timeout
        while True:
            future = client.call_async(request)
            try:
                self.wait(
                    f"an answer from {service}",
                    future.done,
                    min(resend or timeout, max(0.0, deadline - time.monotonic())),
                )
                return future.result()
            except Co3sopError:
                client.remove_pending_request(future)
                if resend is None or self._alive() is not None:
                    raise
                if time.monotonic() >= deadline:
                    raise Co3sopError(f"no answer from {service} within {timeout:g} s") from None

    # --- lifecycle ---

    def state(self, node: str, timeout: float = 60) -> str:
        """The lifecycle state of `node` (a fully qualified name, e.g. /ego): unconfigured, inactive, active, finalized."""
        return self._call(GetState, f"{node}/get_state", GetState.Request(), timeout, resend=5.0).current_state.label

    def change(self, node: str, transition: str, timeout: float = 300) -> bool:
        """Asks `node` for a transition (configure, activate, deactivate, cleanup, shutdown); True when it succeeded."""
        tid = SHUTDOWN[self.state(node, timeout)] if transition == "shutdown" else TRANSITIONS[transition]
        return self._call(
            ChangeState, f"{node}/change_state", ChangeState.Request(transition=Transition(id=tid)), timeout
        ).success

    def bring_up(self, nodes: list[str], timeout: float = 300) -> None:
        """Configures every node (all load their models at once), then activates them; Co3SopError naming the first that fails."""
        for transition in ("configure", "activate"):
            for node in nodes:
                if not self.change(node, transition, timeout):
                    raise Co3sopError(f"{node}: {transition} failed (its log says why)")

    def wait_state(self, node: str, state: str, timeout: float = 300) -> None:
        self.wait(f"{node} {state}", lambda: self.state(node, timeout) == state, timeout)

    # --- graph events ---

    def subscribes(self, node: str, topic: str) -> bool:
        """`node` (fully qualified: /ego, /cav_3/vehicle) has a subscription on `topic`."""
        return any(
            _qualified(info.node_namespace, info.node_name) == node
            for info in self.node.get_subscriptions_info_by_topic(topic)
        )

    def wait_subscribed(self, node: str, topic: str, timeout: float = 60) -> None:
        self.wait(f"{node} subscribed to {topic}", lambda: self.subscribes(node, topic), timeout)

    def publishes(self, node: str, topic: str) -> bool:
        """`node` (fully qualified) has a publisher on `topic`."""
        return any(
            _qualified(info.node_namespace, info.node_name) == node
            for info in self.node.get_publishers_info_by_topic(topic)
        )

    def wait_published(self, node: str, topic: str, timeout: float = 60) -> None:
        self.wait(f"{node} publishing on {topic}", lambda: self.publishes(node, topic), timeout)

    def linked(self, status: str, receives: list[str] = (), sends: list[str] = ()) -> bool:
        """By the node's own account (its latest links status, ros/links.py; `status`: its /diagnostics status name):
        it has matched a publisher on every topic of `receives` and a subscriber on every topic of `sends`. This
        supervisor's own view of the graph says an endpoint exists, not that the node's participant has matched it."""
        reports = self.reports(status + links.SUFFIX)
        if not reports:
            return False
        pubs, subs = links.matched_publishers(reports[-1]), links.matched_subscribers(reports[-1])
        return all(pubs.get(t, 0) > 0 for t in receives) and all(subs.get(t, 0) > 0 for t in sends)

    # --- what the nodes report ---

    def reports(self, status: str) -> list[dict[str, str]]:
        """The values of every /diagnostics status named `status` received so far (e.g. "ego")."""
        with self._lock:
            return list(self._diagnostics[status])

    def wait_reports(
        self, status: str, n: int, timeout: float, where: Callable[[dict[str, str]], bool] = lambda r: True
    ) -> list[dict]:
        """At least `n` reports of `status` satisfying `where`; returns all of them. The error of a wait in vain says
        how many came, how many of them would do, and the last one's values."""

        def seen() -> str:
            got = self.reports(status)
            last = ", ".join(f"{k}={v}" for k, v in got[-1].items()) if got else ""
            return f"{len(got)} came, {sum(map(where, got))} of them as wanted" + (f"; the last: {last}" if got else "")

        self.wait(
            f"{n} /diagnostics reports of {status!r}",
            lambda: sum(map(where, self.reports(status))) >= n,
            timeout,
            seen,
        )
        return self.reports(status)
