"""rosbag2 bags (MCAP storage) of CAV frames, written and read with rosbags (ROS-free).

A bag holds, per CAV, REP-103 frames and standard types (topic names in
common/topics.py): camera images + CameraInfo, PointCloud2, the LiDAR's PoseStamped
in `map`, /tf and /tf_static, and the ground truth of each benchmark range as
co3sop_msgs/SemanticOccupancy. The co3sop_msgs definitions are embedded in the
MCAP schemas, so `ros2 bag`, Foxglove and rosbags read the bag without this
package. A bag is written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import os
import shutil
from collections import defaultdict
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from co3sop_nodes.common import topics
from co3sop_nodes.common.classes import NUM_CLASSES
from co3sop_nodes.common.errors import Co3sopError, DatasetError, exception_line
from co3sop_nodes.common.frames import CavFrame
from co3sop_nodes.common.geometry import OPTICAL_FROM_BODY, Pose
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.common.transforms import StaticTransforms
from co3sop_nodes.messages import (
    OCCUPANCY,
    RosbagsTypes,
    camera_info_msg,
    header_stamp_ns,
    image_msg,
    intrinsics_of,
    occupancy_msg,
    occupancy_of,
    point_cloud_msg,
    points_of,
    pose_of,
    pose_stamped_msg,
    rgb_of,
    tf_msg,
    transform_msg,
    transforms_of,
    xyz_of,
)
from co3sop_nodes.messages.co3sop import TYPES as CO3SOP_TYPES
from co3sop_nodes.messages.sensors import CAMERA_INFO, IMAGE, LIDAR_POINTS, POINT_CLOUD
from co3sop_nodes.v2x.codec import decode_labels, encode_labels

TF = "tf2_msgs/msg/TFMessage"
_RANGE_OF_SUFFIX = {suffix: name for name, suffix in topics.RANGE_SUFFIX.items()}
_NEVER = QosTime(sec=0x7FFFFFFF, nsec=0xFFFFFFFF)
_LATCHED = [
    Qos(
        QosHistory.KEEP_LAST,
        1,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL,
        _NEVER,
        _NEVER,
        QosLiveliness.AUTOMATIC,
        _NEVER,
        False,
    )
]


def msg_dir() -> Path:
    """The installed co3sop_msgs .msg files (found on AMENT_PREFIX_PATH, as ROS tools find them)."""
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        candidate = Path(prefix, "share", "co3sop_msgs", "msg")
        if (candidate / "GridSpec.msg").is_file():
            return candidate
    raise DatasetError("co3sop_msgs is not on AMENT_PREFIX_PATH: source ros2_ws/env.sh (or your workspace) first")


def typestore():
    """Jazzy's standard types plus co3sop_msgs, parsed from the installed .msg files."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for msgtype in CO3SOP_TYPES:
        text = (msg_dir() / f"{msgtype.rsplit('/', 1)[1]}.msg").read_text()
        store.register(get_types_from_msg(text, msgtype))
    return store


COMPRESS_HELP = (
    "bags with zstd chunks (about a third of the size; a player spends about 4 ms more CPU a frame of 3 CAVs "
    "decompressing them); default uncompressed, as ros2 bag record writes"
)


