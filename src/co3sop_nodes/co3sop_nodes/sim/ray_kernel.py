"""The work around the ray casts as a compiled kernel (native/ray_shade.c): rays prepared for Embree, first hits
located, camera pixels shaded.

Embree itself casts millions of rays per second per core; the reference path
(trimesh's intersector, then NumPy shading with per-hit Python lookups) spends
most of a camera's time around it. Here Embree is called directly on a scene
built exactly as trimesh builds its own (same float32 vertices and rays, so the
same triangles are hit) and everything else is one C loop per stage with the
reference's float64 operations in its order: hits and images are bit-identical
(tests compare them on fixed and random scenes).
"""

from __future__ import annotations

import ctypes
from collections.abc import Sequence
from functools import cache

import numpy as np
import trimesh
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from .. import native
from .scene import SceneObject

_P, _I, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
TEXTURES = {"plain": 0, "bricks": 1, "stripes": 2, "noise": 3}  # as native/ray_shade.c numbers them


@cache
def _kernel():
    lib = native.load("ray_shade")
    if lib is None:
        return None
    lib.prepare.argtypes = [_P, _I, _P, _P, _D, _P, _P, _P, _I, _I]
    lib.finish.argtypes = [_P, _I, _P, _P, _P, _P, _P, _P, _D, _P, _P, _P, _P, _I, _I]
    lib.shade.argtypes = [_P] * 10 + [_I, _I]
    for fn in (lib.prepare, lib.finish, lib.shade):
        fn.restype = None
    return lib


def available() -> bool:
    """Whether the kernel is enabled and compiles here (compiling it on first call)."""
    return native.ENABLED and _kernel() is not None


def _ptr(a: np.ndarray) -> int:
    return a.ctypes.data


def _rows(a: np.ndarray) -> tuple[np.ndarray, int]:
    """(N, 3) float64 rays' origins -> (contiguous data, doubles per ray): one row with stride 0 where every ray
    shares it (np.broadcast_to), as cameras and LiDARs pass them."""
    if len(a) and a.strides[0] == 0:
        return np.ascontiguousarray(a[0], np.float64), 0
    return np.ascontiguousarray(a, np.float64), 3


class CompiledScene:
    """A mesh's Embree BVH and the per-triangle planes and owners the kernel reads."""

    def __init__(self, mesh: trimesh.Trimesh, face_owner: np.ndarray, objects: Sequence[SceneObject]):
        # as trimesh's RayMeshIntersector: vertices shifted to the box's corner and scaled to about 100 units
        vertices = np.asarray(mesh.vertices, np.float64)
        self.shift = vertices.min(axis=0)
        self.scale = 100.0 / mesh.scale
        self.embree = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=self.embree, vertices=((vertices - self.shift) * self.scale).astype(np.float32),
                     indices=np.asarray(mesh.faces).astype(np.int32))
        self.plane_origins = np.ascontiguousarray(mesh.triangles[:, 0, :], np.float64)  # (F, 3)
        self.plane_normals = np.ascontiguousarray(mesh.face_normals, np.float64)  # (F, 3)
        self.face_owner = np.ascontiguousarray(face_owner, np.int64)  # (F,)
        self.albedo = np.array([o.colour for o in objects], np.float64).reshape(-1, 3) / 255.0  # (O, 3)
        self.kind = np.array([TEXTURES.get(o.texture, 0) for o in objects], np.int32)  # (O,)

    def first_hits(self, origins: np.ndarray, directions: np.ndarray, max_distance: float, threads: int = 1):
        """RayScene.cast's (distance, owner, normal, point) for rays (N, 3) from `origins` along `directions`."""
        lib = _kernel()
        n = len(directions)
        org, stride = _rows(origins)
        dirs = np.ascontiguousarray(directions, np.float64)
        unit, org32, dir32 = np.empty((n, 3)), np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
        native.parallel(lib.prepare, (_ptr(org), stride, _ptr(dirs), _ptr(self.shift), self.scale, _ptr(unit), _ptr(org32),
                                      _ptr(dir32)), n, threads)
        prim = np.ascontiguousarray(self.embree.run(org32, dir32), np.int32)  # (N,) triangle, -1 for none
        distance, owner = np.empty(n), np.empty(n, np.int64)
        normal, point = np.empty((n, 3)), np.empty((n, 3))
        native.parallel(lib.finish, (_ptr(org), stride, _ptr(dirs), _ptr(unit), _ptr(prim), _ptr(self.plane_origins),
                                     _ptr(self.plane_normals), _ptr(self.face_owner), float(max_distance), _ptr(distance),
                                     _ptr(owner), _ptr(normal), _ptr(point)), n, threads)
        return distance, owner, normal, point

    def shade(self, directions: np.ndarray, distance: np.ndarray, owner: np.ndarray, normal: np.ndarray, point: np.ndarray,
              lit: np.ndarray, sun: np.ndarray, threads: int = 1) -> np.ndarray:
        """camera.shade's colours as uint8 (N, 3); lit (N,) bool: the hit's shadow ray found nothing."""
        n = len(directions)
        dirs = np.ascontiguousarray(directions, np.float64)
        lit = np.ascontiguousarray(lit, np.uint8)
        sun = np.ascontiguousarray(sun, np.float64)
        rgb = np.empty((n, 3), np.uint8)
        native.parallel(_kernel().shade, (_ptr(dirs), _ptr(distance), _ptr(owner), _ptr(normal), _ptr(point), _ptr(lit),
                                          _ptr(self.albedo), _ptr(self.kind), _ptr(sun), _ptr(rgb)), n, threads)
        return rgb
