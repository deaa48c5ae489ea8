"""Simulated datasets: train/validate/test splits of OPV2V-style scenarios with Co3SOP labels.

Each scenario is a procedural town with 2..7 CAVs (four cameras and a LiDAR each)
and traffic, written in the OPV2V folder layout with Co3SOP voxel labels for
the three benchmark ranges, and optionally as a rosbag2 bag. Scenarios run in
parallel worker processes; where fewer scenarios than workers are left, each
scenario renders and labels on the rest as threads. A scenario is written in
OUT/.partial/<split>/<name>/ (its own small OPV2V root, outside every split
folder, where no OPV2V or Co3SOP loader looks) and moved into place when
complete; SIGINT or SIGTERM stops every worker, and a re-run resumes where it
stopped (completed scenarios are skipped, unfinished ones redone).
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import queue
import shutil
import signal
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import yaml

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.frames import CavFrame
from co3sop_nodes.common.progress import progress
from co3sop_nodes.data import opv2v
from co3sop_nodes.sim.scenario import ScenarioConfig, simulate
from co3sop_nodes.sim.town import TownConfig
from co3sop_nodes.sim.traffic import TrafficConfig
from co3sop_nodes.viz.bev import bev_image


def scenario_name(split: str, index: int, seed: int) -> str:
    """An OPV2V-style name (collection time), unique per (split, index, seed)."""
    offset = {"train": 0, "validate": 1, "test": 2}.get(split, 3)
    start = datetime(2021, 8, 16) + timedelta(days=offset * 40 + seed % 30, minutes=index * 17, seconds=(seed * 7) % 60)
    return start.strftime("%Y_%m_%d_%H_%M_%S")


def scenario_seed(split: str, index: int, seed: int) -> int:
    return int(np.random.SeedSequence([seed, sum(map(ord, split)), index]).generate_state(1)[0])


def data_protocol(cfg: ScenarioConfig, seed: int) -> dict:
    """OpenCDA's scenario record, plus what re-creates the scenario exactly (`co3sop_sim`)."""
    return {
        "world": {
            "sync_mode": True,
            "client_port": 2000,
            "fixed_delta_seconds": 0.05,
            "seed": seed,
            "weather": {"sun_altitude_angle": 55, "cloudiness": 0, "precipitation": 0, "fog_density": 0},
        },
        "vehicle_base": {
            "sensing": {
                "lidar": {
                    "channels": cfg.lidar.channels,
                    "range": cfg.lidar.range,
                    "upper_fov": cfg.lidar.upper_fov,
                    "lower_fov": cfg.lidar.lower_fov,
                },
                "camera": {"fov": 100, "image_size_x": cfg.image_size[0], "image_size_y": cfg.image_size[1]},
            }
        },
        "scenario": {"cavs": cfg.traffic.cavs, "background_vehicles": cfg.traffic.vehicles},
        # without the threads it ran on, which change no byte of the scenario
        "co3sop_sim": {"seed": seed, "config": {k: v for k, v in dataclasses.asdict(cfg).items() if k != "workers"}},
    }


