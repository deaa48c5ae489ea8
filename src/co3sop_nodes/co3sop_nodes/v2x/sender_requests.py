"""The egos' request maps a vehicle holds and serves, on the sender's side of the link (ROS-free).

Anyone on the DDS domain can publish a RequestMap, so what a request may
cost the sender is bounded: an ego id's requests are taken from the one
topic they first came on (another topic claiming that id is refused until
the first has no publisher left), a request whose ego is beyond
`comm_range` of the vehicle is refused, a stored request expires `timeout`
after it came, at most `capacity` are held (beyond, the farthest ego's goes,
so a flood of far or made-up ids cannot push out the near egos a vehicle
serves), and a frame answers at most `max_egos` of them, nearest first. The vehicle node feeds it
and counts every refusal by its kind.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Request:
    """An ego's latest request map, as the vehicle holds it."""

    need: np.ndarray  # (X, Y, Z) on the ego's feature grid, in [0, 1]
    world_from_ego: np.ndarray  # (4, 4) the ego's LiDAR pose when it made the request
    stamp: int  # the ego frame it came from
    received_ns: int  # wall clock


@dataclass(frozen=True)
class Refusal:
    kind: str  # request_topic, request_range
    reason: str


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a[:2, 3] - b[:2, 3]))


class RequestBook:
    def __init__(self, comm_range: float, timeout_ns: int, max_egos: int, capacity: int = 64):
        self.comm_range, self.timeout_ns, self.max_egos, self.capacity = comm_range, timeout_ns, max_egos, capacity
        self._requests: dict[int, Request] = {}  # ego -> its latest request, oldest first
        self._topics: dict[int, str] = {}  # ego -> the topic its requests are taken from

    def __len__(self) -> int:
        return len(self._requests)

    def offer(
        self,
        topic: str,
        ego: int,
        request: Request,
        world_from_lidar: np.ndarray | None,
        has_publisher: Callable[[str], bool],
    ) -> Refusal | None:
        """Keeps `request` as `ego`'s latest, or says why not. world_from_lidar: the vehicle's newest pose, if known."""
        self.expire(request.received_ns)
        bound = self._topics.get(ego)
        if bound is not None and bound != topic:
            if has_publisher(bound):
                return Refusal("request_topic", f"ego {ego}'s request maps come on {bound}; refused from another topic")
            self._requests.pop(ego, None)  # its publisher is gone: the id is free
        if (
            world_from_lidar is not None
            and (d := _distance(request.world_from_ego, world_from_lidar)) > self.comm_range
        ):
            return Refusal("request_range", f"ego {ego} is {d:.0f} m away, beyond comm_range {self.comm_range:g} m")
        self._requests.pop(ego, None)  # re-inserted last: insertion order is arrival order
        self._requests[ego], self._topics[ego] = request, topic
        while len(self._requests) > self.capacity:
            drop = (
                next(iter(self._requests))
                if world_from_lidar is None
                else max(self._requests, key=lambda e: _distance(self._requests[e].world_from_ego, world_from_lidar))
            )
            del self._requests[drop], self._topics[drop]
        return None

    def expire(self, now_ns: int) -> None:
        """Forgets every request older than the timeout (and the topic its ego was bound to)."""
        for ego in [e for e, r in self._requests.items() if now_ns - r.received_ns > self.timeout_ns]:
            del self._requests[ego], self._topics[ego]

    def serving(self, now_ns: int, world_from_lidar: np.ndarray) -> dict[int, Request]:
        """The requests a frame at `world_from_lidar` answers: fresh, within comm_range, the max_egos nearest."""
        self.expire(now_ns)
        near = sorted(
            (d, ego)
            for ego, r in self._requests.items()
            if (d := _distance(r.world_from_ego, world_from_lidar)) <= self.comm_range
        )
        return {ego: self._requests[ego] for _, ego in near[: self.max_egos]}
