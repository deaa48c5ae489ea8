"""Simulator benchmark: the voxel sensor vs its oracle, ray rates, generation speed, bag size.

    ros2_ws/benchmarks/bench_simulator.py [--full] [--frames 3] [--tables sensor rays generation] [--out FILE.md]

Run with the workspace environment (`. ros2_ws/env.sh`). Prints markdown tables:

1. The three-stage voxel sensor (compiled kernel, and its NumPy stages) vs the
   brute-force oracle (every voxel against every object) on the same scene,
   around one CAV of a default town: seconds, voxels per second, kernel vs NumPy
   ratio and whether the three grids are identical, for each benchmark grid and,
   with --full, the paper's full 1000 x 1000 x 70 annotation at 0.1 m.
2. Rays per second of the cameras (shaded, with shadow rays) and the LiDAR, on
   the reference path (trimesh + NumPy) and the compiled ray kernel (one and two
   threads), with the images compared, in the same run.
3. End-to-end scenario generation (simulate + OPV2V files + labels at the three
   ranges), frames and CAV-frames per second, and bag megabytes per CAV-frame,
   with every compiled kernel off (the NumPy / trimesh reference paths) and on,
   in the same run.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from co3sop_nodes import kernels
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.data import opv2v
from co3sop_nodes.data.bags import BagWriter
from co3sop_nodes.sim import camera, lidar, rig
from co3sop_nodes.sim.raycast import ObjectMeshes, RayScene
from co3sop_nodes.sim.scenario import ScenarioConfig, simulate
from co3sop_nodes.sim.town import TownConfig, generate_town
from co3sop_nodes.sim.traffic import Traffic, TrafficConfig
from co3sop_nodes.sim.voxel_sensor import annotate, annotate_brute_force

FULL = GridSpec((-50.0, -50.0, -2.0), 0.1, (1000, 1000, 70))


def sensor_table(full: bool, workers: int) -> str:
    town = generate_town(TownConfig(), seed=7)
    traffic = Traffic(town, TrafficConfig(cavs=3), seed=8)
    for _ in range(20):
        traffic.step()
    objects = town.objects + traffic.objects()
    pose = traffic.cavs[0].pose() @ rig.vehicle_from_lidar()
    grids = dict(BENCHMARK_RANGES)
    if full:
        grids["full 100 m"] = FULL
    rows = [
        f"Scene: default town (seed 7), {len(objects)} objects, around a CAV; sensor with {workers} thread(s). Kernel: the "
        "compiled stages (sim/voxel_kernel.py); NumPy: the same stages in NumPy (the sensor before the kernel); oracle: "
        "every voxel against every object.",
        "",
        "| grid | voxels | occupied | kernel s | M voxels/s | NumPy s | NumPy / kernel | oracle s | identical |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    annotate(objects, pose, BENCHMARK_RANGES["51.2m"], workers)  # compiles the kernel: not timed
    for name, grid in grids.items():
        t0 = time.perf_counter()
        fast = annotate(objects, pose, grid, workers, compiled=True)
        t1 = time.perf_counter()
        staged = annotate(objects, pose, grid, workers, compiled=False)
        t2 = time.perf_counter()
        slow = annotate_brute_force(objects, pose, grid)
        t3 = time.perf_counter()
        same = np.array_equal(fast, slow) and np.array_equal(staged, slow)
        rows.append(
            f"| {name} ({'x'.join(map(str, grid.dims))} @ {grid.voxel_size} m) | {grid.num_voxels:,} | {int((fast > 0).sum()):,} | "
            f"{t1 - t0:.3f} | {grid.num_voxels / (t1 - t0) / 1e6:.1f} | {t2 - t1:.2f} | {(t2 - t1) / (t1 - t0):.1f}x | {t3 - t2:.2f} | "
            f"{'yes' if same else 'NO'} |"
        )
        print(f"  sensor {name}: kernel {t1 - t0:.3f} s, NumPy {t2 - t1:.2f} s, oracle {t3 - t2:.2f} s", flush=True)
    return "\n".join(rows)


def ray_table() -> str:
    """Cameras on the reference path (trimesh's intersector, NumPy shading) and the compiled kernel, one and two
    threads, in the same run, with the images compared; then the LiDAR."""
    town = generate_town(TownConfig(), seed=7)
    traffic = Traffic(town, TrafficConfig(cavs=3), seed=8)
    scene = RayScene([ObjectMeshes(town.objects), ObjectMeshes(traffic.objects())])
    vehicle = traffic.cavs[0].pose()
    poses = [vehicle @ mount for mount in rig.vehicle_from_cameras()]
    rows = [
        f"Scene: {len(scene.mesh.faces):,} triangles. Camera rays: one primary ray per pixel (and a shadow ray per "
        "pixel that hits something), counted once; best of 3.",
        "",
        "| sensor | path | threads | rays per frame | seconds | rays/s | reference / path | images identical |",
        "|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for width, height in ((400, 300), (800, 600)):
        k = rig.intrinsics(width, height)
        rays = 4 * width * height
        camera.render_rig(scene, poses, width, height, k, 2, compiled=True)  # BVH, kernel and rays: not timed
        reference, seconds = None, {}
        for compiled, threads in ((False, 1), (True, 1), (True, 2)):
            times = []
            for _ in range(3):
                t0 = time.perf_counter()
                images = camera.render_rig(scene, poses, width, height, k, threads, compiled=compiled)
                times.append(time.perf_counter() - t0)
            dt = seconds[compiled, threads] = min(times)
            reference = reference or images
            same = all(
                np.array_equal(a.rgb, b.rgb)
                and np.array_equal(a.depth, b.depth)
                and np.array_equal(a.semantic, b.semantic)
                for a, b in zip(reference, images)
            )
            rows.append(
                f"| 4 cameras {width}x{height} (+ shadow rays) | {'kernel' if compiled else 'reference'} | {threads} | "
                f"{rays:,} | {dt:.3f} | {rays / dt:,.0f} | {seconds[False, 1] / dt:.1f}x | {'yes' if same else 'NO'} |"
            )
            print(
                f"  cameras {width}x{height} {'kernel' if compiled else 'reference'} x{threads}: {dt:.3f} s", flush=True
            )
    cfg = lidar.LidarConfig()
    rays = cfg.channels * cfg.azimuth_steps
    for compiled in (False, True):
        t0 = time.perf_counter()
        scene.cast(
            np.broadcast_to(vehicle[:3, 3], (rays, 3)),
            lidar.beam_directions(cfg) @ vehicle[:3, :3].T,
            cfg.range,
            compiled=compiled,
        )
        dt = time.perf_counter() - t0
        rows.append(
            f"| LiDAR {cfg.channels} x {cfg.azimuth_steps} | {'kernel' if compiled else 'reference'} | 1 | {rays:,} | "
            f"{dt:.3f} | {rays / dt:,.0f} | | |"
        )
    return "\n".join(rows)


def generate_once(frames: int) -> tuple[float, int, float, float]:
    """(seconds, CAV-frames, bag MB, bag write seconds) of one generated scenario."""
    cfg = ScenarioConfig(traffic=TrafficConfig(cavs=3), frames=frames, workers=2)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        cav_frames = 0
        for per_ts in simulate(cfg, seed=11, name="2021_08_16_12_00_00"):
            for frame in per_ts:
                opv2v.write_frame(root, "train", frame)
                cav_frames += 1
        dt = time.perf_counter() - t0
        t1 = time.perf_counter()
        with BagWriter(root / "bag") as writer:
            for _, per_ts in opv2v.read_scenario(root, "train", "2021_08_16_12_00_00"):
                writer.write(per_ts)
        bag_s = time.perf_counter() - t1
        bag_mb = sum(p.stat().st_size for p in (root / "bag").iterdir()) / 1e6
    return dt, cav_frames, bag_mb, bag_s


def generation_table(frames: int) -> str:
    """Generation with every compiled kernel off (NumPy voxel sensor), then on, in the same run."""
    rows = [
        f"One scenario, 3 CAVs, {frames} frames, cameras 400x300, LiDAR 64 x 1024, labels at the three ranges.",
        "",
        "| kernels | frames/s | CAV-frames/s | s per CAV-frame | bag MB per CAV-frame | bag write s per CAV-frame |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    per_cav_frame = {}
    for enabled in (False, True):
        kernels.ENABLED = enabled
        dt, cav_frames, bag_mb, bag_s = generate_once(frames)
        per_cav_frame[enabled] = dt / cav_frames
        rows.append(
            f"| {'on' if enabled else 'off'} | {frames / dt:.2f} | {cav_frames / dt:.2f} | {dt / cav_frames:.2f} | "
            f"{bag_mb / cav_frames:.2f} | {bag_s / cav_frames:.2f} |"
        )
    rows += ["", f"Kernels off / on, s per CAV-frame: {per_cav_frame[False] / per_cav_frame[True]:.2f}x."]
    return "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--full", action="store_true", help="also the full 1000 x 1000 x 70 grid (minutes for the oracle)"
    )
    parser.add_argument("--frames", type=int, default=3, help="frames for the generation figure")
    parser.add_argument("--workers", type=int, default=2, help="voxel sensor threads")
    parser.add_argument(
        "--tables",
        nargs="+",
        choices=("sensor", "rays", "generation"),
        default=["sensor", "rays", "generation"],
        help="which tables (default: all)",
    )
    parser.add_argument("--out", type=Path, help="also write the tables to this markdown file")
    opts = parser.parse_args()
    tables = {
        "sensor": ("### Voxel sensor vs oracle", lambda: sensor_table(opts.full, opts.workers)),
        "rays": ("### Ray casting", ray_table),
        "generation": ("### Scenario generation", lambda: generation_table(opts.frames)),
    }
    text = "\n\n".join(part for name in opts.tables for part in (tables[name][0], tables[name][1]()))
    print(text)
    if opts.out:
        opts.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
