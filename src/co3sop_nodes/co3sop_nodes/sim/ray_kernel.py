"""The ray casts and the work around them as a compiled kernel (kernels/ray_shade.c): rays prepared for Embree,
cast, first hits located, camera pixels shaded.

Embree itself casts millions of rays per second per core; the reference path
(trimesh's intersector, then NumPy shading with per-hit Python lookups) spends
most of a camera's time around it. Here Embree (embreex's own library) is
called from C on a scene built exactly as trimesh's intersector builds its own
(same flags, float32 vertices and rays, so the same triangles are hit), 8
neighbouring rays per call, and everything else is C with the reference's
float64 operations in its order: hits and images are bit-identical (tests
compare them on fixed and random scenes). A camera is one call: each block of
pixels is cast, located, its shadow rays cast and located, and shaded while it
is in cache, on several threads taking interleaved blocks.
"""

from __future__ import annotations

import ctypes
import importlib
import weakref
from collections.abc import Sequence
from functools import cache

import numpy as np
import trimesh

from co3sop_nodes import kernels
from co3sop_nodes.sim.scene import SceneObject

_P, _I, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
TEXTURES = {"plain": 0, "bricks": 1, "stripes": 2, "noise": 3}  # as kernels/ray_shade.c numbers them


@cache
def _kernel():
    lib = kernels.load("ray_shade")
    if lib is None:
        return None
    lib.prepare.argtypes = [_P, _I, _P, _P, _D, _P, _P, _P, _I, _I]
    lib.finish.argtypes = [_P, _I, _P, _P, _P, _P, _P, _P, _D, _P, _P, _P, _P, _I, _I]
    lib.cast.argtypes = [_P] * 5 + [_I, _I, _I]
    lib.camera.argtypes = [_P] * 5 + [_D] + [_P] * 9 + [_I, _I, _I]
    for fn in (lib.prepare, lib.finish, lib.cast, lib.camera):
        fn.restype = None
    return lib


# Embree 4's constants (include/embree4/rtcore_*.h) for the calls made here
_SCENE_FLAG_ROBUST, _GEOMETRY_TRIANGLE, _BUFFER_INDEX, _BUFFER_VERTEX, _FORMAT_UINT3, _FORMAT_FLOAT3 = (
    4,
    0,
    0,
    1,
    0x5003,
    0x9003,
)


@cache
def _embree() -> ctypes.CDLL | None:
    """The Embree library embreex loaded (the one trimesh's intersector casts with), found among the process's
    mapped files; None where there is none."""
    try:
        importlib.import_module("embreex.rtcore_scene")  # loads the library
    except ImportError:
        return None
    paths = kernels.mapped("libembree4")
    if not paths:
        return None
    lib = ctypes.CDLL(paths[0])
    for name, args, res in (
        ("rtcNewDevice", [ctypes.c_char_p], _P),
        ("rtcReleaseDevice", [_P], None),
        ("rtcGetDeviceError", [_P], ctypes.c_int),
        ("rtcNewScene", [_P], _P),
        ("rtcSetSceneFlags", [_P, ctypes.c_int], None),
        ("rtcCommitScene", [_P], None),
        ("rtcReleaseScene", [_P], None),
        ("rtcNewGeometry", [_P, ctypes.c_int], _P),
        (
            "rtcSetNewGeometryBuffer",
            [_P, ctypes.c_int, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t, ctypes.c_size_t],
            _P,
        ),
        ("rtcCommitGeometry", [_P], None),
        ("rtcAttachGeometry", [_P, _P], ctypes.c_uint),
        ("rtcReleaseGeometry", [_P], None),
    ):
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = args, res
    return lib


def available() -> bool:
    """Whether the kernels are enabled and compile here (compiling them on first call) and Embree is loadable."""
    return kernels.ENABLED and _kernel() is not None and _embree() is not None