def picture(frame: CavFrame, range_name: str) -> np.ndarray:
    """BEV of the ground truth in the paper's palette beside the four camera images."""
    from PIL import Image

    bev = bev_image(frame.labels[range_name], scale=2)  # (512, 512, 3) for 256 x 256 grids
    side = bev.shape[0] // 2
    tiles = [np.asarray(Image.fromarray(c.rgb).resize((side * 4 // 3, side))) for c in frame.cameras]
    mosaic = np.concatenate([np.concatenate(tiles[:2], axis=1), np.concatenate(tiles[2:], axis=1)], axis=0)
    return np.concatenate([bev, mosaic], axis=1)


STAGING = ".partial"  # OUT/.partial/<split>/<name>/: an unfinished scenario, outside every split folder


def staging(out: Path, split: str, name: str) -> Path:
    """Where a scenario is written until complete: an OPV2V root of its own (<split>/<name>/, label folders)."""
    return out / STAGING / split / name


def _ignore_sigint() -> None:
    """Workers leave Ctrl-C to the main process, which stops them all (a terminal sends it to the whole group)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt  # SIGTERM unwinds like Ctrl-C: the pool's exit terminates every worker


def generate_scenario(job: dict, events) -> str:
    """Worker: one scenario, written in its staging folder and moved into place when complete."""
    out, split, name, seed, cfg = Path(job["out"]), job["split"], job["name"], job["seed"], job["config"]
    stage = staging(out, split, name)
    shutil.rmtree(stage, ignore_errors=True)  # leftovers of an interrupted run
    (stage / split / name).mkdir(parents=True)
    with open(stage / split / name / "data_protocol.yaml", "w") as f:
        yaml.safe_dump(data_protocol(cfg, seed), f)
    for frames in simulate(cfg, seed, name):
        for frame in frames:
            opv2v.write_frame(stage, split, frame)
            if job["pictures"]:
                from PIL import Image

                path = out / "pictures" / split / name / str(frame.cav_id) / f"{frame.timestamp:06d}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                Image.fromarray(picture(frame, job["picture_range"])).save(path)
        try:
            events.put(1)
        except (BrokenPipeError, EOFError):  # the main process is gone (interrupted): stop quietly
            return name
    # labels first, the scenario folder last: its presence marks the scenario complete
    for folder in [*opv2v.LABEL_FOLDERS.values(), ""]:
        src, dst = stage / folder / split / name, out / folder / split / name
        if src.exists():
            shutil.rmtree(dst, ignore_errors=True)  # an earlier, incomplete run of this scenario
            dst.parent.mkdir(parents=True, exist_ok=True)
            src.rename(dst)
    shutil.rmtree(stage)
    for empty in (stage.parent, stage.parent.parent):  # .partial/<split>, .partial: gone once nothing is unfinished
        try:
            empty.rmdir()
        except OSError:  # another scenario is still being written
            break
    if job["bags"]:
        from co3sop_nodes.data.bags import BagWriter

        bag = Path(job["bags"]) / split / name
        bag.parent.mkdir(parents=True, exist_ok=True)
        with BagWriter(bag, compress=job["compress_bags"]) as writer:
            for _, frames in opv2v.read_scenario(out, split, name, cfg.ranges):
                if isinstance(frames, DatasetError):
                    raise frames
                writer.write(frames)
    return name


def parse_splits(items: list[str]) -> dict[str, int]:
    splits = {}
    for item in items:
        name, _, count = item.partition("=")
        if name not in opv2v.SPLITS or not count.isdigit():
            raise DatasetError(f"--splits: expected NAME=COUNT with NAME in {', '.join(opv2v.SPLITS)}, got {item!r}")
        splits[name] = int(count)
    return splits


# the real dataset's sizes (OPV2V's cameras and 64-channel LiDAR at about 130 k points per sweep; labels larger
# than the range's grid, as Co3SOP's may be), for `generate --real-size`
REAL_SIZE = {"image_size": "800x600", "lidar_steps": 2048, "label_margin": "8,4"}
RECIPE_KEYS = ("splits", "frames", "seed", "cavs", "vehicles", "image_size", "lidar_steps")


def parse_shard(text: str) -> tuple[int, int]:
    """ "I/N" -> (I, N), 1 <= I <= N."""
    i, _, n = text.partition("/")
    try:
        shard, shards = int(i), int(n)
    except ValueError:
        raise DatasetError(f"--shard {text!r}: expected I/N, e.g. 2/4") from None
    if not 1 <= shard <= shards:
        raise DatasetError(f"--shard {text!r}: I must be between 1 and N")
    return shard, shards


def read_recipe(path: Path) -> dict:
    """A dataset recipe's `dataset` section (config/benchmark.yaml) as generate's option defaults."""
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path}: not YAML ({exc})") from None
    recipe = data.get("dataset") if isinstance(data, dict) else None
    if not isinstance(recipe, dict):
        raise DatasetError(f"{path}: expected a 'dataset' mapping")
    unknown = sorted(set(recipe) - set(RECIPE_KEYS))
    if unknown:
        raise DatasetError(f"{path}: unknown dataset key(s) {', '.join(unknown)} (known: {', '.join(RECIPE_KEYS)})")
    if isinstance(recipe.get("splits"), dict):
        recipe["splits"] = [f"{k}={v}" for k, v in recipe["splits"].items()]
    return {k: str(v) if k in ("cavs", "image_size") else v for k, v in recipe.items()}


@dataclasses.dataclass
class GenerateOptions:
    """What `generate` makes; its options, as the command line names them."""

    out: Path
    splits: list[str] = dataclasses.field(default_factory=lambda: ["train=4", "validate=1", "test=1"])
    frames: int = 20
    seed: int = 0
    workers: int = 2
    shard: str = "1/1"
    cavs: str = "2-4"
    vehicles: int = 30
    image_size: str = "400x300"
    lidar_steps: int = 1024
    label_margin: str = "0,0"
    extras: bool = False
    bags: Path | None = None
    compress_bags: bool = False
    pictures: bool = False
    picture_range: str = "51.2m"


def generate(opts: GenerateOptions) -> int:
    """Simulates and writes every scenario of `opts` not already complete (resumable); 0 when done."""
    opts.out = Path(opts.out)
    splits = parse_splits(opts.splits)
    lo, _, hi = opts.cavs.partition("-")
    try:
        cav_range = (int(lo), int(hi or lo))
        width, height = (int(v) for v in opts.image_size.lower().split("x"))
    except ValueError:
        raise DatasetError(
            f"--cavs {opts.cavs!r} / --image-size {opts.image_size!r}: expected N or MIN-MAX / WIDTHxHEIGHT"
        ) from None
    if not 1 <= cav_range[0] <= cav_range[1] <= 7:
        raise DatasetError(f"--cavs {opts.cavs!r}: between 1 and 7 CAVs")
    try:
        side, top = (int(v) for v in opts.label_margin.split(","))
    except ValueError:
        raise DatasetError(f"--label-margin {opts.label_margin!r}: expected SIDE,TOP voxels, e.g. 8,4") from None
    for option, value, least in (
        ("--label-margin", min(side, top), 0),
        ("--frames", opts.frames, 1),
        ("--vehicles", opts.vehicles, 0),
        ("--lidar-steps", opts.lidar_steps, 1),
        ("--image-size width", width, 1),
        ("--image-size height", height, 1),
        ("--workers", opts.workers, 1),
    ):
        if value < least:  # e.g. 0 frames would write empty scenarios that every reader then rejects
            raise DatasetError(f"{option} {value}: must be at least {least}")
    shard, shards = parse_shard(opts.shard)
    jobs, skipped = [], 0
    every = [(split, index) for split, count in splits.items() for index in range(count)]
    for split, index in every[shard - 1 :: shards]:  # a scenario's seed and name do not depend on the shard
        seed = scenario_seed(split, index, opts.seed)
        name = scenario_name(split, index, opts.seed)
        if (opts.out / split / name).is_dir() and (
            not opts.bags or (opts.bags / split / name / "metadata.yaml").exists()
        ):
            skipped += 1
            continue
        cavs = int(np.random.default_rng(seed).integers(cav_range[0], cav_range[1] + 1))
        cfg = ScenarioConfig(
            town=TownConfig(),
            traffic=TrafficConfig(cavs=cavs, vehicles=opts.vehicles),
            frames=opts.frames,
            image_size=(width, height),
            lidar=dataclasses.replace(ScenarioConfig().lidar, azimuth_steps=opts.lidar_steps),
            extra_images=opts.extras,
            label_margin=(side, top),
        )
        if (opts.out / split / name).is_dir():  # folder complete, only the bag is missing: redo both
            shutil.rmtree(opts.out / split / name)
        jobs.append(
            dict(
                out=str(opts.out),
                split=split,
                name=name,
                seed=seed,
                config=cfg,
                bags=opts.bags and str(opts.bags),
                compress_bags=opts.compress_bags,
                pictures=opts.pictures,
                picture_range=opts.picture_range,
            )
        )
    print(f"generate: {len(jobs)} scenario(s) to simulate, {skipped} already complete", flush=True)
    if not jobs:
        return 0
    # workers beyond the scenarios become each scenario's camera and voxel-sensor threads (the same data)
    for job in jobs:
        job["config"] = dataclasses.replace(job["config"], workers=max(1, opts.workers // len(jobs)))
    opts.out.mkdir(parents=True, exist_ok=True)
    ctx = mp.get_context("spawn")
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        with (
            ctx.Manager() as manager,
            ctx.Pool(max(1, min(opts.workers, len(jobs))), initializer=_ignore_sigint) as pool,
        ):
            events = manager.Queue()
            pending = [pool.apply_async(generate_scenario, (job, events)) for job in jobs]
            bar = progress(sum(j["config"].frames for j in jobs), "frames", "frame")
            while pending:
                try:
                    bar.update(events.get(timeout=0.5))
                except queue.Empty:
                    pass
                for result in [r for r in pending if r.ready()]:
                    pending.remove(result)
                    bar.write(f"generate: scenario {result.get()} complete")  # get() re-raises a worker's error
            while not events.empty():
                bar.update(events.get())
            bar.close()
    finally:
        signal.signal(signal.SIGTERM, previous)
    print(f"generate: {len(jobs)} scenario(s) written to {opts.out}" + (f", bags in {opts.bags}" if opts.bags else ""))
    return 0
