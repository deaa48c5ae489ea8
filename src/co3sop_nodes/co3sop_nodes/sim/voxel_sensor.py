"""The paper's semantic voxel sensor, and its brute-force oracle.

A grid axis-aligned in the sensor's frame (the CAV's LiDAR, REP-103 axes) is
annotated in the paper's three stages (Co3SOP, Sec. III-A):

1. Top-down broad-range trace: a downward multi-hit trace through every voxel
   column finds each object that intersects the volume and where it is first
   hit; the voxels at those impact points are the object's seed voxels.
2. Object-level occupancy completion: per object, a breadth-first search from
   its seeds over the six axis neighbours, each candidate voxel checked for
   collision with that object (exact, strict overlap; see shapes.py). Objects
   run in parallel threads.
3. Label assignment: an object's voxels take its semantic label; every other
   voxel is 0 (empty). There is no "unknown".

The sensor ignores the vehicle that carries it, as Co3SOP's does (its
`self_ignore` option, on in its replay configuration): `ignore` names the
object ids left out (the carrying CAV); the other CAVs stay labelled.

Overlap rule: a voxel that two objects both occupy takes the label ranked
higher in LABEL_PRIORITY (thin and dynamic things win over the large static
surfaces they stand on or touch, e.g. a tyre over the road, a pole over the
sidewalk, a road line over the road); between objects of one label it makes no
difference.

A primitive thinner than a voxel column may slip between the column centres of
stage 1; it is then seeded from an exact check of the voxels inside its own
bounding box, so no object that intersects the volume is missed. The oracle
checks every voxel against every object and must give the identical grid.

The stages run in a compiled kernel (voxel_kernel.py, kernels/voxel_sensor.c)
where a C compiler is present, else in NumPy here; both give the same grid.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from co3sop_nodes.common.classes import LABEL_BY_NAME
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.sim import voxel_kernel
from co3sop_nodes.sim.scene import SceneObject

# Lowest first; a voxel shared by two objects takes the later label.
LABEL_PRIORITY: tuple[int, ...] = tuple(
    LABEL_BY_NAME[name]
    for name in (
        "unlabeled",
        "terrain",
        "ground",
        "water",
        "road",
        "sidewalk",
        "railtrack",
        "roadline",
        "bridge",
        "building",
        "wall",
        "fence",
        "guardrail",
        "other",
        "vegetation",
        "static",
        "dynamic",
        "pole",
        "trafficsign",
        "trafficlight",
        "vehicle",
        "pedestrian",
    )
)
_RANK = np.zeros(256, np.int16)
_RANK[list(LABEL_PRIORITY)] = np.arange(1, len(LABEL_PRIORITY) + 1)
_LABEL_OF_RANK = np.zeros(256, np.uint8)
_LABEL_OF_RANK[1 : len(LABEL_PRIORITY) + 1] = LABEL_PRIORITY
_NEIGHBOURS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])


def in_sensor_frame(objects: Sequence[SceneObject], world_from_sensor: np.ndarray) -> list[SceneObject]:
    sensor_from_world = np.linalg.inv(world_from_sensor)
    return [o.transformed(sensor_from_world) for o in objects]


def _near(objects: Sequence[SceneObject], world_from_sensor: np.ndarray, grid: GridSpec) -> list[SceneObject]:
    """The objects whose world bounding box meets the grid's (a conservative cull)."""
    corners = (
        np.array(np.meshgrid(*[[o, o + n * grid.voxel_size] for o, n in zip(grid.origin, grid.dims)])).reshape(3, -1).T
    )
    world = corners @ world_from_sensor[:3, :3].T + world_from_sensor[:3, 3]
    lo, hi = world.min(axis=0), world.max(axis=0)
    out = []
    for obj in objects:
        a, b = obj.aabb()
        if (a < hi).all() and (b > lo).all():
            out.append(obj)
    return out


