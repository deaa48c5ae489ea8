"""The clouds a recording shows: an ego's prediction and its ground truth as the coloured PointCloud2 the ego
publishes for a live viewer (viz/cloud.py), drawn by the recorder from the label grids it stores, so a recording
shows prediction and truth side by side in Foxglove or RViz2 (ROS-free: raw CDR in, raw CDR out, through rosbags).

The recorder draws the prediction's cloud itself rather than recording the ego's: the ego then publishes its
cloud only while a live viewer subscribes, and a frame's megabytes of points never cross DDS on the ego's
critical path. Only an ego's own ground truth at its prediction's range is drawn (every CAV's three ranges
would multiply a recording's size): a ground-truth message waits (at most `keep` per CAV and range) until a
prediction says which CAV is an ego at which range, and from then on is converted as it comes. The points go
beside that ego's prediction: /ego/occupancy/points and /ego/ground_truth/points for /ego/occupancy,
/cav_3/ego/... for /cav_3/ego/occupancy (every CAV an ego).
"""

from __future__ import annotations

import re
from collections import deque

from co3sop_nodes.common import topics
from co3sop_nodes.common.errors import DatasetError, exception_line
from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.data.bags import occupancy_labels, typestore
from co3sop_nodes.messages import OCCUPANCY, RosbagsTypes, point_cloud_msg, stamp_ns
from co3sop_nodes.messages.sensors import POINT_CLOUD
from co3sop_nodes.viz.cloud import occupancy_cloud


def is_drawn(topic: str) -> bool:
    """A topic whose clouds a recording draws itself (an ego's prediction's or truth's points): never recorded as
    published, so never twice."""
    return _DRAWN.match(topic) is not None


_DRAWN = re.compile(rf"^(/cav_\d+)?({re.escape(topics.EGO_POINTS)}|{re.escape(topics.EGO_TRUTH_POINTS)})$")


def truth_key(topic: str) -> tuple[int, str] | None:
    """(CAV, range) of a ground-truth topic (/cav_3/ground_truth/occupancy_50m -> (3, "51.2m")), None for another."""
    cav = topics.split_cav_topic(topic)
    if cav is None:
        return None
    return next(((cav[0], r) for r in BENCHMARK_RANGES if topic == topics.ground_truth(cav[0], r)), None)


class RecordingClouds:
    def __init__(self, keep: int = 50):
        self._store = typestore()
        self._types = RosbagsTypes(self._store)
        self._egos: dict[tuple[int, str], str] = {}  # (CAV, range) of an ego -> the topic of its truth's points
        self._waiting: dict[tuple[int, str], deque[bytes]] = {}
        self._keep = keep

    def _decode(self, raw: bytes, what: str):
        try:
            return self._store.deserialize_cdr(bytes(raw), OCCUPANCY)
        except Exception as exc:
            raise DatasetError(f"{what}: not a valid SemanticOccupancy ({exception_line(exc)})") from None

    def prediction(self, raw: bytes, topic: str = topics.EGO_OCCUPANCY) -> list[tuple[str, bytes]]:
        """An ego's prediction (on `topic`): (topic, PointCloud2 CDR) of the prediction itself, then of the ground
        truth that waited for it."""
        msg = self._decode(raw, topic)
        ns = topic.removesuffix(topics.EGO_OCCUPANCY)
        drawn = [(ns + topics.EGO_POINTS, self._cloud(msg))]
        grid = msg.grid
        key = next(
            (
                (msg.agent_id, r)
                for r, g in BENCHMARK_RANGES.items()
                if (g.voxel_size, g.dims) == (grid.voxel_size, (grid.nx, grid.ny, grid.nz))
            ),
            None,
        )
        if key is None or key in self._egos:
            return drawn
        shown = self._egos[key] = ns + topics.EGO_TRUTH_POINTS
        return drawn + [(shown, self._points(r, "waiting ground truth")) for r in self._waiting.pop(key, [])]

    def truth(self, topic: str, raw: bytes) -> list[tuple[str, bytes]]:
        """A ground-truth message: (topic, PointCloud2 CDR) when its CAV is an ego at its range, else nothing (yet)."""
        key = truth_key(topic)
        if key is None:
            return []
        if key in self._egos:
            return [(self._egos[key], self._points(raw, topic))]
        self._waiting.setdefault(key, deque(maxlen=self._keep)).append(bytes(raw))
        return []

    def _points(self, raw: bytes, what: str) -> bytes:
        return self._cloud(self._decode(raw, what))

    def _cloud(self, msg) -> bytes:
        labels, grid = occupancy_labels(msg)
        cloud = occupancy_cloud(labels, grid)
        points = point_cloud_msg(self._types, cloud, stamp_ns=stamp_ns(msg.header.stamp), frame_id=msg.header.frame_id)
        return bytes(self._store.serialize_cdr(points, POINT_CLOUD))
