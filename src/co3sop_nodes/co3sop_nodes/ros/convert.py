"""Conversion between co3sop_msgs messages and the ROS-free core's dataclasses."""

from __future__ import annotations

import importlib

import numpy as np
from builtin_interfaces.msg import Time
from co3sop_msgs.msg import GridSpec as GridSpecMsg
from co3sop_msgs.msg import RequestMap, SemanticOccupancy, VoxelFeatures
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose as PoseMsg
from sensor_msgs.msg import Image, PointCloud2, PointField

from co3sop_nodes.viz.cloud import CLOUD_DTYPE, CLOUD_FIELDS, cloud_xyz
from co3sop_nodes.v2x.codec import EncodedFeatures, EncodedLabels, EncodedRequest
from co3sop_nodes.common.errors import Co3sopError, DatasetError
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.common.grid import GridSpec


def stamp_to_ns(stamp: Time) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def ns_to_stamp(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def grid_to_msg(grid: GridSpec) -> GridSpecMsg:
    msg = GridSpecMsg(voxel_size=grid.voxel_size, nx=grid.dims[0], ny=grid.dims[1], nz=grid.dims[2])
    msg.origin.x, msg.origin.y, msg.origin.z = grid.origin
    return msg


def grid_from_msg(msg: GridSpecMsg) -> GridSpec:
    """Raises GridError on an invalid grid."""
    return GridSpec((msg.origin.x, msg.origin.y, msg.origin.z), msg.voxel_size, (msg.nx, msg.ny, msg.nz))


def pose_to_msg(pose: Pose) -> PoseMsg:
    msg = PoseMsg()
    msg.position.x, msg.position.y, msg.position.z = pose.position
    o = msg.orientation
    o.x, o.y, o.z, o.w = pose.orientation
    return msg


def pose_from_msg(msg: PoseMsg) -> Pose:
    p, o = msg.position, msg.orientation
    return Pose((p.x, p.y, p.z), (o.x, o.y, o.z, o.w))


def features_to_msg(enc: EncodedFeatures, *, stamp_ns: int, frame_id: str, agent_id: int, pose: Pose,
                    recipient_id: int | None = None) -> VoxelFeatures:
    """recipient_id: the ego whose request map selected these voxels (None: for every ego)."""
    msg = VoxelFeatures(
        agent_id=agent_id,
        addressed=recipient_id is not None,
        recipient_id=recipient_id or 0,
        lidar_pose=pose_to_msg(pose),
        grid=grid_to_msg(enc.grid),
        channels=enc.channels,
        dtype=enc.dtype,
        codec=enc.codec,
        quant_scale=list(enc.quant_scale),
        quant_offset=list(enc.quant_offset),
        sparse=enc.sparse,
        num_voxels=enc.num_voxels,
        has_confidence=enc.has_confidence,
        voxel_mask_raw_size=enc.voxel_mask_raw_size,
        values_raw_size=enc.values_raw_size,
        confidence_raw_size=enc.confidence_raw_size,
        basis_rank=enc.basis_rank,
        basis=list(enc.basis),
        basis_mean=list(enc.basis_mean),
    )
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    # bytes assign ~100x faster than numpy arrays or lists to uint8[] fields
    msg.voxel_mask, msg.values, msg.confidence = enc.voxel_mask, enc.values, enc.confidence
    return msg


def features_from_msg(msg: VoxelFeatures) -> EncodedFeatures:
    """Raises GridError on an invalid grid; payloads are checked by codec.decode_features."""
    return EncodedFeatures(
        grid=grid_from_msg(msg.grid),
        channels=msg.channels,
        dtype=msg.dtype,
        codec=msg.codec,
        quant_scale=tuple(msg.quant_scale),
        quant_offset=tuple(msg.quant_offset),
        sparse=msg.sparse,
        num_voxels=msg.num_voxels,
        has_confidence=msg.has_confidence,
        voxel_mask=memoryview(msg.voxel_mask),
        values=memoryview(msg.values),
        confidence=memoryview(msg.confidence),
        voxel_mask_raw_size=msg.voxel_mask_raw_size,
        values_raw_size=msg.values_raw_size,
        confidence_raw_size=msg.confidence_raw_size,
        basis_rank=msg.basis_rank,
        basis=tuple(msg.basis),
        basis_mean=tuple(msg.basis_mean),
    )


def request_to_msg(enc: EncodedRequest, *, stamp_ns: int, frame_id: str, agent_id: int, pose: Pose) -> RequestMap:
    msg = RequestMap(agent_id=agent_id, lidar_pose=pose_to_msg(pose), grid=grid_to_msg(enc.grid), codec=enc.codec,
                     need_raw_size=enc.need_raw_size)
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.need = enc.need
    return msg


def request_from_msg(msg: RequestMap) -> EncodedRequest:
    """Raises GridError on an invalid grid; the payload is checked by codec.decode_request."""
    return EncodedRequest(grid_from_msg(msg.grid), msg.codec, memoryview(msg.need), msg.need_raw_size)


def labels_to_msg(enc: EncodedLabels, *, stamp_ns: int, frame_id: str, agent_id: int) -> SemanticOccupancy:
    msg = SemanticOccupancy(
        agent_id=agent_id,
        grid=grid_to_msg(enc.grid),
        num_classes=enc.num_classes,
        codec=enc.codec,
        labels_raw_size=enc.labels_raw_size,
        confidence_raw_size=enc.confidence_raw_size,
    )
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.labels, msg.confidence = enc.labels, enc.confidence
    return msg


def labels_from_msg(msg: SemanticOccupancy) -> EncodedLabels:
    """Raises GridError on an invalid grid; payloads are checked by codec.decode_labels."""
    return EncodedLabels(
        grid=grid_from_msg(msg.grid),
        num_classes=msg.num_classes,
        codec=msg.codec,
        labels=memoryview(msg.labels),
        labels_raw_size=msg.labels_raw_size,
        confidence=memoryview(msg.confidence),
        confidence_raw_size=msg.confidence_raw_size,
    )


def message_class(msgtype: str):
    """'pkg/msg/Type' -> the generated Python class (as ros2 bag play finds it)."""
    package, _, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        raise DatasetError(f"message type {msgtype} is not installed: source the workspace that defines it") from None


def cloud_to_msg(cloud: np.ndarray, *, stamp_ns: int, frame_id: str) -> PointCloud2:
    """A cloud.CLOUD_DTYPE array -> PointCloud2 (x, y, z, rgb, label)."""
    msg = PointCloud2(height=1, width=len(cloud), is_bigendian=False, point_step=CLOUD_DTYPE.itemsize,
                      row_step=CLOUD_DTYPE.itemsize * len(cloud), is_dense=True)
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.fields = [PointField(name=name, offset=offset, datatype=datatype, count=1) for name, offset, datatype in CLOUD_FIELDS]
    msg.data = cloud.tobytes()
    return msg


def cloud_points(msg: PointCloud2) -> np.ndarray:
    """(N, 3) float32 x, y, z of a PointCloud2; raises DatasetError on a layout without them."""
    fields = [(f.name, f.offset, f.datatype) for f in msg.fields]
    return cloud_xyz(bytes(msg.data), fields, msg.point_step, msg.width, msg.height)


def image_rgb(msg: Image, topic: str) -> np.ndarray:
    """(H, W, 3) uint8 view of an rgb8 Image (rows may be padded to `step`); raises Co3sopError naming the topic otherwise."""
    if msg.encoding != "rgb8":
        raise Co3sopError(f"{topic}: encoding {msg.encoding!r}, expected rgb8")
    data = np.frombuffer(msg.data, np.uint8)
    if msg.step < 3 * msg.width or len(data) < msg.step * msg.height:
        raise Co3sopError(f"{topic}: {len(data)} bytes do not hold {msg.height} rows of {msg.step} bytes")
    return data[: msg.step * msg.height].reshape(msg.height, msg.step)[:, : 3 * msg.width].reshape(msg.height, msg.width, 3)


def diagnostics_msg(stamp_ns: int, name: str, hardware_id: str, level: bytes, message: str, values: dict) -> DiagnosticArray:
    """One DiagnosticStatus (values as strings) in a DiagnosticArray, as /diagnostics carries."""
    status = DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                              values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
    msg = DiagnosticArray(status=[status])
    msg.header.stamp = ns_to_stamp(stamp_ns)
    return msg