class _Region:
    """The voxels of `grid` inside a bounding box (lo, hi) in m: an index box [lo, hi)."""

    def __init__(self, grid: GridSpec, bounds: tuple[np.ndarray, np.ndarray]):
        origin, v = np.asarray(grid.origin), grid.voxel_size
        self.lo = np.clip(np.floor((bounds[0] - origin) / v).astype(int), 0, grid.dims)
        self.hi = np.clip(np.ceil((bounds[1] - origin) / v).astype(int), 0, grid.dims)
        self.shape = np.maximum(self.hi - self.lo, 0)

    @property
    def empty(self) -> bool:
        return bool((self.shape == 0).any())

    def voxels(self) -> np.ndarray:
        """Grid indices (M, 3) of every voxel in the box."""
        return np.argwhere(np.ones(self.shape, bool)) + self.lo


def _centres(grid: GridSpec, ijk: np.ndarray) -> np.ndarray:
    return np.asarray(grid.origin) + (ijk + 0.5) * grid.voxel_size  # (N, 3)


def _flat(grid: GridSpec, ijk: np.ndarray) -> np.ndarray:
    return np.ravel_multi_index(ijk.T, grid.dims)


def _trace(grid: GridSpec, primitive, region: _Region) -> np.ndarray:
    """Stage 1 for one primitive: impact voxels (M, 3) of downward traces through the column centres."""
    v, origin = grid.voxel_size, np.asarray(grid.origin)
    ii, jj = np.meshgrid(np.arange(region.lo[0], region.hi[0]), np.arange(region.lo[1], region.hi[1]), indexing="ij")
    cols = np.column_stack([ii.ravel(), jj.ravel()])  # (P, 2) columns under the primitive
    entry = primitive.vertical_entry(origin[:2] + (cols + 0.5) * v)  # (P,) z of first hit, NaN: missed
    hit = np.isfinite(entry) & (entry > origin[2])
    # impact voxel: just below the entry point, clamped into the volume's top layer
    z_top = origin[2] + grid.dims[2] * v
    k = np.floor((np.minimum(entry[hit], z_top) - 1e-4 - origin[2]) / v).astype(int)
    return np.column_stack([cols[hit], np.clip(k, 0, grid.dims[2] - 1)])


def _seeds(grid: GridSpec, obj: SceneObject) -> np.ndarray:
    """Seed voxels (M, 3) of an object, each checked to overlap it."""
    half = grid.voxel_size / 2
    seeds = []
    for p in obj.primitives:
        region = _Region(grid, p.aabb())
        if region.empty:
            continue
        hits = _trace(grid, p, region)  # one impact per column: no duplicates
        hits = hits[p.overlaps(_centres(grid, hits), half)]
        if not len(hits):
            # thinner than a voxel column, or only grazing the volume: check its own box exactly
            hits = region.voxels()
            hits = hits[p.overlaps(_centres(grid, hits), half)]
        seeds.append(hits)
    if not seeds:
        return np.zeros((0, 3), int)
    seeds = np.concatenate(seeds)
    _, first = np.unique(np.ravel_multi_index(seeds.T, grid.dims), return_index=True)
    return seeds[first]


def _grow(grid: GridSpec, obj: SceneObject) -> np.ndarray:
    """Stages 1 + 2 for one object: flat indices of every voxel it occupies."""
    region = _Region(grid, obj.aabb())
    if region.empty:
        return np.zeros(0, np.int64)
    half = grid.voxel_size / 2
    visited = np.zeros(region.shape, bool)  # over the object's box only: it occupies nothing outside
    frontier = _seeds(grid, obj) - region.lo  # local indices
    visited[tuple(frontier.T)] = True
    found = []
    while len(frontier):
        found.append(frontier)
        candidates = (frontier[:, None, :] + _NEIGHBOURS[None]).reshape(-1, 3)
        candidates = candidates[((candidates >= 0) & (candidates < region.shape)).all(axis=1)]
        candidates = candidates[~visited[tuple(candidates.T)]]
        _, first = np.unique(np.ravel_multi_index(candidates.T, region.shape), return_index=True)
        candidates = candidates[first]
        visited[tuple(candidates.T)] = True  # each voxel is checked once
        frontier = candidates[obj.overlaps(_centres(grid, candidates + region.lo), half)]
    if not found:
        return np.zeros(0, np.int64)
    return _flat(grid, np.concatenate(found) + region.lo)