class _EmbreeScene:
    """One triangle mesh in an Embree scene, built with the calls, flags and layouts of embreex's EmbreeScene and
    TriangleMesh (robust scene, float3 vertices in 16-byte rows, uint3 indices)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        lib = _embree()
        self.device = lib.rtcNewDevice(None)
        self.scene = lib.rtcNewScene(self.device)
        lib.rtcSetSceneFlags(self.scene, _SCENE_FLAG_ROBUST)
        geometry = lib.rtcNewGeometry(self.device, _GEOMETRY_TRIANGLE)
        rows = np.zeros((len(vertices), 4), np.float32)
        rows[:, :3] = vertices
        indices = np.ascontiguousarray(faces, np.uint32)
        for kind, fmt, data in ((_BUFFER_VERTEX, _FORMAT_FLOAT3, rows), (_BUFFER_INDEX, _FORMAT_UINT3, indices)):
            buffer = lib.rtcSetNewGeometryBuffer(geometry, kind, 0, fmt, data.strides[0], len(data))
            if buffer and data.nbytes:
                ctypes.memmove(buffer, data.ctypes.data, data.nbytes)
        lib.rtcCommitGeometry(geometry)
        lib.rtcAttachGeometry(self.scene, geometry)
        lib.rtcReleaseGeometry(geometry)
        lib.rtcCommitScene(self.scene)
        error = lib.rtcGetDeviceError(self.device)
        weakref.finalize(self, _release, lib, self.scene, self.device)
        if error:
            raise RuntimeError(f"Embree failed to build the scene of {len(faces)} triangles (error {error})")
        self.intersect = ctypes.cast(lib.rtcIntersect8, _P).value  # 8 rays per call: rays come in neighbouring order

    def first_triangles(self, org32: np.ndarray, dir32: np.ndarray, threads: int) -> np.ndarray:
        """(N,) int32: the triangle each ray (float32 (N, 3) origins and directions in the scene's units) hits
        first, -1 for none."""
        prim = np.empty(len(dir32), np.int32)
        kernels.interleaved(
            _kernel().cast, (self.scene, self.intersect, _ptr(org32), _ptr(dir32), _ptr(prim), len(dir32)), threads
        )
        return prim


def _release(lib: ctypes.CDLL, scene: int, device: int) -> None:
    lib.rtcReleaseScene(scene)
    lib.rtcReleaseDevice(device)


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
        self.embree = _EmbreeScene(((vertices - self.shift) * self.scale).astype(np.float32), np.asarray(mesh.faces))
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
        kernels.parallel(
            lib.prepare,
            (_ptr(org), stride, _ptr(dirs), _ptr(self.shift), self.scale, _ptr(unit), _ptr(org32), _ptr(dir32)),
            n,
            threads,
        )
        prim = self.embree.first_triangles(org32, dir32, threads)  # (N,) triangle, -1 for none
        distance, owner = np.empty(n), np.empty(n, np.int64)
        normal, point = np.empty((n, 3)), np.empty((n, 3))
        kernels.parallel(
            lib.finish,
            (
                _ptr(org),
                stride,
                _ptr(dirs),
                _ptr(unit),
                _ptr(prim),
                _ptr(self.plane_origins),
                _ptr(self.plane_normals),
                _ptr(self.face_owner),
                float(max_distance),
                _ptr(distance),
                _ptr(owner),
                _ptr(normal),
                _ptr(point),
            ),
            n,
            threads,
        )
        return distance, owner, normal, point

    def camera(self, origin: np.ndarray, directions: np.ndarray, sun: np.ndarray, threads: int = 1):
        """camera.render's compiled stages in one call: pixel rays (N, 3) from `origin` (3,) -> their first hits'
        distance (N,) and owner (N,) as RayScene.cast reports them (within 1000 m), and the colours (N, 3) uint8,
        shadow rays towards `sun` (within 300 m) included."""
        n = len(directions)
        origin = np.ascontiguousarray(origin, np.float64)
        dirs = np.ascontiguousarray(directions, np.float64)
        sun = np.ascontiguousarray(sun, np.float64)
        distance, owner, rgb = np.empty(n), np.empty(n, np.int64), np.empty((n, 3), np.uint8)
        kernels.interleaved(
            _kernel().camera,
            (
                self.embree.scene,
                self.embree.intersect,
                _ptr(origin),
                _ptr(dirs),
                _ptr(self.shift),
                self.scale,
                _ptr(self.plane_origins),
                _ptr(self.plane_normals),
                _ptr(self.face_owner),
                _ptr(self.albedo),
                _ptr(self.kind),
                _ptr(sun),
                _ptr(distance),
                _ptr(owner),
                _ptr(rgb),
                n,
            ),
            threads,
        )
        return distance, owner, rgb
