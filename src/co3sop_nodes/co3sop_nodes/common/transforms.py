"""A tree of fixed transforms (what /tf_static carries), looked up between any two frames (ROS-free).

tf2 itself is not needed for mounts that never move: a vehicle node keeps the
static transforms it received and asks for e.g. lidar_from_camera_optical.
Matrices are 4x4 parent_from_child, REP-103.
"""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.errors import DatasetError


class StaticTransforms:
    def __init__(self):
        self._parent: dict[str, tuple[str, np.ndarray]] = {}  # child -> (parent, parent_from_child)

    def add(self, parent: str, child: str, parent_from_child: np.ndarray) -> None:
        self._parent[child] = (parent, np.asarray(parent_from_child, dtype=np.float64))

    def __contains__(self, frame: str) -> bool:
        return frame in self._parent or any(p == frame for p, _ in self._parent.values())

    def _to_root(self, frame: str) -> tuple[list[str], np.ndarray]:
        """(frames from `frame` up to its root, root_from_frame)."""
        chain, m = [frame], np.eye(4)
        while chain[-1] in self._parent:
            parent, parent_from_child = self._parent[chain[-1]]
            if parent in chain:
                raise DatasetError(f"transform loop through {parent!r}")
            m = parent_from_child @ m
            chain.append(parent)
        return chain, m

    def lookup(self, target: str, source: str) -> np.ndarray:
        """target_from_source; raises DatasetError when the two frames are not connected."""
        target_chain, root_from_target = self._to_root(target)
        source_chain, root_from_source = self._to_root(source)
        if target_chain[-1] != source_chain[-1]:
            raise DatasetError(
                f"no transform between {target!r} and {source!r} (have: {', '.join(sorted(self._parent)) or 'none'})"
            )
        return np.linalg.inv(root_from_target) @ root_from_source