class BagWriter:
    """Writes CAV frames to a rosbag2 MCAP bag; use as a context manager. Uncompressed by default, as `ros2 bag
    record` writes: a player then reads a frame's messages without decompressing every chunk (about 4 ms of CPU a
    frame of 3 CAVs); `compress`: zstd chunks, about a third of the size on disk."""

    def __init__(self, path: Path, compress: bool = False):
        self.path = Path(path)
        # written as <parent>/.<name>.partial/<name> (the MCAP file takes the folder's name), moved when complete
        self._partial = self.path.parent / f".{self.path.name}.partial"
        if self._partial.exists():
            shutil.rmtree(self._partial)
        self._partial.mkdir(parents=True)
        self.ts = typestore()
        self.types = RosbagsTypes(self.ts)
        self._writer = Writer(self._partial / self.path.name, version=9, storage_plugin=StoragePlugin.MCAP)
        if compress:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._connections: dict[str, object] = {}
        self._static_sent: set[int] = set()
        self.messages = 0

    def __enter__(self) -> BagWriter:
        self._writer.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._writer.close()
        if exc_type is None:
            if self.path.exists():
                shutil.rmtree(self.path)
            (self._partial / self.path.name).rename(self.path)
        # nothing half-written is left looking complete
        shutil.rmtree(self._partial, ignore_errors=True)

    def _points(self, stamp_ns: int, frame: CavFrame):
        cloud = np.zeros(len(frame.points), LIDAR_POINTS)
        cloud["x"], cloud["y"], cloud["z"] = frame.points.T
        cloud["intensity"] = frame.intensity
        if frame.point_labels is not None:
            cloud["label"] = frame.point_labels
        return point_cloud_msg(self.types, cloud, stamp_ns=stamp_ns, frame_id=topics.lidar_frame(frame.cav_id))

    def _occupancy(self, stamp_ns: int, frame: CavFrame, range_name: str):
        enc = encode_labels(frame.labels[range_name], BENCHMARK_RANGES[range_name], NUM_CLASSES)
        return occupancy_msg(
            self.types, enc, stamp_ns=stamp_ns, frame_id=topics.lidar_frame(frame.cav_id), agent_id=frame.cav_id
        )

    # --- writing -----------------------------------------------------------------------------------

    def _write(self, topic: str, msgtype: str, stamp_ns: int, msg, latched: bool = False) -> None:
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self.ts, offered_qos_profiles=_LATCHED if latched else ()
            )
        self._writer.write(self._connections[topic], stamp_ns, self.ts.serialize_cdr(msg, msgtype))
        self.messages += 1

    def write(self, frames: Sequence[CavFrame]) -> None:
        """One timestamp: every CAV's frame."""
        types, tfs = self.types, []
        for frame in frames:
            stamp, cav = frame.stamp_ns, frame.cav_id
            if cav not in self._static_sent:
                self._write(topics.TF_STATIC, TF, stamp, tf_msg(types, self._mounts(frame)), latched=True)
                self._static_sent.add(cav)
            tfs.append(
                transform_msg(types, stamp, topics.WORLD_FRAME, topics.base_frame(cav), frame.world_from_vehicle)
            )
            pose = pose_stamped_msg(types, stamp, topics.WORLD_FRAME, Pose.from_matrix(frame.world_from_lidar))
            self._write(topics.lidar_pose(cav), "geometry_msgs/msg/PoseStamped", stamp, pose)
            self._write(topics.lidar_points(cav), POINT_CLOUD, stamp, self._points(stamp, frame))
            for cam in frame.cameras:
                optical = topics.camera_optical_frame(cav, cam.name)
                at = {"stamp_ns": stamp, "frame_id": optical}
                h, w = cam.rgb.shape[:2]
                self._write(topics.camera_image(cav, cam.name), IMAGE, stamp, image_msg(types, cam.rgb, "rgb8", **at))
                self._write(
                    topics.camera_info(cav, cam.name),
                    CAMERA_INFO,
                    stamp,
                    camera_info_msg(types, cam.intrinsics, w, h, **at),
                )
                if cam.depth is not None:
                    self._write(
                        topics.camera_depth(cav, cam.name), IMAGE, stamp, image_msg(types, cam.depth, "32FC1", **at)
                    )
                if cam.semantic is not None:
                    self._write(
                        topics.camera_semantic(cav, cam.name),
                        IMAGE,
                        stamp,
                        image_msg(types, cam.semantic, "mono8", **at),
                    )
            for range_name in frame.labels:
                self._write(
                    topics.ground_truth(cav, range_name), OCCUPANCY, stamp, self._occupancy(stamp, frame, range_name)
                )
        if tfs:
            self._write(topics.TF, TF, frames[0].stamp_ns, tf_msg(types, tfs))

    def _mounts(self, frame: CavFrame) -> list:
        """Static transforms of one CAV: base_link -> lidar -> camera body -> camera optical."""
        cav, stamp, types = frame.cav_id, frame.stamp_ns, self.types
        lidar_from_world = np.linalg.inv(frame.world_from_lidar)
        base_from_lidar = np.linalg.inv(frame.world_from_vehicle) @ frame.world_from_lidar
        out = [transform_msg(types, stamp, topics.base_frame(cav), topics.lidar_frame(cav), base_from_lidar)]
        for cam in frame.cameras:
            body, optical = topics.camera_frame(cav, cam.name), topics.camera_optical_frame(cav, cam.name)
            out.append(
                transform_msg(types, stamp, topics.lidar_frame(cav), body, lidar_from_world @ cam.world_from_camera)
            )
            out.append(transform_msg(types, stamp, body, optical, np.linalg.inv(OPTICAL_FROM_BODY)))
        return out


