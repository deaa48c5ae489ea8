"""Collision primitives of the simulated world: exact voxel overlap, vertical ray hits, meshes.

Every scene object is a union of primitives in the world frame (REP-103 axes,
metres). The voxel sensor asks each primitive which voxels it overlaps; the
cameras and LiDAR ray-cast the primitives' triangle meshes, as a game engine
renders visual meshes and queries collision shapes.

Overlap is strict: a voxel belongs to a primitive only if they interpenetrate
by more than EPS, so a road whose top lies exactly on a voxel boundary does
not leak into the voxel above it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
import trimesh
from trimesh.transformations import flips_winding, transform_points

EPS = 1e-6  # m
Triangles = tuple[np.ndarray, np.ndarray]  # vertices (V, 3) float64, faces (F, 3) int64


@lru_cache(maxsize=4096)
def _template(kind: str, radius: float = 0.0, height: float = 0.0) -> Triangles:
    """trimesh.creation's mesh before placement: a unit box, a 12-sided cylinder, a twice subdivided icosphere
    (read-only; the town repeats sizes, so each is built once)."""
    if kind == "box":
        m = trimesh.creation.box()
    elif kind == "cylinder":
        m = trimesh.creation.cylinder(radius=radius, height=height, sections=12)
    else:
        m = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    vertices, faces = np.array(m.vertices), np.array(m.faces)
    vertices.setflags(write=False)
    faces.setflags(write=False)
    return vertices, faces


def _placed(vertices: np.ndarray, faces: np.ndarray, matrix: np.ndarray) -> Triangles:
    """What trimesh's Trimesh.apply_transform makes of a mesh, with the same calls, without building a Trimesh
    (most of the cost of meshing a town): the cameras see bit-identical triangles."""
    matrix = np.asanyarray(matrix, order="C", dtype=np.float64)
    if trimesh.util.allclose(matrix, np.eye(4), 1e-8):
        return vertices, faces
    if not trimesh.util.allclose(matrix[:3, :3], np.eye(3), atol=1e-6) and flips_winding(matrix):
        faces = np.ascontiguousarray(np.fliplr(faces))
    return transform_points(vertices, matrix), faces


def _translation(t) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, 3] = np.asanyarray(t, dtype=np.float64)
    return matrix


def rotation(yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """R = Rz(yaw) @ Ry(pitch) @ Rx(roll), radians, REP-103 (right-handed) axes."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


