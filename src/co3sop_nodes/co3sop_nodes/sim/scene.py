"""Scene objects (a label and a union of primitives) and their rigid transforms."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from co3sop_nodes.sim.shapes import Box, Cylinder, Primitive, Sphere


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One actor of the world: what the game engine would give a semantic tag."""

    id: int
    label: int  # Co3SOP label: the CARLA 0.9.12 tag (1..22)
    primitives: tuple[Primitive, ...]
    colour: tuple[int, int, int] = (128, 128, 128)  # base albedo for the cameras, RGB
    texture: str = "plain"  # "plain" | "bricks" | "stripes" | "noise": procedural pattern for the cameras

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        return self._aabb

    @cached_property
    def _aabb(self) -> tuple[np.ndarray, np.ndarray]:
        # the town's static objects are culled by their box for every sensor and every frame
        boxes = [p.aabb() for p in self.primitives]
        return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)

    def overlaps(self, centers: np.ndarray, half: float) -> np.ndarray:
        """Whether cubes of half size `half` at `centers` (N, 3) overlap any primitive -> (N,) bool."""
        hit = np.zeros(len(centers), bool)
        for p in self.primitives:
            hit |= p.overlaps(centers, half)
        return hit

    def transformed(self, transform: np.ndarray) -> SceneObject:
        """The object moved by a 4x4 rigid transform whose rotation is about z only."""
        return SceneObject(
            self.id,
            self.label,
            tuple(transform_primitive(p, transform) for p in self.primitives),
            self.colour,
            self.texture,
        )


def transform_primitive(p: Primitive, transform: np.ndarray) -> Primitive:
    rot, t = transform[:3, :3], transform[:3, 3]
    if isinstance(p, Box):
        return Box(rot @ p.center + t, p.half, rot @ p.rot)
    if isinstance(p, Sphere):
        return Sphere(rot @ p.center + t, p.radius)
    if abs(rot[2, 2] - 1) > 1e-9:
        raise ValueError("cylinders stay upright: only rotations about z may move them")
    x, y, z = rot @ np.array([p.x, p.y, 0.0]) + t
    return Cylinder(x, y, p.radius, p.z0 + z, p.z1 + z)