def occupancy_labels(msg) -> tuple[np.ndarray, GridSpec]:
    """Decoded (nx, ny, nz) labels and grid of a SemanticOccupancy (its confidence, if any, left undecoded)."""
    enc = occupancy_of(msg)
    return decode_labels(enc, with_confidence=False).labels, enc.grid


# --- reading ---------------------------------------------------------------------------------------


class BagReader:
    """A rosbag2 bag folder or an MCAP recording read with rosbags, damage reported as DatasetError.

    rosbags raises many types for a damaged file (bad magic, a truncated or
    corrupt zstd chunk, metadata.yaml that is not YAML, a message that does not
    deserialise): every one becomes one DatasetError naming the file and, for a
    message, its topic and time. Use as a context manager.
    """

    def __init__(self, path: Path, what: str = "bag", hint: str = "", store=None):
        self.path, self._what, self._hint = Path(path), what, hint
        try:
            self._reader = AnyReader([self.path], default_typestore=store or get_typestore(Stores.ROS2_JAZZY))
        except Exception as exc:  # see the class docstring
            raise self._damaged(exc) from None

    def _damaged(self, exc: BaseException) -> DatasetError:
        return DatasetError(f"{self.path}: damaged or not a {self._what}: {exception_line(exc)}{self._hint}")

    def open(self) -> None:
        try:
            self._reader.open()
        except Exception as exc:
            raise self._damaged(exc) from None

    def close(self) -> None:
        self._reader.close()

    def __enter__(self) -> BagReader:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def connections(self) -> list:
        return self._reader.connections

    @property
    def message_count(self) -> int:
        return self._reader.message_count

    @property
    def start_time(self) -> int:
        return self._reader.start_time

    @property
    def end_time(self) -> int:
        return self._reader.end_time

    def messages(self, connections: Sequence | None = None, start: int | None = None) -> Iterator[tuple]:
        """(connection, log time ns, raw CDR) in log-time order; of every connection when `connections` is None
        (an empty list gives none, where rosbags would give all)."""
        if connections is not None and not connections:
            return
        it = self._reader.messages(connections=connections or (), start=start)
        while True:
            try:
                item = next(it)
            except StopIteration:
                return
            except Exception as exc:  # a chunk that does not decompress, a truncated record...
                raise self._damaged(exc) from None
            yield item

    def deserialize(self, raw, conn, stamp: int):
        """The message, or a DatasetError naming its topic and log time."""
        try:
            return self._reader.deserialize(raw, conn.msgtype)
        except Exception as exc:
            raise DatasetError(
                f"{self.path}: {conn.topic} at {stamp} ns: not a valid {conn.msgtype} ({exception_line(exc)})"
            ) from None

    @contextmanager
    def about(self, conn, stamp: int):
        """Errors reading one message's content (a bad payload, a point layout that does not fit) name the file,
        the topic and the time."""
        try:
            yield
        except DatasetError:
            raise
        except (Co3sopError, ValueError, TypeError, IndexError, KeyError) as exc:
            raise DatasetError(f"{self.path}: {conn.topic} at {stamp} ns: {exception_line(exc)}") from None


