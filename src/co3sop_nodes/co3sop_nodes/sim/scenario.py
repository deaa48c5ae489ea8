"""A scenario: a town, its traffic, and every CAV's sensor data and voxel labels per 10 Hz frame."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from co3sop_nodes.common.frames import CameraFrame, CavFrame, OtherVehicle
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.sim import camera, lidar, rig
from co3sop_nodes.sim.raycast import ObjectMeshes, RayScene
from co3sop_nodes.sim.scene import SceneObject
from co3sop_nodes.sim.town import Town, TownConfig, generate_town
from co3sop_nodes.sim.traffic import Traffic, TrafficConfig
from co3sop_nodes.sim.voxel_sensor import annotate

FIRST_TIMESTAMP = 70  # OPV2V keys are CARLA frame numbers: dumping starts after ~60 ticks, every 2nd tick


@dataclass(frozen=True)
class ScenarioConfig:
    town: TownConfig = field(default_factory=TownConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    frames: int = 20  # 10 Hz frames written
    warmup: int = 20  # steps simulated before the first frame, so traffic is under way
    image_size: tuple[int, int] = (400, 300)  # width, height; OPV2V's are 800 x 600 (intrinsics scale with it)
    lidar: lidar.LidarConfig = field(default_factory=lidar.LidarConfig)
    ranges: tuple[str, ...] = tuple(BENCHMARK_RANGES)  # benchmark grids to annotate per CAV
    # label grids larger than the range's, as Co3SOP's sensor may write them: (voxels added on each side in x and
    # y, layers added on top); readers crop them back as Co3SOP's LoadOccupancy does (data/opv2v.read_labels)
    label_margin: tuple[int, int] = (0, 0)
    extra_images: bool = False  # also keep depth and semantic camera images
    gnss_noise: float = 0.2  # m, std of the predicted_ego_pos error
    workers: int = 2  # threads of the voxel sensor and of the cameras


def config_from_dict(data: dict) -> ScenarioConfig:
    """Inverse of dataclasses.asdict(ScenarioConfig) (as recorded in data_protocol.yaml)."""
    return ScenarioConfig(
        town=TownConfig(**data["town"]),
        traffic=TrafficConfig(**data["traffic"]),
        lidar=lidar.LidarConfig(**data["lidar"]),
        **{k: tuple(v) if isinstance(v, list) else v for k, v in data.items() if k not in ("town", "traffic", "lidar")},
    )


def _others(traffic: Traffic, me, radius: float = 150.0) -> list[OtherVehicle]:
    out = []
    for v in traffic.vehicles:
        if v is me or np.hypot(v.x - me.x, v.y - me.y) > radius:
            continue
        out.append(OtherVehicle(v.id, v.pose(), np.array([0.0, 0.0, v.size[2] / 2]), np.array(v.size) / 2, v.speed))
    return out


def world_states(cfg: ScenarioConfig, seed: int) -> Iterator[tuple[int, Town, Traffic, list[SceneObject]]]:
    """Per frame: (OPV2V timestamp, town, traffic, dynamic objects). Deterministic in (cfg, seed)."""
    town = generate_town(cfg.town, seed)
    traffic = Traffic(town, cfg.traffic, seed + 1)
    for _ in range(cfg.warmup):
        traffic.step()
    for index in range(cfg.frames):
        yield FIRST_TIMESTAMP + 2 * index, town, traffic, traffic.objects()
        traffic.step()


def labelled_grid(grid: GridSpec, margin: tuple[int, int]) -> GridSpec:
    """`grid` with `margin[0]` voxels more on each side in x and y and `margin[1]` layers more on top: the centre
    crop in x and y and the bottom layers in z give `grid` back."""
    side, top = margin
    x, y, z = grid.origin
    nx, ny, nz = grid.dims
    return GridSpec(
        (x - side * grid.voxel_size, y - side * grid.voxel_size, z),
        grid.voxel_size,
        (nx + 2 * side, ny + 2 * side, nz + top),
    )


def simulate(cfg: ScenarioConfig, seed: int, name: str) -> Iterator[list[CavFrame]]:
    """Yields, per frame, one CavFrame for every CAV (REP-103 frames)."""
    rng = np.random.default_rng(seed)
    width, height = cfg.image_size
    k = rig.intrinsics(width, height)
    grids: dict[str, GridSpec] = {r: labelled_grid(BENCHMARK_RANGES[r], cfg.label_margin) for r in cfg.ranges}
    static = None
    for timestamp, town, traffic, dynamic in world_states(cfg, seed):
        if static is None:  # the static world is meshed once
            static = ObjectMeshes(town.objects)
        objects = town.objects + dynamic
        scene = RayScene([static, ObjectMeshes(dynamic)])
        frames = []
        for cav in traffic.cavs:
            vehicle = cav.pose()
            world_lidar = vehicle @ rig.vehicle_from_lidar()
            poses = [vehicle @ mount for mount in rig.vehicle_from_cameras()]
            cams = [
                CameraFrame(name_i, pose, k, img.rgb, *((img.depth, img.semantic) if cfg.extra_images else ()))
                for name_i, pose, img in zip(
                    rig.CAMERA_NAMES, poses, camera.render_rig(scene, poses, width, height, k, cfg.workers)
                )
            ]
            scan = lidar.scan(scene, world_lidar, cfg.lidar, rng)
            predicted = vehicle.copy()
            predicted[:2, 3] += rng.normal(0, cfg.gnss_noise, 2)
            plan = np.array([[p[0], p[1], cav.desired] for p in cav.path[:10]]) if cav.path else np.zeros((0, 3))
            frames.append(
                CavFrame(
                    scenario=name,
                    cav_id=cav.id,
                    timestamp=timestamp,
                    world_from_vehicle=vehicle,
                    world_from_lidar=world_lidar,
                    speed=cav.speed,
                    cameras=cams,
                    points=scan.points,
                    intensity=scan.intensity,
                    point_labels=scan.label,
                    labels={
                        r: annotate(objects, world_lidar, g, cfg.workers, ignore=(cav.id,)) for r, g in grids.items()
                    },
                    vehicles=_others(traffic, cav),
                    plan=plan,
                    world_from_predicted=predicted,
                )
            )
        yield frames