@dataclass(frozen=True, eq=False)
class Box:
    """An oriented box: centre (3,), half sizes (3,), rotation (3, 3) whose columns are the box axes."""

    center: np.ndarray
    half: np.ndarray
    rot: np.ndarray

    @classmethod
    def make(cls, center, size, yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> Box:
        return cls(np.asarray(center, float), np.asarray(size, float) / 2, rotation(yaw, pitch, roll))

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        r = np.abs(self.rot) @ self.half
        return self.center - r, self.center + r

    @cached_property
    def overlap_constants(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The separating axis test's constants: 15 candidate axes (15, 3) (the cube's faces, the box's faces, their
        edge crossings; a degenerate crossing is all zeros), per axis |a| summed (15,) and the box's reach (15,)
        (inf for a degenerate axis, which separates nothing). Written as elementwise float64 arithmetic, as the
        compiled voxel sensor (kernels/voxel_sensor.c) repeats it, so both decide every voxel alike."""
        eye, r = np.eye(3), self.rot
        e, b = np.repeat(eye, 3, axis=0), np.tile(r.T, (3, 1))  # (9, 3): e_i and box axis j, i major
        edges = np.stack(
            [
                e[:, 1] * b[:, 2] - e[:, 2] * b[:, 1],
                e[:, 2] * b[:, 0] - e[:, 0] * b[:, 2],
                e[:, 0] * b[:, 1] - e[:, 1] * b[:, 0],
            ],
            axis=1,
        )  # e_i x b_j, np.cross's formula
        norm = np.sqrt((edges[:, 0] * edges[:, 0] + edges[:, 1] * edges[:, 1]) + edges[:, 2] * edges[:, 2])
        long = norm > 1e-9
        edges = np.where(long[:, None], edges / np.where(long, norm, 1.0)[:, None], 0.0)
        a = np.concatenate([eye, r.T, edges])  # (15, 3)
        valid = np.abs(a).sum(axis=1) > 0
        abs_sum = (np.abs(a[:, 0]) + np.abs(a[:, 1])) + np.abs(a[:, 2])
        along = np.abs(a @ r)  # (15, 3): |axis . box axis j|
        reach = (along[:, 0] * self.half[0] + along[:, 1] * self.half[1]) + along[:, 2] * self.half[2]
        return a, abs_sum, np.where(valid, reach, np.inf)

    def overlaps(self, centers: np.ndarray, half: float) -> np.ndarray:
        """Strict overlap with axis-aligned cubes of half size `half` at `centers` (N, 3) -> (N,) bool."""
        a, abs_sum, box_reach = self.overlap_constants
        reach = half * abs_sum + box_reach - EPS  # (15,)
        d = self.center - centers  # (N, 3)
        distance = np.abs(d[:, 0:1] * a[:, 0] + d[:, 1:2] * a[:, 1] + d[:, 2:3] * a[:, 2])  # (N, 15)
        return (distance < reach).all(axis=1)  # separating axis theorem

    def vertical_entry(self, xy: np.ndarray) -> np.ndarray:
        """Top z where downward vertical rays at xy (N, 2) enter the box; NaN where they miss."""
        origin = np.column_stack([xy, np.zeros(len(xy))]) - self.center  # (N, 3), box-centred
        o = origin @ self.rot  # box axes coordinates of the ray origins at z = 0
        d = self.rot[2]  # direction +z in box axes (rows of rot.T)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-self.half - o) / d
            t2 = (self.half - o) / d
        lo = np.where(np.abs(d) < 1e-12, np.where(np.abs(o) < self.half, -np.inf, np.inf), np.minimum(t1, t2))
        hi = np.where(np.abs(d) < 1e-12, np.where(np.abs(o) < self.half, np.inf, -np.inf), np.maximum(t1, t2))
        t_in, t_out = lo.max(axis=1), hi.min(axis=1)
        return np.where(t_in < t_out, t_out, np.nan)  # rays start at z = 0: t is world z

    def triangles(self) -> Triangles:
        """trimesh.creation.box(extents=2 * half, transform=pose)'s vertices and faces."""
        transform = np.eye(4)
        transform[:3, :3], transform[:3, 3] = self.rot, self.center
        vertices, faces = _template("box")
        return _placed(vertices * (2 * self.half), faces, transform)

    def mesh(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(*self.triangles(), process=False)


@dataclass(frozen=True, eq=False)
class Cylinder:
    """An upright cylinder: axis centre (x, y), radius, z from z0 to z1."""

    x: float
    y: float
    radius: float
    z0: float
    z1: float

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        r = self.radius
        return np.array([self.x - r, self.y - r, self.z0]), np.array([self.x + r, self.y + r, self.z1])

    @cached_property
    def overlap_constants(self) -> tuple[float, float, float]:
        """z0 + EPS, z1 - EPS, (radius - EPS)^2: the strict overlap's thresholds (the compiled sensor takes them)."""
        return self.z0 + EPS, self.z1 - EPS, (self.radius - EPS) ** 2

    def overlaps(self, centers: np.ndarray, half: float) -> np.ndarray:
        z0, z1, r2 = self.overlap_constants
        dx = np.maximum(np.abs(centers[:, 0] - self.x) - half, 0)
        dy = np.maximum(np.abs(centers[:, 1] - self.y) - half, 0)
        in_z = (centers[:, 2] + half > z0) & (centers[:, 2] - half < z1)
        # the cube's nearest point to the axis lies inside the circle
        return in_z & (dx * dx + dy * dy < r2)

    def vertical_entry(self, xy: np.ndarray) -> np.ndarray:
        inside = (xy[:, 0] - self.x) ** 2 + (xy[:, 1] - self.y) ** 2 < self.radius**2
        return np.where(inside, self.z1, np.nan)

    def triangles(self) -> Triangles:
        """trimesh.creation.cylinder(radius, height, sections=12) moved to its place."""
        return _placed(
            *_template("cylinder", self.radius, self.z1 - self.z0),
            _translation([self.x, self.y, (self.z0 + self.z1) / 2]),
        )

    def mesh(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(*self.triangles(), process=False)


@dataclass(frozen=True, eq=False)
class Sphere:
    center: np.ndarray
    radius: float

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        return self.center - self.radius, self.center + self.radius

    @cached_property
    def overlap_constants(self) -> float:
        """(radius - EPS)^2: the strict overlap's threshold (the compiled sensor takes it)."""
        return (self.radius - EPS) ** 2

    def overlaps(self, centers: np.ndarray, half: float) -> np.ndarray:
        gap = np.maximum(np.abs(centers - self.center) - half, 0)  # (N, 3)
        return (gap[:, 0] * gap[:, 0] + gap[:, 1] * gap[:, 1]) + gap[:, 2] * gap[:, 2] < self.overlap_constants

    def vertical_entry(self, xy: np.ndarray) -> np.ndarray:
        d2 = ((xy - self.center[:2]) ** 2).sum(axis=1)
        with np.errstate(invalid="ignore"):
            return np.where(d2 < self.radius**2, self.center[2] + np.sqrt(self.radius**2 - d2), np.nan)

    def triangles(self) -> Triangles:
        """trimesh.creation.icosphere(subdivisions=2, radius) moved to its centre."""
        return _placed(*_template("sphere", self.radius), _translation(self.center))

    def mesh(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(*self.triangles(), process=False)


Primitive = Box | Cylinder | Sphere
