"""co3sop_msgs: GridSpec, VoxelFeatures, VoxelScan, RequestMap, SemanticOccupancy <-> the codecs' encoded payloads
(ROS-free adapters; see backend.py). Payloads are checked where they are decoded (co3sop_nodes.v2x.codec)."""

from __future__ import annotations

from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.messages.backend import MessageTypes, octets_of
from co3sop_nodes.messages.std import header_msg, pose_msg
from co3sop_nodes.v2x.codec import EncodedFeatures, EncodedLabels, EncodedRequest
from co3sop_nodes.v2x.scan import EncodedScan

GRID = "co3sop_msgs/msg/GridSpec"
FEATURES = "co3sop_msgs/msg/VoxelFeatures"
SCAN = "co3sop_msgs/msg/VoxelScan"
REQUEST = "co3sop_msgs/msg/RequestMap"
OCCUPANCY = "co3sop_msgs/msg/SemanticOccupancy"
TYPES = (GRID, FEATURES, SCAN, REQUEST, OCCUPANCY)


def grid_msg(types: MessageTypes, grid: GridSpec):
    x, y, z = grid.origin
    return types.make(
        GRID,
        origin=types.make("geometry_msgs/msg/Point", x=x, y=y, z=z),
        voxel_size=grid.voxel_size,
        nx=grid.dims[0],
        ny=grid.dims[1],
        nz=grid.dims[2],
    )


def grid_of(msg) -> GridSpec:
    """Raises GridError on an invalid grid."""
    return GridSpec((msg.origin.x, msg.origin.y, msg.origin.z), msg.voxel_size, (msg.nx, msg.ny, msg.nz))


def features_msg(
    types: MessageTypes,
    enc: EncodedFeatures,
    *,
    stamp_ns: int,
    frame_id: str,
    agent_id: int,
    pose: Pose,
    recipient_id: int | None = None,
):
    """recipient_id: the ego whose request map selected these voxels (None: for every ego)."""
    return types.make(
        FEATURES,
        header=header_msg(types, stamp_ns, frame_id),
        agent_id=agent_id,
        addressed=recipient_id is not None,
        recipient_id=recipient_id or 0,
        lidar_pose=pose_msg(types, pose),
        grid=grid_msg(types, enc.grid),
        channels=enc.channels,
        dtype=enc.dtype,
        codec=enc.codec,
        quant_scale=types.sequence(enc.quant_scale, "float32"),
        quant_offset=types.sequence(enc.quant_offset, "float32"),
        basis_rank=enc.basis_rank,
        basis=types.sequence(enc.basis, "float32"),
        basis_mean=types.sequence(enc.basis_mean, "float32"),
        learned_code=enc.learned_code,
        sparse=enc.sparse,
        num_voxels=enc.num_voxels,
        voxel_mask=types.octets(enc.voxel_mask),
        values=types.octets(enc.values),
        has_confidence=enc.has_confidence,
        confidence=types.octets(enc.confidence),
        voxel_mask_raw_size=enc.voxel_mask_raw_size,
        values_raw_size=enc.values_raw_size,
        confidence_raw_size=enc.confidence_raw_size,
    )


def features_of(msg) -> EncodedFeatures:
    """Raises GridError on an invalid grid."""
    return EncodedFeatures(
        grid=grid_of(msg.grid),
        channels=msg.channels,
        dtype=msg.dtype,
        codec=msg.codec,
        quant_scale=tuple(msg.quant_scale),
        quant_offset=tuple(msg.quant_offset),
        sparse=msg.sparse,
        num_voxels=msg.num_voxels,
        has_confidence=msg.has_confidence,
        voxel_mask=octets_of(msg.voxel_mask),
        values=octets_of(msg.values),
        confidence=octets_of(msg.confidence),
        voxel_mask_raw_size=msg.voxel_mask_raw_size,
        values_raw_size=msg.values_raw_size,
        confidence_raw_size=msg.confidence_raw_size,
        basis_rank=msg.basis_rank,
        basis=tuple(msg.basis),
        basis_mean=tuple(msg.basis_mean),
        learned_code=msg.learned_code,
    )


def scan_msg(types: MessageTypes, enc: EncodedScan, *, stamp_ns: int, frame_id: str, agent_id: int, pose: Pose):
    return types.make(
        SCAN,
        header=header_msg(types, stamp_ns, frame_id),
        agent_id=agent_id,
        lidar_pose=pose_msg(types, pose),
        grid=grid_msg(types, enc.grid),
        codec=enc.codec,
        num_voxels=enc.num_voxels,
        occupancy=types.octets(enc.occupancy),
        occupancy_raw_size=enc.occupancy_raw_size,
    )


def scan_of(msg) -> EncodedScan:
    """Raises GridError on an invalid grid."""
    return EncodedScan(
        grid=grid_of(msg.grid),
        codec=msg.codec,
        num_voxels=msg.num_voxels,
        occupancy=octets_of(msg.occupancy),
        occupancy_raw_size=msg.occupancy_raw_size,
    )


def request_msg(types: MessageTypes, enc: EncodedRequest, *, stamp_ns: int, frame_id: str, agent_id: int, pose: Pose):
    return types.make(
        REQUEST,
        header=header_msg(types, stamp_ns, frame_id),
        agent_id=agent_id,
        lidar_pose=pose_msg(types, pose),
        grid=grid_msg(types, enc.grid),
        codec=enc.codec,
        need=types.octets(enc.need),
        need_raw_size=enc.need_raw_size,
        levels=enc.levels,
    )


def request_of(msg) -> EncodedRequest:
    """Raises GridError on an invalid grid."""
    return EncodedRequest(grid_of(msg.grid), msg.codec, octets_of(msg.need), msg.need_raw_size, msg.levels)


def occupancy_msg(types: MessageTypes, enc: EncodedLabels, *, stamp_ns: int, frame_id: str, agent_id: int):
    return types.make(
        OCCUPANCY,
        header=header_msg(types, stamp_ns, frame_id),
        agent_id=agent_id,
        grid=grid_msg(types, enc.grid),
        num_classes=enc.num_classes,
        codec=enc.codec,
        labels=types.octets(enc.labels),
        labels_raw_size=enc.labels_raw_size,
        confidence=types.octets(enc.confidence),
        confidence_raw_size=enc.confidence_raw_size,
    )


def occupancy_of(msg) -> EncodedLabels:
    """Raises GridError on an invalid grid."""
    return EncodedLabels(
        grid=grid_of(msg.grid),
        num_classes=msg.num_classes,
        codec=msg.codec,
        labels=octets_of(msg.labels),
        labels_raw_size=msg.labels_raw_size,
        confidence=octets_of(msg.confidence),
        confidence_raw_size=msg.confidence_raw_size,
    )
