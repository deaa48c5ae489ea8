"""Pinhole cameras rendered by ray casting: shaded colour, depth and semantic images.

The colour image is a shaded render: Lambert lighting from a sun with cast
shadows, sky light, each object's own albedo modulated by a procedural texture
(bricks, paving, stripes, noise) evaluated at the world hit point, and distance
haze. Depth (m along the optical axis) and semantic labels (CARLA tags; sky is
13) come from the same rays.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from co3sop_nodes import kernels
from co3sop_nodes.common.classes import LABEL_BY_NAME
from co3sop_nodes.sim import ray_kernel
from co3sop_nodes.sim.raycast import Hits, RayScene

SUN = np.array([0.35, 0.45, 0.82]) / np.linalg.norm([0.35, 0.45, 0.82])  # towards the sun, world
SKY_LABEL = LABEL_BY_NAME["sky"]


@dataclass(frozen=True)
class CameraImages:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32, m along the optical axis; 0 for sky
    semantic: np.ndarray  # (H, W) uint8 labels; 13 (sky) where nothing was hit


def pixel_rays(width: int, height: int, k: np.ndarray) -> np.ndarray:
    """Unit ray directions (H*W, 3) in the camera body frame (x along the view, y left, z up); read-only (cached:
    every camera of a rig shares them)."""
    return _pixel_rays(width, height, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))


@lru_cache(maxsize=8)
def _pixel_rays(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d = np.stack([np.full(u.shape, fx), -(u - cx), -(v - cy) * fx / fy], axis=-1)
    rays = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3)
    rays.setflags(write=False)
    return rays


def _hash(cells: np.ndarray) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) per integer cell (N, 3)."""
    h = (cells[:, 0] * 73856093) ^ (cells[:, 1] * 19349663) ^ (cells[:, 2] * 83492791)
    return ((h * 2654435761) % 4294967296) / 4294967296.0


def _texture(kind: str, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Brightness factor (M,) of a procedural pattern at world points p (M, 3) with normals n."""
    if kind == "bricks":
        # walls: 0.3 m courses of 0.6 m bricks, every other course offset; floors: 0.5 m paving
        horizontal = np.abs(n[:, 2]) > 0.7
        along = np.where(np.abs(n[:, 0]) > np.abs(n[:, 1]), p[:, 1], p[:, 0])
        w = np.where(horizontal, p[:, 1] / 0.5, p[:, 2] / 0.3)
        u = np.where(horizontal, p[:, 0] / 0.5, along / 0.6) + 0.5 * (np.floor(w) % 2)
        mortar = (np.abs(u - np.round(u)) < 0.06) | (np.abs(w - np.round(w)) < 0.08)
        tone = 0.9 + 0.2 * _hash(np.stack([np.floor(u), np.floor(w), np.zeros_like(u)], axis=1).astype(np.int64))
        return np.where(mortar, 0.7, tone)
    if kind == "stripes":
        return np.where((np.floor((p[:, 0] + p[:, 1]) / 0.25) % 2) == 0, 1.0, 0.75)
    if kind == "noise":
        fine = _hash(np.floor(p / 0.15).astype(np.int64))
        coarse = _hash(np.floor(p / 1.3).astype(np.int64) + 7)
        return 0.8 + 0.25 * fine * 0.6 + 0.25 * coarse * 0.4
    return np.ones(len(p))


def shade(scene: RayScene, hits: Hits, directions: np.ndarray) -> np.ndarray:
    """(N, 3) float colours in [0, 1] for camera rays."""
    n = len(directions)
    colour = np.zeros((n, 3))
    hit = hits.object_index >= 0
    # sky: brighter and paler towards the horizon
    up = np.clip(directions[~hit, 2], 0, 1)[:, None]
    colour[~hit] = (1 - up) * np.array([0.78, 0.85, 0.93]) + up * np.array([0.35, 0.55, 0.85])
    if not hit.any():
        return colour
    idx = np.flatnonzero(hit)
    owner = hits.object_index[idx]
    albedo = np.array([scene.objects[o].colour for o in owner]) / 255.0  # (M, 3)
    textures = np.array([scene.objects[o].texture for o in owner])
    factor = np.ones(len(idx))
    for kind in np.unique(textures):
        sel = textures == kind
        factor[sel] = _texture(kind, hits.point[idx][sel], hits.normal[idx][sel])
    normal = hits.normal[idx]
    # shadow rays towards the sun, started just off the surface
    shadow = scene.cast(hits.point[idx] + normal * 0.02, np.broadcast_to(SUN, (len(idx), 3)).copy(), 300.0)
    lit = (shadow.object_index < 0).astype(float)
    diffuse = np.clip(normal @ SUN, 0, 1) * lit
    ambient = 0.35 + 0.15 * np.clip(normal[:, 2], 0, 1)
    c = albedo * factor[:, None] * (ambient + 0.75 * diffuse)[:, None]
    haze = 1 - np.exp(-hits.distance[idx] / 400.0)
    colour[idx] = (1 - haze[:, None]) * c + haze[:, None] * np.array([0.75, 0.8, 0.88])
    return colour


def render(
    scene: RayScene,
    world_from_camera: np.ndarray,
    width: int,
    height: int,
    k: np.ndarray,
    compiled: bool | None = None,
    threads: int = 1,
) -> CameraImages:
    """compiled: rays and shading by the compiled kernel (default: where it compiles; bit-identical) or the reference;
    threads: the kernel's threads for this camera's rays."""
    body = pixel_rays(width, height, k)  # (H*W, 3)
    with kernels.single_threaded_blas():
        directions = body @ world_from_camera[:3, :3].T
    origin = world_from_camera[:3, 3]
    if compiled is None:
        compiled = ray_kernel.available()
    if compiled:
        distance, owner, rgb = scene.compiled.camera(origin, directions, SUN, threads)
    else:
        hits = scene.cast(np.broadcast_to(origin, directions.shape), directions, 1000.0, compiled=False)
        distance, owner = hits.distance, hits.object_index
        rgb = (np.clip(shade(scene, hits, directions), 0, 1) * 255 + 0.5).astype(np.uint8)
    depth = np.where(np.isfinite(distance), distance * body[:, 0], 0).astype(np.float32).reshape(height, width)
    labels = np.array([o.label for o in scene.objects] + [SKY_LABEL], np.uint8)
    semantic = labels[owner].reshape(height, width)  # index -1 -> the appended sky label
    return CameraImages(rgb.reshape(height, width, 3), depth, semantic)


def render_rig(
    scene: RayScene,
    world_from_cameras: Sequence[np.ndarray],
    width: int,
    height: int,
    k: np.ndarray,
    threads: int = 1,
    compiled: bool | None = None,
) -> list[CameraImages]:
    """Every camera of a rig in order, on `threads` threads: the kernel splits each camera's rays among them (even
    shares: no camera waits for another), the reference renders `threads` cameras at once (Embree and NumPy release
    the GIL)."""
    if compiled is None:
        compiled = ray_kernel.available()
    if threads <= 1 or compiled:
        return [render(scene, pose, width, height, k, compiled, threads) for pose in world_from_cameras]
    return list(_pool(threads).map(lambda pose: render(scene, pose, width, height, k, compiled), world_from_cameras))


@lru_cache(maxsize=4)
def _pool(threads: int) -> ThreadPoolExecutor:
    """Threads kept for the process's life: a frame's four cameras take tens of milliseconds, a new pool's start
    would be a noticeable share of that."""
    return ThreadPoolExecutor(threads, thread_name_prefix="co3sop-camera")
