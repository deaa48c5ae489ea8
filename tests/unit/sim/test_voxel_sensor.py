"""Unit tests for co3sop_nodes.sim.voxel_sensor: the three-stage annotator against its oracles.

Random scenes are built in the sensor frame and moved to the world by the test
itself, so a third oracle (every voxel centre against every sensor-frame
primitive, then the overlap rule) shares nothing with the module but the
primitives' overlap tests (covered by test_shapes.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from co3sop_nodes.common.classes import LABEL_BY_NAME as L
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.sim import rig
from co3sop_nodes.sim.scene import SceneObject
from co3sop_nodes.sim.shapes import Box, Cylinder, Sphere
from co3sop_nodes.sim.town import TownConfig, generate_town
from co3sop_nodes.sim.traffic import Traffic, TrafficConfig
from co3sop_nodes.sim.voxel_sensor import LABEL_PRIORITY, annotate, annotate_brute_force

SMALL = GridSpec((-4.0, -4.0, -2.0), 0.2, (40, 40, 24))

# the overlap rule as the module documents it, lowest first (written out here, not imported)
SPEC_PRIORITY = (
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


# --- helpers ------------------------------------------------------------------------------------


def pose(yaw: float = 0.0, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0, t[0]], [s, c, 0, t[1]], [0, 0, 1, t[2]], [0, 0, 0, 1.0]])


def to_world(p, m: np.ndarray):
    """A sensor-frame primitive in the world, for a yaw + translation pose m (written independently of scene.py)."""
    r, t = m[:3, :3], m[:3, 3]
    if isinstance(p, Box):
        return Box(r @ p.center + t, p.half.copy(), r @ p.rot)
    if isinstance(p, Sphere):
        return Sphere(r @ p.center + t, p.radius)
    x, y = (r[:2, :2] @ [p.x, p.y]) + t[:2]
    return Cylinder(float(x), float(y), p.radius, p.z0 + t[2], p.z1 + t[2])


def centres(grid: GridSpec) -> np.ndarray:
    axes = [grid.origin[a] + (np.arange(n) + 0.5) * grid.voxel_size for a, n in enumerate(grid.dims)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def overlap_mask(thing, c: np.ndarray, h: float) -> np.ndarray:
    """thing.overlaps(c, h), evaluated only near its bounding box (a cull only: test_shapes checks
    that nothing overlaps a cube whose centre lies outside the box grown by half)."""
    lo, hi = thing.aabb()
    near = np.flatnonzero(((c > lo - h - 1e-9) & (c < hi + h + 1e-9)).all(axis=1))
    out = np.zeros(len(c), bool)
    out[near] = thing.overlaps(c[near], h)
    return out


def oracle(local: list[SceneObject], grid: GridSpec) -> np.ndarray:
    """Every voxel against every sensor-frame object; the higher SPEC_PRIORITY label wins."""
    rank = {L[name]: i + 1 for i, name in enumerate(SPEC_PRIORITY)}
    c = centres(grid)
    best = np.zeros(len(c), int)
    labels = np.zeros(len(c), np.uint8)
    for obj in local:
        hit = overlap_mask(obj, c, grid.voxel_size / 2) & (rank[obj.label] > best)
        best[hit], labels[hit] = rank[obj.label], obj.label
    return labels.reshape(grid.dims)


def random_primitive(rng, kind: str):
    c = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-2.6, 3.4)])  # grid: +-4 m, -2..2.8 m
    if kind == "box":
        size = np.exp(rng.uniform(np.log(0.1), np.log(5.0), 3))
        angles = rng.uniform(-np.pi, np.pi, 3) if rng.random() < 0.7 else (rng.uniform(-np.pi, np.pi), 0.0, 0.0)
        return Box.make(c, size, *angles)
    if kind == "thin":  # a sheet or a wire, thinner than a voxel
        size = np.exp(rng.uniform(np.log(0.5), np.log(6.0), 3))
        size[rng.choice(3, int(rng.integers(1, 3)), replace=False)] = rng.uniform(0.01, 0.05)
        return Box.make(c, size, *rng.uniform(-np.pi, np.pi, 3))
    if kind == "cylinder":
        z0 = c[2] - rng.uniform(0.05, 4)
        return Cylinder(
            float(c[0]), float(c[1]), float(np.exp(rng.uniform(np.log(0.01), np.log(1.5)))), float(z0), float(c[2])
        )
    return Sphere(c, float(rng.uniform(0.05, 2.0)))


def random_scene(seed: int) -> tuple[list[SceneObject], list[SceneObject], np.ndarray]:
    """(world objects, the same objects in the sensor frame, world_from_sensor)."""
    rng = np.random.default_rng(seed)
    world_from_sensor = pose(rng.uniform(-np.pi, np.pi), rng.uniform([-60, -60, -3], [60, 60, 3]))
    local = []
    labels = [L[n] for n in SPEC_PRIORITY]
    # a ground slab whose top sits on a voxel boundary, or between boundaries
    top = -1.0 if seed % 2 else -0.93
    local.append(SceneObject(1, L["road"], (Box.make([0, 0, top - 0.15], [12, 12, 0.3], rng.uniform(-0.3, 0.3)),)))
    for i in range(int(rng.integers(8, 15))):
        kinds = rng.choice(["box", "thin", "cylinder", "sphere"], int(rng.integers(1, 4)), p=[0.35, 0.25, 0.2, 0.2])
        prims = tuple(random_primitive(rng, str(k)) for k in kinds)
        local.append(SceneObject(i + 2, int(rng.choice(labels)), prims))
    world = [SceneObject(o.id, o.label, tuple(to_world(p, world_from_sensor) for p in o.primitives)) for o in local]
    order = rng.permutation(len(world))  # list order must not matter
    return [world[i] for i in order], local, world_from_sensor


# --- annotate == oracles on random scenes -----------------------------------------------------------


@pytest.mark.parametrize("compiled", [True, False], ids=["kernel", "numpy"])
@pytest.mark.parametrize("seed", range(24))
def test_annotate_equals_brute_force_on_random_scenes(seed, compiled):
    world, local, world_from_sensor = random_scene(seed)
    got = annotate(world, world_from_sensor, SMALL, compiled=compiled)
    assert got.shape == SMALL.dims and got.dtype == np.uint8
    brute = annotate_brute_force(world, world_from_sensor, SMALL)
    np.testing.assert_array_equal(got, brute)
    np.testing.assert_array_equal(got, oracle(local, SMALL))
    # not a trivial scene: many voxels, several labels, and the labels come from the objects only
    assert (got > 0).sum() > 500
    values = set(np.unique(got).tolist())
    assert len(values - {0}) >= 3
    assert values <= {0} | {o.label for o in world}


def test_random_scenes_exercise_overlaps_and_thin_objects():
    # the scenes above contain what they claim: contested voxels and sub-voxel primitives that
    # no column centre hits
    contested = thin_missed = 0
    for seed in range(24):
        _, local, _ = random_scene(seed)
        c = centres(SMALL)
        per_label = {}
        for o in local:
            per_label[o.label] = per_label.get(o.label, False) | overlap_mask(o, c, 0.1)
        contested += int((np.sum(list(per_label.values()), axis=0) > 1).sum())
        cols = c.reshape(*SMALL.dims, 3)[:, :, 0, :2].reshape(-1, 2)
        for o in local:
            for p in o.primitives:
                if overlap_mask(p, c, 0.1).any() and not np.isfinite(p.vertical_entry(cols)).any():
                    thin_missed += 1
    assert contested > 1000
    assert thin_missed >= 15


@pytest.mark.parametrize("compiled", [True, False], ids=["kernel", "numpy"])
@pytest.mark.parametrize("workers", [1, 4])
def test_worker_count_does_not_change_the_result(workers, compiled):
    world, _, world_from_sensor = random_scene(100)
    np.testing.assert_array_equal(
        annotate(world, world_from_sensor, SMALL, workers=workers, compiled=compiled),
        annotate(world, world_from_sensor, SMALL, workers=2),
    )


# --- a procedural town around a CAV ---------------------------------------------------------------


@pytest.mark.parametrize("compiled", [True, False], ids=["kernel", "numpy"])
@pytest.mark.parametrize("seed", [0, 5])
def test_annotate_equals_brute_force_in_a_town(seed, compiled):
    town = generate_town(TownConfig(), seed)
    traffic = Traffic(town, TrafficConfig(), seed + 1)
    for _ in range(3):
        traffic.step()
    objects = town.objects + traffic.objects()
    cav = traffic.cavs[0]
    world_from_lidar = cav.pose() @ rig.vehicle_from_lidar()
    grid = GridSpec.centred(12.8, (-2.0, 2.8), 0.2)
    got = annotate(objects, world_from_lidar, grid, ignore=(cav.id,), compiled=compiled)
    np.testing.assert_array_equal(got, annotate_brute_force(objects, world_from_lidar, grid, ignore=(cav.id,)))
    body = np.linalg.inv(rig.vehicle_from_lidar()) @ [0.0, 0.0, 0.5, 1.0]  # a point of its body, vehicle frame
    ijk = tuple(np.floor((body[:3] - np.array(grid.origin)) / grid.voxel_size).astype(int))
    # the sensor ignores the CAV that carries it (Co3SOP's self_ignore) ...
    assert got[ijk] == L["empty"]
    assert annotate(objects, world_from_lidar, grid, compiled=compiled)[ijk] == L["vehicle"]
    # ... and the road surface lies just under it (world z in (-0.2, 0])
    under = np.linalg.inv(rig.vehicle_from_lidar()) @ [2.0, 0.0, -0.05, 1.0]
    assert got[tuple(np.floor((under[:3] - np.array(grid.origin)) / grid.voxel_size).astype(int))] in (
        L["road"],
        L["roadline"],
        L["railtrack"],
    )
    assert L["road"] in set(np.unique(got).tolist())


def test_only_the_carrying_cav_is_ignored():
    """Another CAV in the grid stays labelled: ignoring is by object id, not by class."""
    seed = 0
    town = generate_town(TownConfig(), seed)
    traffic = Traffic(town, TrafficConfig(cavs=2), seed + 1)
    objects = town.objects + traffic.objects()
    me, other = traffic.cavs[:2]
    world_from_lidar = me.pose() @ rig.vehicle_from_lidar()
    grid = GridSpec.centred(76.8, (-2.0, 2.8), 0.3)
    sensor_from_world = np.linalg.inv(world_from_lidar)

    def voxel(world_point):
        p = sensor_from_world @ world_point  # homogeneous (4,)
        return tuple(np.floor((p[:3] - np.array(grid.origin)) / grid.voxel_size).astype(int))

    other_body = voxel(other.pose() @ [0.0, 0.0, 0.8, 1.0])
    assert all(0 <= i < n for i, n in zip(other_body, grid.dims)), "the two CAVs start within 38 m of each other"
    got = annotate(objects, world_from_lidar, grid, ignore=(me.id,))
    assert got[other_body] == L["vehicle"]
    assert got[voxel(me.pose() @ [0.0, 0.0, 0.8, 1.0])] == L["empty"]


# --- the overlap rule ---------------------------------------------------------------------------


def test_label_priority_is_the_documented_order():
    assert LABEL_PRIORITY == tuple(L[n] for n in SPEC_PRIORITY)
    assert sorted(LABEL_PRIORITY) == [v for v in range(1, 24) if v != L["sky"]]


OVERLAP_GRID = GridSpec((-1.0, -1.0, -1.0), 0.2, (10, 10, 10))  # layer k spans z in [-1 + 0.2k, -0.8 + 0.2k)


def _labels_of(objects, grid=OVERLAP_GRID, world_from_sensor=None):
    m = np.eye(4) if world_from_sensor is None else world_from_sensor
    got = annotate(objects, m, grid)  # the kernel where it compiles, as the simulator runs
    np.testing.assert_array_equal(got, annotate_brute_force(objects, m, grid))
    np.testing.assert_array_equal(got, annotate(objects, m, grid, compiled=False))
    return got


@pytest.mark.parametrize("reverse", [False, True])
def test_pole_over_sidewalk_is_pole(reverse):
    sidewalk = SceneObject(1, L["sidewalk"], (Box.make([0, 0, -0.075], [2, 2, 0.45]),))  # z -0.3 .. 0.15
    pole = SceneObject(2, L["pole"], (Cylinder(0.1, 0.1, 0.12, 0.15, 0.9),))  # stands on the sidewalk's top
    objs = [pole, sidewalk] if reverse else [sidewalk, pole]
    got = _labels_of(objs)
    # layer 5 (z 0 .. 0.2) holds both the sidewalk's top and the pole's foot
    assert got[5, 5, 5] == L["pole"]  # voxel x, y in (0, 0.2): the pole's axis
    assert got[8, 8, 5] == L["sidewalk"]  # away from the pole
    assert got[5, 5, 4] == L["sidewalk"]  # below the pole's foot
    assert got[5, 5, 6] == L["pole"]


@pytest.mark.parametrize("reverse", [False, True])
def test_vehicle_over_road_is_vehicle(reverse):
    road = SceneObject(7, L["road"], (Box.make([0, 0, -0.15], [4, 4, 0.3]),))
    car = SceneObject(3, L["vehicle"], (Box.make([0, 0, 0.75], [1.6, 0.8, 1.4], yaw=0.3),))  # z 0.05 .. 1.45
    # a grid whose layer boundaries fall at z = -0.1, 0.1, ...: the layer (-0.1, 0.1) holds both
    grid = GridSpec((-1.1, -1.1, -1.1), 0.2, (11, 11, 10))
    objs = [car, road] if reverse else [road, car]
    got = _labels_of(objs, grid)
    assert got[5, 5, 5] == L["vehicle"]
    assert got[5, 5, 4] == L["road"]
    assert got[0, 5, 5] == L["road"]  # beside the car


@pytest.mark.parametrize(
    "low, high",
    [
        ("road", "roadline"),
        ("sidewalk", "pedestrian"),
        ("terrain", "vegetation"),
        ("pole", "trafficsign"),
        ("road", "railtrack"),
        ("building", "vehicle"),
        ("unlabeled", "terrain"),
    ],
)
def test_documented_pairs(low, high):
    a = SceneObject(1, L[high], (Box.make([0.05, 0.05, 0.05], [0.3, 0.3, 0.3]),))
    b = SceneObject(2, L[low], (Box.make([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]),))
    got = _labels_of([a, b])
    assert got[5, 5, 5] == L[high]
    assert got[3, 3, 3] == L[low]


def test_every_pair_follows_the_priority():
    for i, low in enumerate(SPEC_PRIORITY):
        for high in SPEC_PRIORITY[i + 1 :]:
            # give the lower label the larger id too: neither id nor list order decides
            objs = [
                SceneObject(9, L[low], (Box.make([0, 0, 0], [0.4, 0.4, 0.4]),)),
                SceneObject(1, L[high], (Box.make([0, 0, 0], [0.2, 0.2, 0.2]),)),
            ]
            got = annotate(objs, np.eye(4), GridSpec((-0.2, -0.2, -0.2), 0.2, (2, 2, 2)))
            assert (got == L[high]).all(), (low, high)


# --- strictness ---------------------------------------------------------------------------------


def test_road_top_on_a_voxel_boundary_does_not_leak_upwards():
    road = SceneObject(1, L["road"], (Box.make([0, 0, -0.15], [20, 20, 0.3]),))  # z -0.3 .. 0
    got = _labels_of([road], SMALL)  # layer k spans z in [-2 + 0.2k, -1.8 + 0.2k): z = 0 is a boundary
    occupied_layers = sorted(set(np.argwhere(got)[:, 2].tolist()))
    assert occupied_layers == [8, 9]  # (-0.4, -0.2) and (-0.2, 0)
    assert (got[:, :, 8:10] == L["road"]).all()


@pytest.mark.parametrize("height, layers", [(1.8, [0]), (2.0, []), (1.6, [0, 1]), (1.9, [0])])
def test_road_under_a_raised_turned_sensor(height, layers):
    road = SceneObject(1, L["road"], (Box.make([30, -20, -0.15], [80, 80, 0.3]),))  # z -0.3 .. 0
    world_from_sensor = pose(0.7, (30.3, -20.1, height))  # the grid starts 2 m under the sensor
    got = _labels_of([road], SMALL, world_from_sensor)
    assert sorted(set(np.argwhere(got)[:, 2].tolist())) == layers


def test_sub_voxel_wire_and_pole_between_column_centres_are_found():
    grid = GridSpec((-2.0, -2.0, -1.0), 0.2, (20, 20, 10))  # column centres at +-0.1, +-0.3, ...
    wire = Box.make([0.0, 0.03, 0.5], [2.0, 0.02, 0.02])  # x -1 .. 1, y 0.02 .. 0.04, z 0.49 .. 0.51
    pole = Cylinder(0.53, 0.53, 0.01, -0.5, 0.5)
    diagonal = Box.make([-1.0, -1.0, -0.5], [1.5, 0.02, 0.02], yaw=0.6, pitch=0.3)
    cols = centres(grid).reshape(*grid.dims, 3)[:, :, 0, :2].reshape(-1, 2)
    for p in (wire, pole):
        assert not np.isfinite(p.vertical_entry(cols)).any()  # stage 1 misses them
    got = _labels_of([SceneObject(1, L["other"], (wire,)), SceneObject(2, L["pole"], (pole,))], grid)
    assert sorted(map(tuple, np.argwhere(got == L["other"]).tolist())) == [(i, 10, 7) for i in range(5, 15)]
    assert sorted(map(tuple, np.argwhere(got == L["pole"]).tolist())) == [(12, 12, k) for k in range(2, 8)]
    # one object of a big box and a far-away wire: both parts are found
    combo = SceneObject(3, L["fence"], (Box.make([1.5, 1.5, 0.0], [0.6, 0.6, 0.6]), diagonal))
    got = _labels_of([combo], grid)
    expected = combo.overlaps(centres(grid), 0.1).reshape(grid.dims)
    np.testing.assert_array_equal(got == L["fence"], expected)
    assert (got[:10, :10] > 0).sum() >= 5  # the wire's part


def test_wire_crossing_the_volume_border():
    wire = Box.make([4.0, 0.03, 0.51], [3.0, 0.02, 0.02], yaw=0.05)  # runs out of the +x face
    got = _labels_of([SceneObject(1, L["other"], (wire,))], SMALL)
    assert (got > 0).sum() >= 5
    assert got[-1].any()


# --- degenerate scenes --------------------------------------------------------------------------


def test_empty_scene_is_all_zeros():
    for got in (
        annotate([], np.eye(4), SMALL),
        annotate([], np.eye(4), SMALL, compiled=False),
        annotate_brute_force([], np.eye(4), SMALL),
    ):
        assert got.shape == SMALL.dims and got.dtype == np.uint8 and not got.any()


def test_objects_outside_the_volume_give_zeros():
    far = [
        SceneObject(1, L["building"], (Box.make([20, 0, 0], [5, 5, 5]),)),
        SceneObject(2, L["vegetation"], (Sphere(np.array([0.0, 0.0, 5.0]), 2.0),)),  # bottom at z = 3 > 2.8
        SceneObject(3, L["pole"], (Cylinder(0.0, 0.0, 0.5, -9.0, -2.0),)),
    ]  # top exactly at the grid's bottom
    assert not _labels_of(far, SMALL).any()


def test_labels_only_from_objects():
    world, _, world_from_sensor = random_scene(7)
    relabelled = [SceneObject(o.id, L["unlabeled"] if i % 2 else L["water"], o.primitives) for i, o in enumerate(world)]
    got = annotate(relabelled, world_from_sensor, SMALL)
    assert set(np.unique(got).tolist()) == {0, L["unlabeled"], L["water"]}
