"""Traffic over a town: CAVs and other vehicles driving the lanes, parked rows, pedestrians.

Vehicles follow lane centre lines (right-hand traffic), cross intersections on
smooth turn curves, keep a gap to whatever drives ahead of them, and never
leave the town's interior road network. A vehicle's frame has its origin on
the ground under the centre of its bounding box, x forward, y left, z up
(REP-103). Scenario steps are 0.1 s (10 Hz, as OPV2V).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from co3sop_nodes.common.classes import LABEL_BY_NAME as L
from co3sop_nodes.sim.scene import SceneObject
from co3sop_nodes.sim.shapes import Box, Cylinder, Sphere
from co3sop_nodes.sim.town import Lane, Town

DT = 0.1  # s
# name -> (length, width, height) m, and relative frequency among moving vehicles
VEHICLE_KINDS = {
    "car": ((4.6, 1.9, 1.5), 0.62),
    "van": ((5.4, 2.1, 2.2), 0.18),
    "truck": ((8.5, 2.5, 3.4), 0.12),
    "bus": ((11.0, 2.6, 3.2), 0.08),
}
VEHICLE_COLOURS = [
    (200, 30, 30),
    (30, 60, 160),
    (220, 220, 220),
    (30, 30, 30),
    (150, 150, 155),
    (20, 110, 60),
    (230, 180, 20),
]


def vehicle_primitives(kind: str, size: tuple[float, float, float]) -> tuple[Box, ...]:
    """Collision/visual primitives in the vehicle frame: body plus cabin (or cab plus box)."""
    length, width, height = size
    if kind == "car":
        return (
            Box.make([0, 0, 0.2 + 0.35], [length, width, 0.7]),
            Box.make([-0.2, 0, 0.9 + (height - 0.9) / 2], [length * 0.55, width * 0.9, height - 0.9]),
        )
    if kind == "truck":
        return (
            Box.make([length / 2 - 1.1, 0, 0.3 + (height - 0.6) / 2], [2.2, width, height - 0.6]),
            Box.make([-1.2, 0, 0.3 + (height - 0.3) / 2], [length - 2.4, width, height - 0.3]),
        )
    return (Box.make([0, 0, 0.25 + (height - 0.25) / 2], [length, width, height - 0.25]),)


@dataclass
class Vehicle:
    id: int  # actor id, as CARLA's (also the OPV2V CAV folder name)
    kind: str
    size: tuple[float, float, float]  # length, width, height, m
    colour: tuple[int, int, int]
    connected: bool  # a CAV: carries sensors and communicates
    x: float
    y: float
    yaw: float  # rad, REP-103 world
    speed: float = 0.0  # m/s
    desired: float = 8.0  # m/s
    parked: bool = False
    path: list[np.ndarray] = field(default_factory=list)  # upcoming waypoints (2,)
    lane: int = -1  # the lane it drives, or is heading into

    def pose(self) -> np.ndarray:
        """4x4 world_from_vehicle."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, 0, self.x], [s, c, 0, self.y], [0, 0, 1, 0.0], [0, 0, 0, 1]])


@dataclass
class Pedestrian:
    id: int
    start: np.ndarray
    end: np.ndarray
    t: float  # position along the path, 0..1
    speed: float  # m/s
    colour: tuple[int, int, int]
    direction: int = 1

    def position(self) -> np.ndarray:
        return self.start + self.t * (self.end - self.start)


@dataclass(frozen=True)
class TrafficConfig:
    cavs: int = 3  # connected vehicles (2..7 in OPV2V)
    vehicles: int = 30  # other moving vehicles
    parked_fraction: float = 0.7  # of the town's parking spots holding a car
    pedestrians: int = 40
    cav_radius: float = 45.0  # CAVs start within this distance of a common centre, m


def _lane_length(lane: Lane) -> float:
    return float(np.hypot(lane.end[0] - lane.start[0], lane.end[1] - lane.start[1]))