def _assign(grid: GridSpec, objects: Sequence[SceneObject], occupied: Sequence[np.ndarray]) -> np.ndarray:
    """Stage 3: labels (nx, ny, nz) uint8 by the overlap rule; 0 where no object is."""
    labels = np.zeros(grid.num_voxels, np.uint8)
    order = sorted(range(len(objects)), key=lambda i: (_RANK[objects[i].label], objects[i].id))
    for i in order:  # higher priority written last
        labels[occupied[i]] = objects[i].label
    return labels.reshape(grid.dims)


def _kept(objects: Sequence[SceneObject], ignore: Collection[int]) -> list[SceneObject]:
    return [o for o in objects if o.id not in ignore]


def _compiled(grid: GridSpec, local: Sequence[SceneObject], workers: int) -> np.ndarray:
    """The three stages in the compiled kernel (voxel_kernel.py): the same grid as the NumPy path."""

    def box(bounds) -> list[int]:
        r = _Region(grid, bounds)
        return [*r.lo, *r.hi]

    boxes = np.array([box(o.aabb()) for o in local], np.int64).reshape(-1, 6)
    primitive_boxes = np.array([box(p.aabb()) for o in local for p in o.primitives], np.int64).reshape(-1, 6)
    rank = _RANK[[o.label for o in local]].astype(np.uint8)
    grid_ranks = voxel_kernel.ranks(grid, local, rank, boxes, primitive_boxes, max(1, workers))
    return voxel_kernel.to_labels(grid_ranks, _LABEL_OF_RANK, max(1, workers)).reshape(grid.dims)


def annotate(
    objects: Sequence[SceneObject],
    world_from_sensor: np.ndarray,
    grid: GridSpec,
    workers: int = 2,
    ignore: Collection[int] = (),
    compiled: bool | None = None,
) -> np.ndarray:
    """The voxel sensor: (nx, ny, nz) uint8 labels of `grid`, axis-aligned in the sensor frame.

    Objects whose id is in `ignore` (the sensor's own vehicle) are not labelled. `compiled`: the kernel
    (voxel_kernel.py; default: where it compiles) or the NumPy stages; the same grid either way.
    """
    local = in_sensor_frame(_near(_kept(objects, ignore), world_from_sensor, grid), world_from_sensor)
    if voxel_kernel.available() if compiled is None else compiled:
        return _compiled(grid, local, workers)
    with ThreadPoolExecutor(max(1, workers)) as pool:
        occupied = list(pool.map(lambda o: _grow(grid, o), local))
    return _assign(grid, local, occupied)


def annotate_brute_force(
    objects: Sequence[SceneObject], world_from_sensor: np.ndarray, grid: GridSpec, ignore: Collection[int] = ()
) -> np.ndarray:
    """The oracle: every voxel checked against every object, then the same overlap rule.

    Each (voxel, object) pair is first tested against the object's bounding box
    (exact and conservative: an object lies inside its box), then exactly.
    """
    local = in_sensor_frame(_kept(objects, ignore), world_from_sensor)
    nx, ny, nz = grid.dims
    v, origin = grid.voxel_size, np.asarray(grid.origin)
    axes_c = [origin[a] + (np.arange(n) + 0.5) * v for a, n in enumerate(grid.dims)]  # voxel centres per axis
    occupied = []
    for obj in local:
        lo, hi = obj.aabb()
        near = [(c + v / 2 > lo[a]) & (c - v / 2 < hi[a]) for a, c in enumerate(axes_c)]
        candidates = np.argwhere(near[0][:, None, None] & near[1][None, :, None] & near[2][None, None, :])
        hit = candidates[obj.overlaps(_centres(grid, candidates), v / 2)]
        occupied.append(_flat(grid, hit))
    return _assign(grid, local, occupied)
