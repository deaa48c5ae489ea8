"""Request maps (Where2comm-style, ROS-free): where an ego is unsure, and that need seen from a neighbour.

An ego requests what its own features are least sure of: request = 1 - its
confidence, on its feature grid (X, Y, Z). A neighbour weighs each of its own
voxels by its confidence times the request at that place, the request warped
into its frame with the affine warp the ego uses for features (0 outside the
ego's grid), and sends the best-weighted voxels its byte budget holds (codec
selection "request"). A request is a frame old when it arrives: the neighbour
moves it by the ego's motion (the transform is taken from the pose the request
was made at to the neighbour's pose now), the world being assumed still.
"""

from __future__ import annotations

import numpy as np
import torch

from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.kernels.warp import warp_with_mask


def request_of(confidence: torch.Tensor) -> np.ndarray:
    """The ego's confidence (1, 1, X, Y, Z) -> its request (X, Y, Z) float32 in [0, 1]."""
    return (1.0 - confidence[0, 0].detach().float().cpu().numpy()).clip(0.0, 1.0).astype(np.float32)


def request_for_neighbour(
    request: np.ndarray, world_from_ego: np.ndarray, world_from_neighbour: np.ndarray, grid: GridSpec
) -> np.ndarray:
    """The ego's request (X, Y, Z) on its feature grid `grid`, made at pose world_from_ego, as the neighbour at
    world_from_neighbour sees it on its own feature grid: (X, Y, Z) float32, 0 where the ego's grid does not reach."""
    ego_from_neighbour = (
        np.linalg.inv(world_from_ego) @ world_from_neighbour
    )  # samples the ego's grid at the neighbour's voxels
    volume = torch.from_numpy(np.ascontiguousarray(request, np.float32))[None, None]
    warped, filled = warp_with_mask(volume, torch.from_numpy(ego_from_neighbour).float()[None], grid)
    return (warped[0, 0] * filled[0, 0]).clamp(0.0, 1.0).numpy()
