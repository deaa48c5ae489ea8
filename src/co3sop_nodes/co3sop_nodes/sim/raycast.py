"""Ray casting against a scene's meshes with Embree: through trimesh's intersector (the reference), or directly
with the hits located by a compiled kernel (sim/ray_kernel.py, bit-identical)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from co3sop_nodes.sim import ray_kernel
from co3sop_nodes.sim.scene import SceneObject


@dataclass(frozen=True)
class Hits:
    distance: np.ndarray  # (N,) m along each ray; inf where it missed
    object_index: np.ndarray  # (N,) index into the scene's objects, -1 where missed
    normal: np.ndarray  # (N, 3) unit surface normal facing the ray origin (0 where missed)
    point: np.ndarray  # (N, 3) world hit point (origin where missed)


class ObjectMeshes:
    """Triangle meshes of a list of objects, built once (the static world is reused every frame)."""

    def __init__(self, objects: Sequence[SceneObject]):
        self.objects = list(objects)
        meshes, owner = [], []
        for i, obj in enumerate(self.objects):
            for p in obj.primitives:
                vertices, faces = p.triangles()
                meshes.append((vertices, faces))
                owner.append(np.full(len(faces), i))
        self.vertices = np.concatenate([v for v, _ in meshes]) if meshes else np.zeros((0, 3))
        offsets = np.cumsum([0] + [len(v) for v, _ in meshes[:-1]])
        self.faces = np.concatenate([f + o for (_, f), o in zip(meshes, offsets)]) if meshes else np.zeros((0, 3), int)
        self.face_owner = np.concatenate(owner) if owner else np.zeros(0, int)


class RayScene:
    """Static plus dynamic meshes in one BVH."""

    def __init__(self, parts: Sequence[ObjectMeshes]):
        self.objects = [o for part in parts for o in part.objects]
        vert_off = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
        obj_off = np.cumsum([0] + [len(p.objects) for p in parts[:-1]])
        vertices = np.concatenate([p.vertices for p in parts])
        faces = np.concatenate([p.faces + o for p, o in zip(parts, vert_off)])
        self.face_owner = np.concatenate([p.face_owner + o for p, o in zip(parts, obj_off)])
        self.mesh = trimesh.Trimesh(vertices, faces, process=False)
        self._intersector = RayMeshIntersector(self.mesh)

    @cached_property
    def compiled(self) -> ray_kernel.CompiledScene:
        return ray_kernel.CompiledScene(self.mesh, self.face_owner, self.objects)

    def cast(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        max_distance: float = np.inf,
        compiled: bool | None = None,
        threads: int = 1,
    ) -> Hits:
        """First hits of rays (N, 3) from `origins` along unit `directions`.

        compiled: the compiled kernel (default: where it compiles) or trimesh's intersector and NumPy.
        threads: the kernel's threads (Embree's casts themselves run on the calling thread).
        """
        origins = np.broadcast_to(origins, directions.shape)
        if compiled is None:
            compiled = ray_kernel.available()
        if compiled:
            return Hits(*self.compiled.first_hits(origins, directions, max_distance, threads))
        n = len(directions)
        tri, ray, loc = self._intersector.intersects_id(origins, directions, multiple_hits=False, return_locations=True)
        distance = np.full(n, np.inf)
        distance[ray] = np.einsum("ij,ij->i", loc - origins[ray], directions[ray])
        owner = np.full(n, -1)
        owner[ray] = self.face_owner[tri]
        normal = np.zeros((n, 3))
        face_n = self.mesh.face_normals[tri]
        flip = np.einsum("ij,ij->i", face_n, directions[ray]) > 0
        normal[ray] = np.where(flip[:, None], -face_n, face_n)
        far = distance > max_distance
        distance[far], owner[far], normal[far] = np.inf, -1, 0
        point = origins + np.where(np.isfinite(distance), distance, 0)[:, None] * directions
        return Hits(distance, owner, normal, point)