class Traffic:
    def __init__(self, town: Town, cfg: TrafficConfig, seed: int):
        self.town = town
        self.rng = np.random.default_rng(seed)
        half = town.config.size / 2 - 1.0
        # only lanes between two intersections: vehicles never reach the town edge
        self.lanes = [
            i
            for i, lane in enumerate(town.lanes)
            if all(abs(c) < half - 5 for c in (*lane.start, *lane.end)) and _lane_length(lane) > 10
        ]
        self.vehicles: list[Vehicle] = []
        self.pedestrians: list[Pedestrian] = []
        self._next_id = 600 + int(self.rng.integers(0, 400))
        self._spawn(cfg)

    # --- spawning -------------------------------------------------------------------------------

    def _new_id(self) -> int:
        self._next_id += int(self.rng.integers(1, 40))
        return self._next_id

    def _free(self, x: float, y: float, clearance: float) -> bool:
        return all(np.hypot(v.x - x, v.y - y) > clearance for v in self.vehicles)

    def _spawn_on_lane(self, kind: str, connected: bool, lanes: list[int]) -> bool:
        size = VEHICLE_KINDS[kind][0]
        for _ in range(50):
            li = int(self.rng.choice(lanes))
            lane = self.town.lanes[li]
            start, end = np.array(lane.start), np.array(lane.end)
            s = self.rng.uniform(0.15, 0.85)
            pos = start + s * (end - start)
            if not self._free(*pos, size[0] + 6.0):
                continue
            yaw = float(np.arctan2(*(end - start)[::-1]))
            colour = VEHICLE_COLOURS[int(self.rng.integers(0, len(VEHICLE_COLOURS)))]
            v = Vehicle(
                self._new_id(),
                kind,
                size,
                colour,
                connected,
                float(pos[0]),
                float(pos[1]),
                yaw,
                desired=float(self.rng.uniform(6, 11) if kind in ("car", "van") else self.rng.uniform(5, 8)),
            )
            v.speed = v.desired * self.rng.uniform(0.5, 1.0)
            v.path, v.lane = [end], li
            self.vehicles.append(v)
            return True
        return False

    def _spawn(self, cfg: TrafficConfig) -> None:
        # CAVs: cars near a common centre (an intersection), so they can collaborate
        centre = np.array(self.town.intersections[int(self.rng.integers(0, len(self.town.intersections)))])
        near = [
            i
            for i in self.lanes
            if np.hypot(*(np.add(self.town.lanes[i].start, self.town.lanes[i].end) / 2 - centre)) < cfg.cav_radius
        ]
        for _ in range(cfg.cavs):
            if not self._spawn_on_lane("car", True, near or self.lanes):
                self._spawn_on_lane("car", True, self.lanes)
        kinds, weights = zip(*[(k, w) for k, (_, w) in VEHICLE_KINDS.items()])
        for _ in range(cfg.vehicles):
            kind = str(self.rng.choice(kinds, p=np.array(weights) / sum(weights)))
            # half of the traffic near the CAVs, where it occludes and matters
            self._spawn_on_lane(kind, False, near if near and self.rng.random() < 0.5 else self.lanes)
        for x, y, yaw in self.town.parking:
            if self.rng.random() < cfg.parked_fraction and self._free(x, y, 5.0):
                kind = "car" if self.rng.random() < 0.8 else "van"
                colour = VEHICLE_COLOURS[int(self.rng.integers(0, len(VEHICLE_COLOURS)))]
                self.vehicles.append(
                    Vehicle(self._new_id(), kind, VEHICLE_KINDS[kind][0], colour, False, x, y, yaw, parked=True)
                )
        paths = self.town.sidewalk_paths
        for i in range(cfg.pedestrians if paths else 0):
            a, b = paths[int(self.rng.integers(0, len(paths)))]
            colour = tuple(int(c) for c in self.rng.integers(30, 230, 3))
            self.pedestrians.append(
                Pedestrian(
                    5000 + i, np.array(a), np.array(b), self.rng.uniform(0, 1), self.rng.uniform(0.9, 1.6), colour
                )
            )

    # --- motion ---------------------------------------------------------------------------------

    def _next_lane(self, lane_index: int) -> int:
        lane = self.town.lanes[lane_index]
        end, heading = np.array(lane.end), np.subtract(lane.end, lane.start)
        heading = heading / np.linalg.norm(heading)
        options = []
        for i in self.lanes:
            other = self.town.lanes[i]
            d = np.subtract(other.start, end)
            h = np.subtract(other.end, other.start) / _lane_length(other)
            # a lane starting across this intersection, not back where we came from
            if np.hypot(*d) < 25 and heading @ h > -0.5 and d @ heading > -1.0:
                options.append(i)
        straight = [i for i in options if heading @ np.subtract(self.town.lanes[i].end, self.town.lanes[i].start) > 0]
        if not options:
            return -1
        if straight and self.rng.random() < 0.5:
            return int(self.rng.choice(straight))
        return int(self.rng.choice(options))

    def _extend_path(self, v: Vehicle) -> None:
        """Appends the turn through the next intersection and the next lane."""
        nxt = self._next_lane(v.lane)
        if nxt < 0:  # a dead end (only at the rim of small towns): the vehicle parks where it is
            v.parked, v.speed, v.path = True, 0.0, []
            return
        a, b = self.town.lanes[v.lane], self.town.lanes[nxt]
        p0, p2 = np.array(a.end), np.array(b.start)
        d0 = np.subtract(a.end, a.start) / _lane_length(a)
        d1 = np.subtract(b.end, b.start) / _lane_length(b)
        # control point where the two lane lines meet (straight on: the midpoint)
        m = np.array([d0, -d1]).T
        if abs(np.linalg.det(m)) > 1e-6:
            t = np.linalg.solve(m, p2 - p0)[0]
            p1 = p0 + t * d0
        else:
            p1 = (p0 + p2) / 2
        for t in np.linspace(0.2, 1.0, 5):
            v.path.append((1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t * t * p2)
        v.path.append(np.array(b.end))
        v.lane = nxt

    def _gap_ahead(self, v: Vehicle) -> float:
        """Bumper-to-bumper distance to the nearest vehicle in v's way, m (inf if none)."""
        c, s = np.cos(v.yaw), np.sin(v.yaw)
        best = np.inf
        for o in self.vehicles:
            if o is v:
                continue
            dx, dy = o.x - v.x, o.y - v.y
            ahead, lateral = c * dx + s * dy, -s * dx + c * dy
            if 0 < ahead < 30 and abs(lateral) < (v.size[1] + o.size[1]) / 2 + 0.3:
                best = min(best, ahead - (v.size[0] + o.size[0]) / 2)
        for p in self.pedestrians:
            dx, dy = p.position() - (v.x, v.y)
            ahead, lateral = c * dx + s * dy, -s * dx + c * dy
            if 0 < ahead < 15 and abs(lateral) < v.size[1] / 2 + 0.5:
                best = min(best, ahead - v.size[0] / 2)
        return best

    def _intersection_gap(self, v: Vehicle) -> float:
        """Distance to the intersection ahead if a crossing vehicle occupies it, else inf.

        A vehicle already inside an intersection always drives on, so waiting never deadlocks.
        """
        c, s = np.cos(v.yaw), np.sin(v.yaw)
        for ix, iy in self.town.intersections:
            dx, dy = ix - v.x, iy - v.y
            ahead, lateral = c * dx + s * dy, -s * dx + c * dy
            if not (0 < ahead < 25 and abs(lateral) < 10):
                continue
            entry = ahead - 9.0 - v.size[0] / 2  # ~ the stop line
            if entry < 0:
                return np.inf
            for o in self.vehicles:
                crossing = abs(np.cos(o.yaw - v.yaw)) < 0.7
                if o is not v and not o.parked and crossing and abs(o.x - ix) < 9 and abs(o.y - iy) < 9:
                    return entry
        return np.inf

    def step(self) -> None:
        """Advances the world by DT."""
        for v in self.vehicles:
            if v.parked:
                continue
            gap = min(self._gap_ahead(v), self._intersection_gap(v))
            target = min(v.desired, max(0.0, (gap - 3.0) / 1.2))
            accel = np.clip((target - v.speed) / DT, -6.0, 2.5)
            v.speed = max(0.0, v.speed + accel * DT)
            travel = v.speed * DT
            while travel > 0 and v.path:
                goal = v.path[0]
                d = goal - (v.x, v.y)
                dist = float(np.hypot(*d))
                if dist > 1e-6:
                    v.yaw = float(np.arctan2(d[1], d[0]))
                if dist <= travel:
                    v.x, v.y = float(goal[0]), float(goal[1])
                    travel -= dist
                    v.path.pop(0)
                    if len(v.path) < 2:
                        self._extend_path(v)
                else:
                    v.x += travel * d[0] / dist
                    v.y += travel * d[1] / dist
                    travel = 0
        for p in self.pedestrians:
            length = float(np.linalg.norm(p.end - p.start)) or 1.0
            p.t += p.direction * p.speed * DT / length
            if not 0 <= p.t <= 1:
                p.direction *= -1
                p.t = float(np.clip(p.t, 0, 1))

    # --- the world at this instant ----------------------------------------------------------------

    def objects(self) -> list[SceneObject]:
        """The dynamic scene objects (vehicles, pedestrians) at the current time, world frame."""
        out = []
        for v in self.vehicles:
            local = SceneObject(v.id, L["vehicle"], vehicle_primitives(v.kind, v.size), v.colour)
            out.append(local.transformed(v.pose()))
        for p in self.pedestrians:
            x, y = p.position()
            out.append(
                SceneObject(
                    p.id,
                    L["pedestrian"],
                    (Cylinder(x, y, 0.22, 0.15, 1.45), Sphere(np.array([x, y, 1.62]), 0.14)),
                    p.colour,
                )
            )
        return out

    @property
    def cavs(self) -> list[Vehicle]:
        return [v for v in self.vehicles if v.connected]
