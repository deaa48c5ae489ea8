"""Procedural towns: a seeded street grid with everything a CARLA street scene holds.

World frame: REP-103 (x east, y north, z up; metres), ground level at z = 0,
origin at the town centre. Roads run along x and along y and cross at
intersections; blocks between them hold buildings, parks, parking lots and
plazas; a canal with bridges and a tram track appear where they fit. Every
static object is a SceneObject with a CARLA 0.9.12 label; traffic (vehicles,
pedestrians) lives in traffic.py and moves over the lanes and sidewalks
exported here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from co3sop_nodes.common.classes import LABEL_BY_NAME as L
from co3sop_nodes.sim.scene import SceneObject
from co3sop_nodes.sim.shapes import Box, Cylinder, Sphere

LANE_WIDTH = 3.5  # m
SIDEWALK_WIDTH = 3.5  # m
CURB = 0.15  # sidewalk top above the road, m
SURFACE_DEPTH = 0.3  # road / ground slabs reach this far below z = 0, m


@dataclass(frozen=True)
class TownConfig:
    size: float = 260.0  # side of the square town, m
    block_min: float = 50.0  # block pitch range (road centre to road centre), m
    block_max: float = 85.0
    canal: bool = True  # a canal with bridges across one block row
    tram: bool = True  # tram tracks along one avenue in x and one in y


@dataclass(frozen=True)
class Road:
    """A straight road between two intersections (or the town edge)."""

    axis: int  # 0: runs along x, 1: along y
    offset: float  # its centre line's y (axis 0) or x (axis 1), m
    start: float  # extent along its axis, m
    end: float
    lanes_per_direction: int

    @property
    def half_width(self) -> float:
        return self.lanes_per_direction * LANE_WIDTH


@dataclass(frozen=True)
class Lane:
    """A directed lane centre line from `start` to `end` (2D points, m)."""

    start: tuple[float, float]
    end: tuple[float, float]
    road: int  # index into Town.roads


@dataclass
class Town:
    config: TownConfig
    seed: int
    objects: list[SceneObject] = field(default_factory=list)
    roads: list[Road] = field(default_factory=list)
    lanes: list[Lane] = field(default_factory=list)
    intersections: list[tuple[float, float]] = field(default_factory=list)
    sidewalk_paths: list[tuple[tuple[float, float], tuple[float, float]]] = field(default_factory=list)
    parking: list[tuple[float, float, float]] = field(default_factory=list)  # (x, y, yaw) of parking spots

    def add(self, label: str, primitives, colour, texture: str = "plain") -> SceneObject:
        obj = SceneObject(len(self.objects) + 1, L[label], tuple(primitives), tuple(int(c) for c in colour), texture)
        self.objects.append(obj)
        return obj


def _lines(rng: np.random.Generator, size: float, lo: float, hi: float) -> list[float]:
    """Road centre offsets across the town, spaced lo..hi apart, roughly centred."""
    offsets, pos = [], -size / 2 + rng.uniform(lo / 3, lo / 2)
    while pos < size / 2 - lo / 3:
        offsets.append(pos)
        pos += rng.uniform(lo, hi)
    return offsets


def _vary(rng: np.random.Generator, colour, amount: int = 18) -> np.ndarray:
    return np.clip(np.asarray(colour) + rng.integers(-amount, amount + 1, 3), 0, 255)


def _box(x0, y0, x1, y1, z0, z1, yaw: float = 0.0) -> Box:
    return Box.make([(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2], [abs(x1 - x0), abs(y1 - y0), z1 - z0], yaw)


def _along(axis: int, offset: float, a: float, b: float, across0: float, across1: float, z0: float, z1: float) -> Box:
    """A box spanning [a, b] along `axis` and [offset + across0, offset + across1] across it."""
    if axis == 0:
        return _box(a, offset + across0, b, offset + across1, z0, z1)
    return _box(offset + across0, a, offset + across1, b, z0, z1)


def generate_town(cfg: TownConfig, seed: int) -> Town:
    rng = np.random.default_rng(seed)
    town = Town(cfg, seed)
    half = cfg.size / 2
    xs = _lines(rng, cfg.size, cfg.block_min, cfg.block_max)  # x of the roads running along y
    ys = _lines(rng, cfg.size, cfg.block_min, cfg.block_max)  # y of the roads running along x
    widths = {(0, y): int(rng.choice([1, 2], p=[0.6, 0.4])) for y in ys} | {
        (1, x): int(rng.choice([1, 2], p=[0.6, 0.4])) for x in xs
    }
    canal_row = int(rng.integers(0, len(ys) - 1)) if cfg.canal and len(ys) > 1 else None
    canal_y = (ys[canal_row] + ys[canal_row + 1]) / 2 if canal_row is not None else None
    # the tram runs along one avenue each way
    trams = (
        {(0, ys[int(rng.integers(0, len(ys)))]), (1, xs[int(rng.integers(0, len(xs)))])}
        if cfg.tram and xs and ys
        else set()
    )

    _terrain_base(town, rng, half)
    for (axis, offset), lanes in widths.items():
        crossing = ys if axis == 1 else xs
        _road(town, rng, axis, offset, lanes, crossing, widths, half, canal_y, tram=(axis, offset) in trams)
    for x in xs:
        for y in ys:
            town.intersections.append((x, y))
            _intersection(town, rng, x, y, widths[(1, x)], widths[(0, y)])
    # blocks between consecutive roads (and the town edge)
    bx = [-half, *xs, half]
    by = [-half, *ys, half]
    for i in range(len(bx) - 1):
        for j in range(len(by) - 1):
            x0 = bx[i] + (widths[(1, bx[i])] * LANE_WIDTH + SIDEWALK_WIDTH if i > 0 else 0)
            x1 = bx[i + 1] - (widths[(1, bx[i + 1])] * LANE_WIDTH + SIDEWALK_WIDTH if i + 1 < len(bx) - 1 else 0)
            y0 = by[j] + (widths[(0, by[j])] * LANE_WIDTH + SIDEWALK_WIDTH if j > 0 else 0)
            y1 = by[j + 1] - (widths[(0, by[j + 1])] * LANE_WIDTH + SIDEWALK_WIDTH if j + 1 < len(by) - 1 else 0)
            if x1 - x0 < 8 or y1 - y0 < 8:
                continue
            if canal_row is not None and j == canal_row + 1:
                _canal_block(town, rng, x0, y0, x1, y1, canal_y)
            else:
                _block(town, rng, x0, y0, x1, y1)
    return town


def _terrain_base(town: Town, rng, half: float) -> None:
    """Everything not covered by something else is terrain, its top just under the road surface."""
    # it reaches 100 m past the streets, so no sensor near the rim looks into a void
    town.add(
        "terrain",
        [_box(-half - 100, -half - 100, half + 100, half + 100, -SURFACE_DEPTH, -0.02)],
        (120, 150, 80),
        "noise",
    )


def _road(town: Town, rng, axis, offset, lanes, crossing, widths, half, canal_y, tram: bool) -> None:
    hw = lanes * LANE_WIDTH
    other = 0 if axis == 1 else 1
    cuts = [-half, *crossing, half]
    for a, b in zip(cuts[:-1], cuts[1:]):
        # the stretch between intersections (intersections themselves are separate squares)
        a_in = a + (widths[(other, a)] * LANE_WIDTH if a > -half else 0)
        b_in = b - (widths[(other, b)] * LANE_WIDTH if b < half else 0)
        if b_in - a_in < 1:
            continue
        town.roads.append(Road(axis, offset, a_in, b_in, lanes))
        over_canal = canal_y is not None and axis == 1 and a < canal_y < b
        if over_canal:
            gap = (canal_y - 9, canal_y + 9)  # canal width 14 m plus abutments
            for s0, s1 in ((a_in, gap[0]), (gap[1], b_in)):
                town.add("road", [_along(axis, offset, s0, s1, -hw, hw, -SURFACE_DEPTH, 0)], (90, 90, 95), "noise")
            _bridge(town, rng, axis, offset, gap, hw)
        else:
            town.add("road", [_along(axis, offset, a_in, b_in, -hw, hw, -SURFACE_DEPTH, 0)], (90, 90, 95), "noise")
        _markings(town, rng, axis, offset, a_in, b_in, lanes, tram)
        _sidewalks(town, rng, axis, offset, a_in, b_in, hw, over_canal and canal_y)
        # lanes: right-hand traffic; direction +axis on the right (negative across side for +x, ...)
        # on two-lane roads the outer lanes are parking lanes: parked rows stand there, traffic keeps inside
        for k in range(lanes - (1 if lanes > 1 else 0)):
            across = (k + 0.5) * LANE_WIDTH
            p, q = (
                _point(axis, offset, a_in, -across if axis == 0 else across),
                _point(axis, offset, b_in, -across if axis == 0 else across),
            )
            town.lanes.append(Lane(p, q, len(town.roads) - 1))
            p2, q2 = (
                _point(axis, offset, b_in, across if axis == 0 else -across),
                _point(axis, offset, a_in, across if axis == 0 else -across),
            )
            town.lanes.append(Lane(p2, q2, len(town.roads) - 1))


def _point(axis: int, offset: float, along: float, across: float) -> tuple[float, float]:
    return (along, offset + across) if axis == 0 else (offset + across, along)


def _markings(town: Town, rng, axis, offset, a, b, lanes, tram: bool) -> None:
    colour = (235, 235, 220)
    if tram:
        # tram track on the centre line: sleepers bed + two rails
        town.add("railtrack", [_along(axis, offset, a, b, -0.9, 0.9, -0.05, 0.06)], (110, 95, 80), "stripes")
    else:
        # solid double centre line
        town.add(
            "roadline",
            [_along(axis, offset, a, b, -0.25, -0.1, -0.05, 0.02), _along(axis, offset, a, b, 0.1, 0.25, -0.05, 0.02)],
            colour,
        )
    for k in range(1, lanes):  # dashed lane separators
        dashes = []
        for s in np.arange(a + 1.0, b - 3.0, 9.0):
            for side in (-1, 1):
                dashes.append(
                    _along(
                        axis,
                        offset,
                        s,
                        s + 3.0,
                        side * k * LANE_WIDTH - 0.075,
                        side * k * LANE_WIDTH + 0.075,
                        -0.05,
                        0.02,
                    )
                )
        if dashes:
            town.add("roadline", dashes, colour)
    for end, sign in ((a, 1), (b, -1)):  # stop lines before the intersections
        s0 = end + sign * 0.5
        for side in (-1, 1):
            town.add(
                "roadline",
                [
                    _along(
                        axis,
                        offset,
                        min(s0, s0 + sign * 0.4),
                        max(s0, s0 + sign * 0.4),
                        side * 0.3,
                        side * lanes * LANE_WIDTH,
                        -0.05,
                        0.02,
                    )
                ],
                colour,
            )


def _sidewalks(town: Town, rng, axis, offset, a, b, hw, canal_y) -> None:
    for side in (-1, 1):
        lo, hi = sorted((side * hw, side * (hw + SIDEWALK_WIDTH)))
        spans = [(a, b)]
        if canal_y:
            spans = [(a, canal_y - 9), (canal_y + 9, b)]
        for s0, s1 in spans:
            if s1 - s0 < 1:
                continue
            town.add(
                "sidewalk", [_along(axis, offset, s0, s1, lo, hi, -SURFACE_DEPTH, CURB)], (175, 170, 165), "bricks"
            )
            mid = side * (hw + SIDEWALK_WIDTH / 2)
            town.sidewalk_paths.append((_point(axis, offset, s0, mid), _point(axis, offset, s1, mid)))
            _street_furniture(town, rng, axis, offset, s0, s1, side, hw)


def _street_furniture(town: Town, rng, axis, offset, a, b, side, hw) -> None:
    """Street lights, signs, trees, props and parked rows along one sidewalk."""
    edge = side * (hw + 0.5)  # just inside the curb
    s = a + rng.uniform(2, 8)
    while s < b - 2:
        x, y = _point(axis, offset, s, edge)
        kind = rng.choice(["light", "sign", "tree", "prop", "bush", "none"], p=[0.25, 0.12, 0.25, 0.15, 0.13, 0.10])
        if kind == "light":
            arm_x, arm_y = _point(axis, offset, s, edge - side * 1.5)
            town.add(
                "pole",
                [
                    Cylinder(x, y, 0.12, CURB, 7.5),
                    _box(
                        min(x, arm_x) - 0.08, min(y, arm_y) - 0.08, max(x, arm_x) + 0.08, max(y, arm_y) + 0.08, 7.3, 7.5
                    ),
                ],
                (120, 120, 125),
            )
        elif kind == "sign":
            town.add("pole", [Cylinder(x, y, 0.05, CURB, 2.8)], (140, 140, 145))
            town.add(
                "trafficsign",
                [Box.make([x, y, 2.5], [0.08, 0.7, 0.7], yaw=0.0 if axis == 0 else np.pi / 2)],
                (200, 30, 30),
            )
        elif kind == "tree":
            h = rng.uniform(3, 5)
            town.add(
                "vegetation",
                [Cylinder(x, y, 0.18, CURB, h), Sphere(np.array([x, y, h + 1.0]), rng.uniform(1.5, 2.6))],
                _vary(rng, (70, 110, 40), 25),
                "noise",
            )
        elif kind == "bush":
            town.add(
                "vegetation",
                [Sphere(np.array([x, y, CURB + 0.3]), rng.uniform(0.5, 0.9))],
                _vary(rng, (60, 120, 45), 25),
                "noise",
            )
        elif kind == "prop":
            _prop(town, rng, axis, offset, s, side * (hw + SIDEWALK_WIDTH - 0.8))
        s += rng.uniform(6, 14)
    # a parked row in the parking lane of a two-lane road (vehicles are placed by traffic.py)
    if hw > LANE_WIDTH and rng.random() < 0.6 and b - a > 20:
        start = rng.uniform(a + 3, (a + b) / 2)
        stop = min(b - 3, start + rng.uniform(15, 40))
        yaw = 0.0 if axis == 0 else np.pi / 2
        for s in np.arange(start, stop, 6.5):
            px, py = _point(axis, offset, s, side * (hw - LANE_WIDTH / 2))
            town.parking.append((px, py, yaw))


def _prop(town: Town, rng, axis, offset, s, across) -> None:
    x, y = _point(axis, offset, s, across)
    yaw = 0.0 if axis == 0 else np.pi / 2
    kind = rng.choice(["bench", "hydrant", "bin", "shelter", "cart", "clutter"])
    if kind == "bench":
        town.add(
            "static",
            [Box.make([x, y, CURB + 0.45], [1.6, 0.5, 0.1], yaw), Box.make([x, y, CURB + 0.2], [1.4, 0.4, 0.4], yaw)],
            (120, 80, 50),
        )
    elif kind == "hydrant":
        town.add("static", [Cylinder(x, y, 0.15, CURB, CURB + 0.7)], (200, 40, 30))
    elif kind == "bin":
        town.add("dynamic", [Box.make([x, y, CURB + 0.5], [0.6, 0.6, 1.0], yaw)], _vary(rng, (40, 90, 50)))
    elif kind == "clutter":  # what CARLA leaves untagged (tag 0): construction debris, crates
        town.add(
            "unlabeled",
            [Box.make([x, y, CURB + 0.3], [rng.uniform(0.5, 1.5), 0.6, 0.6], yaw + rng.uniform(-0.5, 0.5))],
            (150, 120, 90),
        )
    elif kind == "cart":
        town.add("dynamic", [Box.make([x, y, CURB + 0.5], [0.9, 0.6, 0.7], yaw)], (160, 160, 170))
    else:  # bus shelter: roof and back wall
        town.add(
            "other",
            [Box.make([x, y, CURB + 2.5], [3.5, 1.6, 0.1], yaw), Box.make([x, y, CURB + 1.25], [3.5, 0.1, 2.3], yaw)],
            (90, 120, 130),
        )


def _intersection(town: Town, rng, x, y, lanes_x_road, lanes_y_road) -> None:
    hx, hy = lanes_x_road * LANE_WIDTH, lanes_y_road * LANE_WIDTH
    town.add("road", [_box(x - hx, y - hy, x + hx, y + hy, -SURFACE_DEPTH, 0)], (90, 90, 95), "noise")
    # corner sidewalks and a traffic light on each corner
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = x + sx * (hx + SIDEWALK_WIDTH / 2), y + sy * (hy + SIDEWALK_WIDTH / 2)
            town.add(
                "sidewalk",
                [
                    _box(
                        cx - SIDEWALK_WIDTH / 2,
                        cy - SIDEWALK_WIDTH / 2,
                        cx + SIDEWALK_WIDTH / 2,
                        cy + SIDEWALK_WIDTH / 2,
                        -SURFACE_DEPTH,
                        CURB,
                    )
                ],
                (175, 170, 165),
                "bricks",
            )
            px, py = x + sx * (hx + 0.6), y + sy * (hy + 0.6)
            arm_end = px - sx * 2.5  # the arm reaches over the road
            town.add(
                "pole",
                [
                    Cylinder(px, py, 0.1, CURB, 5.0),
                    _box(min(px, arm_end) - 0.06, py - 0.06, max(px, arm_end) + 0.06, py + 0.06, 4.8, 5.0),
                ],
                (60, 60, 65),
            )
            hx_arm = px - sx * 2.3
            town.add("trafficlight", [Box.make([hx_arm, py, 4.4], [0.35, 0.35, 1.0])], (40, 40, 40))


def _bridge(town: Town, rng, axis, offset, gap, hw) -> None:
    """A road bridge over the canal: deck, guard rails and a pedestrian walkway."""
    town.add(
        "bridge",
        [
            _along(axis, offset, gap[0], gap[1], -hw - SIDEWALK_WIDTH, hw + SIDEWALK_WIDTH, -0.9, 0.0),
            _along(axis, offset, gap[0] + 4, gap[0] + 5, -hw - 1, hw + 1, -3.5, -0.9),
            _along(axis, offset, gap[1] - 5, gap[1] - 4, -hw - 1, hw + 1, -3.5, -0.9),
        ],
        (150, 140, 130),
        "bricks",
    )
    for side in (-1, 1):
        rail = side * (hw + 0.2)
        town.add(
            "guardrail",
            [
                _along(axis, offset, gap[0], gap[1], rail - 0.1, rail + 0.1, 0.3, 0.9),
                *[
                    _along(axis, offset, s, s + 0.15, rail - 0.08, rail + 0.08, 0.0, 0.3)
                    for s in np.arange(gap[0], gap[1], 2.0)
                ],
            ],
            (170, 170, 175),
        )
        outer = side * (hw + SIDEWALK_WIDTH - 0.1)
        town.add(
            "fence",
            [_along(axis, offset, gap[0], gap[1], outer - 0.05, outer + 0.05, 0.0, 1.1)],
            (120, 110, 100),
            "stripes",
        )


def _canal_block(town: Town, rng, x0, y0, x1, y1, canal_y) -> None:
    """Embankments of terrain, canal walls and water in a block of the canal row."""
    # the water surface stays just below street level: the benchmark grids end 0.1 m under the road
    town.add("water", [_box(x0, canal_y - 7, x1, canal_y + 7, -2.5, -0.05)], (40, 70, 110))
    for side in (-1, 1):
        wall_in = canal_y + side * 7
        town.add(
            "wall",
            [_box(x0, min(wall_in, wall_in + side * 0.5), x1, max(wall_in, wall_in + side * 0.5), -3.5, 0.3)],
            (140, 135, 125),
            "bricks",
        )
        bank0, bank1 = sorted((wall_in + side * 0.5, (y1 if side > 0 else y0)))
        town.add("terrain", [_box(x0, bank0, x1, bank1, -SURFACE_DEPTH, 0.05)], _vary(rng, (110, 150, 70)), "noise")
        # a guard rail along the top of the bank
        rail = wall_in + side * 1.2
        town.add("guardrail", [_box(x0, rail - 0.1, x1, rail + 0.1, 0.4, 0.9)], (170, 170, 175))
        for tx in np.arange(x0 + 4, x1 - 4, rng.uniform(9, 15)):
            ty = (bank0 + bank1) / 2
            if rng.random() < 0.6:
                h = rng.uniform(3, 6)
                town.add(
                    "vegetation",
                    [Cylinder(tx, ty, 0.2, 0.0, h), Sphere(np.array([tx, ty, h + 1.2]), rng.uniform(1.8, 3.0))],
                    _vary(rng, (70, 110, 40), 25),
                    "noise",
                )


def _block(town: Town, rng, x0, y0, x1, y1) -> None:
    kind = rng.choice(["buildings", "buildings", "buildings", "park", "parking", "plaza"])
    if kind == "park":
        town.add("terrain", [_box(x0, y0, x1, y1, -SURFACE_DEPTH, 0.05)], _vary(rng, (100, 150, 60)), "noise")
        town.add(
            "fence", [_box(x0, y0, x1, y0 + 0.1, 0, 1.2), _box(x0, y1 - 0.1, x1, y1, 0, 1.2)], (110, 100, 90), "stripes"
        )
        for _ in range(int((x1 - x0) * (y1 - y0) / 120)):
            tx, ty = rng.uniform(x0 + 3, x1 - 3), rng.uniform(y0 + 3, y1 - 3)
            if rng.random() < 0.7:
                h = rng.uniform(3, 7)
                town.add(
                    "vegetation",
                    [Cylinder(tx, ty, 0.25, 0.0, h), Sphere(np.array([tx, ty, h + 1.3]), rng.uniform(1.8, 3.2))],
                    _vary(rng, (65, 105, 40), 25),
                    "noise",
                )
            else:
                town.add(
                    "vegetation",
                    [Sphere(np.array([tx, ty, 0.4]), rng.uniform(0.6, 1.2))],
                    _vary(rng, (60, 120, 45), 25),
                    "noise",
                )
        return
    if kind == "parking":
        town.add("ground", [_box(x0, y0, x1, y1, -SURFACE_DEPTH, 0.02)], (100, 95, 90), "noise")
        town.add("wall", [_box(x0, y1 - 0.3, x1, y1, 0, 1.5)], (150, 140, 130), "bricks")
        for px in np.arange(x0 + 3, x1 - 3, 3.0):
            for py in (y0 + 4, y1 - 5):
                if rng.random() < 0.6:
                    town.parking.append((px, py, np.pi / 2))
        return
    if kind == "plaza":
        town.add("ground", [_box(x0, y0, x1, y1, -SURFACE_DEPTH, 0.02)], (160, 150, 140), "bricks")
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        town.add(
            "static", [Cylinder(cx, cy, 3.0, 0.0, 0.8), Cylinder(cx, cy, 0.4, 0.8, 2.5)], (180, 180, 190)
        )  # fountain
        for _ in range(4):
            town.add(
                "vegetation",
                [Sphere(np.array([rng.uniform(x0 + 2, x1 - 2), rng.uniform(y0 + 2, y1 - 2), 0.5]), 0.8)],
                _vary(rng, (60, 120, 45), 25),
                "noise",
            )
        return
    # perimeter buildings of varied footprint and height around a yard
    town.add("terrain", [_box(x0, y0, x1, y1, -SURFACE_DEPTH, 0.02)], _vary(rng, (105, 140, 70)), "noise")
    depth = min(rng.uniform(10, 18), (y1 - y0) / 2 - 1, (x1 - x0) / 2 - 1)
    palette = [(200, 190, 170), (160, 80, 60), (120, 120, 125), (220, 215, 205), (150, 130, 100)]
    for side in ("s", "n", "w", "e"):
        along0, along1 = (x0, x1) if side in "sn" else (y0 + depth, y1 - depth)
        s = along0
        while s < along1 - 3:
            width = min(rng.uniform(8, 24), along1 - s)
            gap = rng.uniform(0, 2.5) if rng.random() < 0.4 else 0.0
            height = rng.choice([rng.uniform(4, 9), rng.uniform(9, 20), rng.uniform(20, 40)], p=[0.4, 0.4, 0.2])
            if side == "s":
                fp = (s, y0, s + width - gap, y0 + depth)
            elif side == "n":
                fp = (s, y1 - depth, s + width - gap, y1)
            elif side == "w":
                fp = (x0, s, x0 + depth, s + width - gap)
            else:
                fp = (x1 - depth, s, x1, s + width - gap)
            colour = _vary(rng, palette[int(rng.integers(0, len(palette)))])
            prims = [_box(*fp, -SURFACE_DEPTH, height)]
            if rng.random() < 0.3:  # an L-shaped or stepped building: a second, lower wing
                fx0, fy0, fx1, fy1 = fp
                prims.append(_box(fx0, fy0, (fx0 + fx1) / 2, fy1, -SURFACE_DEPTH, height * rng.uniform(1.2, 1.6)))
            town.add("building", prims, colour, "bricks")
            if gap > 1.0 and rng.random() < 0.5:  # a wall or fence closing the gap
                gx0, gy0, gx1, gy1 = fp
                label = "wall" if rng.random() < 0.5 else "fence"
                if side in "sn":
                    edge = gy0 if side == "s" else gy1
                    town.add(label, [_box(gx1, edge - 0.1, gx1 + gap, edge + 0.1, 0, 2.0)], (150, 145, 140))
                else:
                    edge = gx0 if side == "w" else gx1
                    town.add(label, [_box(edge - 0.1, gy1, edge + 0.1, gy1 + gap, 0, 2.0)], (150, 145, 140))
            s += width