def open_reader(path: Path) -> BagReader:
    path = Path(path)
    if not (path / "metadata.yaml").is_file():
        raise DatasetError(f"{path}: not a rosbag2 bag (no metadata.yaml)")
    return BagReader(path, "rosbag2 bag")


def open_recording(path: Path) -> BagReader:
    """A `recorder` MCAP file (one file, no metadata.yaml), read with co3sop_msgs' types; not yet opened."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such recording")
    return BagReader(path, "MCAP recording", f"; if the recorder crashed, run `recover {path}` first", typestore())


def read_static_transforms(path: Path) -> StaticTransforms:
    """Every /tf_static transform of a bag (the sensor mounts)."""
    tree = StaticTransforms()
    with open_reader(path) as reader:
        for conn, stamp, raw in reader.messages(
            connections=[c for c in reader.connections if c.topic == topics.TF_STATIC]
        ):
            for parent, child, parent_from_child in transforms_of(reader.deserialize(raw, conn, stamp)):
                tree.add(parent, child, parent_from_child)
    return tree


def read_frames(path: Path) -> Iterator[tuple[int, dict[int, dict]]]:
    """Per sensor stamp: {cav_id: {"pose", "points", "intensity", "labels", "cameras", "intrinsics", "optical_frames"}} from a bag.

    Meant for checks and offline evaluation; the player replays raw messages.
    """
    by_stamp: dict[int, dict[int, dict]] = defaultdict(lambda: defaultdict(lambda: {"cameras": {}, "labels": {}}))
    with open_reader(path) as reader:
        for conn, log_stamp, raw in reader.messages():
            cav = topics.split_cav_topic(conn.topic)
            if cav is None:
                continue
            msg = reader.deserialize(raw, conn, log_stamp)
            with reader.about(conn, log_stamp):
                _read_part(by_stamp[header_stamp_ns(msg)][cav[0]], cav[1].split("/"), msg)
    for stamp in sorted(by_stamp):
        yield stamp, {cav: dict(v) for cav, v in by_stamp[stamp].items()}


def read_scans(path: Path, count: int) -> list[np.ndarray]:
    """The first `count` LiDAR scans of a bag's CAVs (fewer where it holds fewer), in the bag's order: (N, 3) each, in
    its sensor's frame, as a vehicle node reads them."""
    scans = []
    with open_reader(path) as reader:
        lidar = [c for c in reader.connections if (topics.split_cav_topic(c.topic) or (0, ""))[1] == "lidar/points"]
        for conn, stamp, raw in reader.messages(connections=lidar):
            if len(scans) == count:
                break
            with reader.about(conn, stamp):
                scans.append(xyz_of(reader.deserialize(raw, conn, stamp)))
    return scans


def _read_part(entry: dict, parts: list[str], msg) -> None:
    """One CAV message into its frame's entry (read_frames); parts: its topic relative to the CAV's namespace."""
    if parts == ["lidar", "pose"]:
        entry["pose"] = pose_of(msg.pose).matrix()
    elif parts == ["lidar", "points"]:
        cloud = points_of(msg, ("x", "y", "z", "intensity"))
        entry["points"] = np.column_stack([cloud["x"], cloud["y"], cloud["z"]])
        entry["intensity"] = cloud["intensity"].copy()
    elif parts[0] == "ground_truth":
        entry["labels"][_RANGE_OF_SUFFIX[parts[1].removeprefix("occupancy_")]] = occupancy_labels(msg)[0]
    elif parts[-1] == "image_raw":
        entry["cameras"][parts[0]] = rgb_of(msg, parts[0])
        entry.setdefault("optical_frames", {})[parts[0]] = msg.header.frame_id
    elif parts[-1] == "camera_info":
        entry.setdefault("intrinsics", {})[parts[0]] = intrinsics_of(msg)
