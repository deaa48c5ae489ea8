"""Model inputs from sensor data, shared by training, offline evaluation and the vehicle node (ROS-free).

One function builds a vehicle half's camera inputs and one its LiDAR input, so
the graph and the offline path feed the model identical tensors.
"""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.common.frames import CameraFrame
from co3sop_nodes.common.geometry import OPTICAL_FROM_BODY
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.kernels import point_occupancy as point_kernel
from co3sop_nodes.model.config import ModelConfig


def camera_inputs(cameras: list[CameraFrame], world_from_lidar: np.ndarray, image_size: tuple[int, int]):
    """(images (N, 3, H, W) uint8, lidar2img (N, 4, 4) float32) at `image_size` = (W, H)."""
    width, height = image_size
    images, projections = [], []
    lidar_to_world = world_from_lidar
    for cam in cameras:
        h0, w0 = cam.rgb.shape[:2]
        rgb = (
            cam.rgb
            if (w0, h0) == (width, height)
            else np.asarray(Image.fromarray(cam.rgb).resize((width, height), Image.BILINEAR))
        )
        images.append(rgb.transpose(2, 0, 1))
        k = np.eye(4)
        k[:3, :3] = np.diag([width / w0, height / h0, 1.0]) @ cam.intrinsics
        camera_from_lidar = np.linalg.inv(cam.world_from_camera) @ lidar_to_world
        projections.append(k @ OPTICAL_FROM_BODY @ camera_from_lidar)
    return np.stack(images), np.stack(projections).astype(np.float32)


def lidar_occupancy_reference(points: np.ndarray, grid: GridSpec) -> np.ndarray:
    """The definition of `lidar_occupancy`, in NumPy."""
    x = (points[:, :3] - np.asarray(grid.origin)) / grid.voxel_size  # (N, 3) in voxels
    ok = (x >= 0) & (x < np.asarray(grid.dims))  # (N, 3), false for NaN: per axis, columns combined below
    i, j, k = x[ok[:, 0] & ok[:, 1] & ok[:, 2]].astype(np.int64).T  # truncation is floor at x >= 0
    _, ny, nz = grid.dims
    occ = np.zeros(grid.dims, np.uint8)
    occ.reshape(-1)[(i * ny + j) * nz + k] = 1
    return occ[None]


def lidar_occupancy(points: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(1, X, Y, Z) uint8: 1 where a LiDAR point (LiDAR frame, REP-103) falls in a voxel of `grid`: by the compiled
    kernel for float32 points where it compiles, the same voxels as `lidar_occupancy_reference` (tested).

    uint8, not float: a training split holds thousands of scans in memory (1.5 MB each at 51.2 m, not 6).
    """
    if point_kernel.fits(points) and point_kernel.available():
        return point_kernel.point_occupancy(points, grid)[None]
    return lidar_occupancy_reference(points, grid)


def hits_in_ego_grid(occupancy: np.ndarray, ego_from_neighbour: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(X, Y, Z) bool: the ego-grid voxels a neighbour's occupied voxels (its own grid, same spec) fall in.

    The neighbour's occupied voxels' centres are carried into the ego's LiDAR frame and binned as the ego's own
    returns are, so they land within half a voxel of where its returns were.
    """
    centres = (
        np.asarray(grid.origin) + (np.argwhere(occupancy) + 0.5) * grid.voxel_size
    )  # (N, 3), neighbour's LiDAR frame
    moved = centres @ ego_from_neighbour[:3, :3].T + ego_from_neighbour[:3, 3]
    return lidar_occupancy(moved, grid)[0].astype(bool)


def merged_occupancy(
    ego: np.ndarray, others: list[np.ndarray], neighbour_from_ego: np.ndarray, grid: GridSpec
) -> np.ndarray:
    """(1, X, Y, Z) uint8: the ego's LiDAR occupancy with its collaborators' joined in, for an early-fusion model.

    ego and others[a]: (1, X, Y, Z) uint8 occupancy, each in its own agent's LiDAR frame; neighbour_from_ego: (A, 4, 4).
    Each collaborator's scan reaches the ego as its occupied voxels (1 bit per voxel of its own grid).
    """
    merged = ego[0].astype(bool)  # (X, Y, Z)
    for occupancy, n_from_e in zip(others, neighbour_from_ego):
        merged |= hits_in_ego_grid(occupancy[0], np.linalg.inv(n_from_e), grid)
    return merged.astype(np.uint8)[None]


def to_batch(inputs: dict, device: torch.device | str = "cpu") -> dict:
    """One agent's numpy inputs -> VehicleHalf keyword tensors with a batch dimension of 1, on `device`."""
    return {k: torch.from_numpy(v)[None].to(device) for k, v in inputs.items()}


def sensor_inputs(cfg: ModelConfig, world_from_lidar: np.ndarray, cameras=(), points: np.ndarray | None = None) -> dict:
    """One agent's numpy VehicleHalf inputs from sensor messages' contents, as the vehicle node and bag evaluation build them.

    cameras: (name, rgb (H, W, 3) uint8, intrinsics (3, 3), lidar_from_optical (4, 4)) per camera; points: (N, 3) LiDAR
    frame.
    """
    if cfg.modality == "lidar":
        return {"occupancy": lidar_occupancy(points, cfg.grid)}
    frames = []
    for name, rgb, k, lidar_from_optical in cameras:
        k = np.asarray(k, np.float64)
        if not (np.isfinite(k).all() and np.isfinite(lidar_from_optical).all()) or min(rgb.shape[:2]) == 0:
            raise Co3sopError(f"{name}: NaN or infinite intrinsics or mount, or an empty image")
        if not (k[0, 0] > 0 and k[1, 1] > 0 and np.array_equal(k[2], [0.0, 0.0, 1.0])):
            raise Co3sopError(f"{name}: intrinsics are not a pinhole camera's (fx, fy > 0, last row 0 0 1)")
        # the camera's body frame (x forward, y left, z up), which camera_inputs takes, from its optical frame
        frames.append(CameraFrame(name, world_from_lidar @ lidar_from_optical @ OPTICAL_FROM_BODY, k, rgb))
    try:
        images, lidar2img = camera_inputs(frames, world_from_lidar, cfg.image_size)
    except np.linalg.LinAlgError:
        raise Co3sopError("a camera mount is singular (not a rigid transform)") from None
    if not np.isfinite(lidar2img).all():  # a singular mount can still invert to huge values
        raise Co3sopError("camera projections are not finite (degenerate intrinsics or mounts)")
    return {"images": images, "lidar2img": lidar2img}
