"""The ego's ground truth as a viewer draws it: the coloured PointCloud2 the ego publishes for its prediction,
made from the ground truth the recorder stores, so a recording shows prediction and truth side by side in
Foxglove or RViz2 (ROS-free: raw CDR in, raw CDR out, through rosbags).

Only an ego's own ground truth at its prediction's range is drawn (every CAV's three ranges would multiply a
recording's size): a ground-truth message waits (at most `keep` per CAV and range) until a prediction says
which CAV is an ego at which range, and from then on is converted as it comes. The points go beside that
ego's prediction: /ego/ground_truth/points for /ego/occupancy, /cav_3/ego/ground_truth/points for
/cav_3/ego/occupancy (every CAV an ego).
"""

from __future__ import annotations

from collections import deque

from co3sop_nodes.common import topics
from co3sop_nodes.common.errors import DatasetError, exception_line
from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.data.bags import occupancy_labels, typestore
from co3sop_nodes.messages import OCCUPANCY, RosbagsTypes, point_cloud_msg, stamp_ns
from co3sop_nodes.messages.sensors import POINT_CLOUD
from co3sop_nodes.viz.cloud import occupancy_cloud


def truth_key(topic: str) -> tuple[int, str] | None:
    """(CAV, range) of a ground-truth topic (/cav_3/ground_truth/occupancy_50m -> (3, "51.2m")), None for another."""
    cav = topics.split_cav_topic(topic)
    if cav is None:
        return None
    return next(((cav[0], r) for r in BENCHMARK_RANGES if topic == topics.ground_truth(cav[0], r)), None)


class TruthPoints:
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
        """An ego's prediction (on `topic`): (topic, PointCloud2 CDR) of the ground truth that waited for it."""
        msg = self._decode(raw, topic)
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
            return []
        shown = self._egos[key] = topic.removesuffix(topics.EGO_OCCUPANCY) + topics.EGO_TRUTH_POINTS
        return [(shown, self._points(r, "waiting ground truth")) for r in self._waiting.pop(key, [])]

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
        msg = self._decode(raw, what)
        labels, grid = occupancy_labels(msg)
        cloud = occupancy_cloud(labels, grid)
        points = point_cloud_msg(self._types, cloud, stamp_ns=stamp_ns(msg.header.stamp), frame_id=msg.header.frame_id)
        return bytes(self._store.serialize_cdr(points, POINT_CLOUD))
