"""`voxelize`: run the semantic voxel sensor at any extent and resolution over generated scenarios.

    ros2 run co3sop_nodes voxelize DATA_ROOT --name additional_40m --extent 40 --voxel 0.2 [--z -2.0 2.8]

The paper ships preprocessing tools for custom extents and resolutions; here
every generated scenario records how to re-create its world exactly
(data_protocol.yaml, `co3sop_sim`), so the sensor re-annotates each CAV frame at
the new settings instead of resampling coarser labels. Labels are written like
Co3SOP's: <root>/<name>/<split>/<scenario>/<cav>/<ts>_voxels.npz (uint8
[x][y][z], CARLA axes), one scenario at a time under a temporary name.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np

from co3sop_nodes.cli.common import run
from co3sop_nodes.common import geometry as geo
from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.common.progress import progress
from co3sop_nodes.data import opv2v
from co3sop_nodes.sim import rig
from co3sop_nodes.sim.scenario import config_from_dict, world_states
from co3sop_nodes.sim.voxel_sensor import annotate


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="voxelize", description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("root", type=Path, help="a dataset written by `generate`")
    parser.add_argument("--name", required=True, help="label folder to write, e.g. additional_40m")
    parser.add_argument(
        "--extent", type=float, required=True, help="side of the square grid in x/y, m, centred on the LiDAR"
    )
    parser.add_argument("--voxel", type=float, required=True, help="voxel size, m")
    parser.add_argument(
        "--z", type=float, nargs=2, default=(-2.0, 2.8), metavar=("MIN", "MAX"), help="z range relative to the LiDAR, m"
    )
    parser.add_argument("--workers", type=int, default=2, help="voxel sensor threads")
    opts = parser.parse_args(args)
    if not opts.name.replace("_", "").isalnum():
        raise DatasetError(f"--name {opts.name!r}: use letters, digits and underscores")
    grid = GridSpec.centred(opts.extent, tuple(opts.z), opts.voxel)
    scenarios = opv2v.find_scenarios(opts.root)
    print(
        f"voxelize: grid {'x'.join(map(str, grid.dims))} at {grid.voxel_size} m for {len(scenarios)} scenario(s)",
        flush=True,
    )
    bar = progress(len(scenarios), "scenarios", "scenario")
    for split, scenario in scenarios:
        protocol = opv2v.read_yaml(opts.root / split / scenario / "data_protocol.yaml")
        if "co3sop_sim" not in protocol:
            raise DatasetError(
                f"{opts.root / split / scenario / 'data_protocol.yaml'}: no co3sop_sim record: only generated "
                f"scenarios can be re-annotated"
            )
        cfg = config_from_dict(protocol["co3sop_sim"]["config"])
        final = opts.root / opts.name / split / scenario
        partial = final.with_name(f".{scenario}.partial")
        shutil.rmtree(partial, ignore_errors=True)
        for timestamp, town, traffic, dynamic in world_states(cfg, protocol["co3sop_sim"]["seed"]):
            objects = town.objects + dynamic
            for cav in traffic.cavs:
                labels = annotate(objects, cav.pose() @ rig.vehicle_from_lidar(), grid, opts.workers, ignore=(cav.id,))
                path = partial / str(cav.id) / f"{timestamp:06d}_voxels.npz"
                path.parent.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(path, voxels=geo.ros_to_carla_grid(labels))
        if final.exists():
            shutil.rmtree(final)
        partial.rename(final)
        bar.update(1)
    bar.close()
    print(f"voxelize: labels in {opts.root / opts.name}")
    return 0


entry = run(main)
