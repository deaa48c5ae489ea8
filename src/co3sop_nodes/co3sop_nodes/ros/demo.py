"""`demo`: the whole graph on a small scenario, scored: player + vehicles + ego + recorder, then `score`.

    ros2 run co3sop_nodes demo [--bag BAG] [--model tiny-lidar|tiny|small|CKPT] [--out results/demo] [--rate R]

Without --bag it generates one scenario with three CAVs (once; kept in
data/demo and bags/demo). It starts a recorder, the ego, one vehicle per CAV
(at most --vehicles) as separate processes, drives the ego and vehicles
through their lifecycle as a lifecycle manager does (configure, then
activate), waits until the ego subscribes to every vehicle and the recorder
to the ego's outputs (graph events), plays the bag once at --rate
(default: the rate this machine keeps up with, from the model's CPU time per
frame measured before the nodes start, model.pace), waits until the ego has
reported every frame fused on /diagnostics, stops everything with SIGINT,
scores the MCAP (table printed, pictures beside it, and a Foxglove layout
for the recording: prediction | ground truth in 3D, the ego's cameras) and checks the recording
holds every /ego/occupancy message the ego published. Nothing is decided from
the nodes' logs.

With --channel-rate the graph runs over an emulated V2X channel (v2x/channel.py,
root and nftables needed): the ego (with its own encoder and the recorder) and
each neighbour in its own network namespace, their transmit limited to
--channel-rate Mbit/s of real time (times --rate, so that the link keeps its
real-time meaning at a slower playback) with --channel-loss percent of their
packets dropped at random; the player and this launcher stay on the machine's
side, unshaped. A neighbour's DDS runs over UDP only (config/fastdds_udp.xml);
the ego's processes and the player share memory among themselves, as one car's
computers and sensors would (config/fastdds_onboard.xml), and reach the
neighbours over UDP.
Namespaces are removed on exit, SIGINT and SIGTERM included.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import signal
import subprocess
import threading
import time
from pathlib import Path

from ament_index_python.packages import get_package_prefix

from co3sop_nodes.common import topics
from co3sop_nodes.data.bags import open_reader
from co3sop_nodes.v2x.channel import Channel, Link
from co3sop_nodes.cli import generate, score
from co3sop_nodes.cli.common import run
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.viz.foxglove import CAMERAS, write_layout
from co3sop_nodes.inference import PRECISIONS, inference_path
from co3sop_nodes.inference import pace
from co3sop_nodes.inference.checkpoint import load_graph_model, resolve_checkpoint
from co3sop_nodes.eval.scoring import message_counts
from co3sop_nodes.ros.dds import channel_environment
from co3sop_nodes.ros.recorder import DEFAULT_TOPICS
from co3sop_nodes.ros.supervisor import Supervisor

# A scene whose CAVs can help each other: seed 11 is the first base seed (counting from 1) whose three CAVs all
# stay within 30 m of the ego over the 10 frames (most seeds spread them 50-100 m apart, where a 51.2 m grid
# shares little or nothing; the seed-7 scene used before had its neighbours 57 and 73 m away). Chosen by that
# rule alone, before scoring; no training or validation split uses seed 11.
DEMO_SEED = 11
DEMO_FRAMES = 10
DEMO_SCENARIO = ["--splits", "test=1", "--cavs", "3", "--seed", str(DEMO_SEED), "--image-size", "320x240",
                 "--lidar-steps", "512", "--workers", "1"]


LOSSLESS = ["codec.dtype:=float32", "codec.selection:=dense", "codec.compression:=none"]
DEFAULT_MODEL = "tiny-lidar"  # the best collaborative model shipped (checkpoints/tiny-lidar.md); "tiny": the camera model


def say(text: str) -> None:
    print(f"[demo] {text}", flush=True)


def executable(name: str) -> str:
    """A co3sop_nodes executable, found as `ros2 run` finds it."""
    return str(Path(get_package_prefix("co3sop_nodes"), "lib", "co3sop_nodes", name))


class Process:
    """A child process whose output is echoed with a prefix (or swallowed)."""

    def __init__(self, label: str, argv: list[str], echo: bool = True, env: dict[str, str] | None = None):
        self.label = label
        self._echo = echo
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, **(env or {})},
                                     start_new_session=True)  # Ctrl-C on the demo reaches the demo only; it stops the children
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            if self._echo:
                print(f"  [{self.label}] {line.rstrip()}", flush=True)

    def stop(self, timeout: float = 30) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(5)
        return self.proc.returncode


def bag_contents(bag: Path) -> tuple[list[int], int]:
    """(CAV ids, frames) of a bag."""
    reader = open_reader(bag)
    with reader:
        poses = {cav[0]: c.msgcount for c in reader.connections if (cav := topics.split_cav_topic(c.topic)) is not None
                 and c.topic == topics.lidar_pose(cav[0])}
    if not poses:
        raise Co3sopError(f"{bag}: no /cav_N/lidar/pose topic: not a CAV bag")
    return sorted(poses), max(poses.values())


def bag_period(bag: Path, frames: int) -> float:
    """Seconds between a bag's frames (0.1 for a 10 Hz bag)."""
    reader = open_reader(bag)
    with reader:
        return (reader.end_time - reader.start_time) / 1e9 / max(1, frames - 1) if frames > 1 else 0.1


def measured_rate(model, vehicles: int, period: float) -> float:
    """The playback rate this machine keeps up with for `vehicles` vehicles and the ego (model.pace), to 2 digits."""
    cost = pace.frame_cost(model)
    n = pace.cores()
    rate = math.floor(100 * pace.sustainable_rate(cost, vehicles, period, n)) / 100
    say(f"measured per frame on one thread: vehicle {1e3 * cost.vehicle_s:.0f} ms, ego {1e3 * cost.ego_s:.0f} ms; "
        f"{vehicles} vehicles + ego on {n} cores keep up with rate {rate:g} (a frame every {period / max(rate, 0.01):.2f} s)")
    return max(rate, 0.01)


def played_topics(cavs: list[int], sensors: str) -> list[str]:
    """What the graph listens to (so the player waits for exactly those subscribers): sensors, mounts, ground truth,
    and the ego's camera images (recorded for the Foxglove layout, whatever the model's sensors)."""
    played = [topics.TF_STATIC]
    for c in cavs:
        played.append(topics.lidar_pose(c))
        if sensors == "lidar":
            played.append(topics.lidar_points(c))
        else:
            played += [f(c, cam) for cam in CAMERAS for f in (topics.camera_image, topics.camera_info)]
        played += [topics.ground_truth(c, r) for r in topics.RANGE_SUFFIX]
    return played + [t for cam in CAMERAS if (t := topics.camera_image(cavs[0], cam)) not in played]


def ensure_scenario(opts) -> Path:
    if opts.bag:
        return opts.bag
    data, bags = (
        (opts.data, opts.bags)
        if opts.frames == DEMO_FRAMES
        else (opts.data / f"{opts.frames}f", opts.bags / f"{opts.frames}f")
    )
    bag = bags / "test" / generate.scenario_name("test", 0, DEMO_SEED)
    if not (bag / "metadata.yaml").exists():
        say(f"no demo scenario of {opts.frames} frames yet: generating one (3 CAVs) into {data} and {bags} "
            f"(about {max(1, round(opts.frames / 10))} minute(s))")
        generate.main(["--out", str(data), "--bags", str(bags), *DEMO_SCENARIO, "--frames", str(opts.frames)])
    return bag


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bag", type=Path, help="a CAV bag to play (default: the generated demo scenario)")
    parser.add_argument("--data", type=Path, default=Path("data/demo"), help="where the demo scenario is generated")
    parser.add_argument("--bags", type=Path, default=Path("bags/demo"), help="where the demo scenario's bag is written")
    parser.add_argument("--out", type=Path, default=Path("results/demo"), help="recording, score and pictures")
    parser.add_argument(
        "--frames",
        type=int,
        default=DEMO_FRAMES,
        help="10 Hz frames of the generated demo scenario (the same "
        "town and traffic, longer; generated once per length)",
    )
    parser.add_argument("--rate", type=float, help="playback rate, 1 = real time (default: what this machine keeps up with, measured)")
    parser.add_argument("--vehicles", type=int, default=3, help="vehicle processes (the first CAVs of the bag; the first is the ego)")
    parser.add_argument("--model", default=DEFAULT_MODEL,
                        help=f"checkpoint of every node: a shipped one by name (tiny-lidar: collaborative LiDAR; tiny: camera; small: the larger, GPU-trained camera model) or a path "
                             f"(default: {DEFAULT_MODEL})")
    parser.add_argument("--params", nargs="*", default=[],
                        help="parameters of the other vehicles, e.g. codec.dtype:=int8 (the V2X codec; the ego's own encoder is lossless)")
    parser.add_argument("--ego-params", nargs="*", default=[], help="parameters of the ego node, e.g. threads:=2")
    parser.add_argument(
        "--precision",
        default="auto",
        choices=PRECISIONS,
        help="inference precision of every node (auto: what the "
        "machine computes fast; float32 on CPUs without AMX or AVX-512 BF16)",
    )
    parser.add_argument("--device", default="cpu", help="where every node's model runs: cpu, cuda, cuda:N, auto")
    parser.add_argument("--quiet", action="store_true", help="do not echo the nodes' output")
    parser.add_argument("--channel-rate", type=float, metavar="MBIT",
                        help="run over an emulated V2X channel: each CAV in its own network namespace, transmitting at most MBIT "
                             "Mbit/s of real time (the link runs at MBIT x --rate); needs root, iproute2 and nftables")
    parser.add_argument("--channel-loss", type=float, default=0.0, metavar="PERCENT",
                        help="with --channel-rate: share of each CAV's packets dropped at random (default 0)")
    opts = parser.parse_args(args)
    if opts.channel_rate is None and opts.channel_loss:
        parser.error("--channel-loss needs --channel-rate")
    if opts.rate is not None and not opts.rate > 0:
        parser.error(f"--rate {opts.rate}: must be above 0")
    if opts.frames < 1:
        parser.error(f"--frames {opts.frames}: at least 1")
    if opts.vehicles < 1:
        parser.error(f"--vehicles {opts.vehicles}: at least 1 (the ego's)")
    signal.signal(signal.SIGTERM, _interrupt)  # SIGTERM unwinds like Ctrl-C: the children are stopped, namespaces removed
    t0 = time.monotonic()
    checkpoint = resolve_checkpoint(opts.model, "--model")
    path = inference_path(opts.device, opts.precision, what="--")  # refused here if the machine lacks the device
    model, _ = load_graph_model(checkpoint)  # refused here, before any node starts, if the graph cannot run it
    sensors = model.cfg.modality
    bag = ensure_scenario(opts)
    cavs, frames = bag_contents(bag)
    cavs = cavs[: opts.vehicles]
    ego = cavs[0]
    opts.out.mkdir(parents=True, exist_ok=True)
    mcap = opts.out / "demo.mcap"
    say(f"bag {bag}: {frames} frames; vehicles {cavs}, ego cav {ego}; recording to {mcap}")
    say(f"model {checkpoint} ({sensors}); inference on {path.describe()}")
    model.use(path)
    if opts.rate is None:
        opts.rate = measured_rate(model, len(cavs), bag_period(bag, frames))
    channel = None
    if opts.channel_rate is not None:
        link = Link(opts.channel_rate * opts.rate, opts.channel_loss / 100)
        channel = Channel({member: link for member in ["ego", *(f"cav{c}" for c in cavs[1:])]})
        os.environ.update(channel_environment(None))  # before any DDS participant, the supervisor's included
        say(f"emulated V2X channel: each CAV transmits at {link.rate_mbit:g} Mbit/s ({opts.channel_rate:g} Mbit/s of real time "
            f"at rate {opts.rate:g}), {opts.channel_loss:g} % of its packets lost")
    with channel or contextlib.nullcontext():
        return _graph(opts, checkpoint, sensors, bag, cavs, frames, mcap, channel, t0)


def frames_accounted(supervisor: Supervisor, ego: int) -> int:
    """The ego's own frames fused, or skipped to stay current by the ego or by its own encoder (from their latest
    /diagnostics: the newest frame is never skipped, so the last report counts every skip before it)."""
    fused = supervisor.reports("ego")
    encoder = supervisor.reports(f"vehicle cav_{ego}")
    return (
        len(fused)
        + (int(fused[-1].get("skipped", 0)) if fused else 0)
        + (int(encoder[-1].get("skipped", 0)) if encoder else 0)
    )


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _graph(opts, checkpoint: Path, sensors: str, bag: Path, cavs: list[int], frames: int, mcap: Path, channel: Channel | None,
           t0: float) -> int:
    """The nodes started (inside the channel's namespaces where there is one), the bag played, the recording scored."""
    ego = cavs[0]

    echo = not opts.quiet

    def on(member: str, label: str, argv: list[str]) -> Process:
        """argv started in `member`'s car: on a channel, in its namespace with its DDS profile."""
        return Process(label, channel.wrap(member, argv), echo, channel_environment(member)) if channel else Process(label, argv, echo)

    model = ["-p", f"checkpoint:={checkpoint}", "-p", "autostart:=false",  # the demo drives the lifecycle
             "-p", f"device:={opts.device}", "-p", f"precision:={opts.precision}"]
    ros_params = [x for p in opts.params for x in ("-p", p)]
    ego_params = [x for p in opts.ego_params for x in ("-p", p)]
    shown = [re.escape(topics.camera_image(ego, cam)) for cam in CAMERAS]  # the layout's camera panels
    recorder = on("ego", "recorder", [executable("recorder"), "--out", str(mcap), "--topics", *DEFAULT_TOPICS, *shown])
    nodes = {"/ego": on("ego", "ego", [executable("ego"), "--ros-args", "-p", f"ego_id:={ego}", *model, *ego_params])}
    # the ego's own encoder runs on the ego: its features reach the fusion losslessly; --params is the V2X codec of the others
    lossless = [x for p in LOSSLESS for x in ("-p", p)]
    for c in cavs:
        nodes[topics.vehicle_node(c)] = on("ego" if c == ego else f"cav{c}", f"vehicle {c}", [
            executable("vehicle"), "--id", str(c), "--ros-args", *model, *(lossless if c == ego else ros_params)])
    player = None
    supervisor = Supervisor("demo", alive=lambda: next((f"{p.label} exited with code {p.proc.returncode}" for p in [recorder, *nodes.values()]
                                                        if p.proc.poll() is not None), None))
    try:
        say("configuring the nodes (each loads the model), then activating them")
        supervisor.bring_up(list(nodes))
        for c in cavs:  # the ego knows every neighbour before the first frame, or fuses it alone
            supervisor.wait_subscribed("/ego", topics.voxel_features(c))
        for topic in (topics.EGO_OCCUPANCY, topics.DIAGNOSTICS):  # the nodes' outputs are recorded from their first frame on
            supervisor.wait_subscribed("/recorder", topic)
        say(f"playing the bag at rate {opts.rate}")
        player = Process("player", [executable("player"), str(bag), "--rate", str(opts.rate), "--wait-subscribers", "30",
                                    "--topics", *played_topics(cavs, sensors)], echo)
        if player.proc.wait() != 0:
            raise Co3sopError(f"player failed with code {player.proc.returncode}")
        say("bag played; waiting for the ego to fuse the last frames")
        accounted = lambda: frames_accounted(supervisor, ego) >= frames  # noqa: E731
        supervisor.wait(f"the ego to fuse (or skip) all {frames} frames", accounted, timeout=120)
    finally:
        for p in [player, *nodes.values(), recorder]:  # the recorder last, so it sees everything
            if p is not None:
                p.stop()
        supervisor.close()
    reports = supervisor.reports("ego")
    published = len(reports)
    # every node's /diagnostics as the launcher received them (beside the recording, which holds what the recorder got)
    statuses = {"ego": reports, **{f"vehicle cav_{c}": supervisor.reports(f"vehicle cav_{c}") for c in cavs}}
    (opts.out / "diagnostics.json").write_text(json.dumps(statuses, indent=1) + "\n")
    skipped = frames_accounted(supervisor, ego) - published
    say(
        f"graph stopped after {time.monotonic() - t0:.0f} s; the ego reported {published} fused frames"
        + (
            f", {skipped} skipped to stay current (the graph fuses slower than rate {opts.rate:g} feeds it)"
            if skipped
            else ""
        )
    )
    if channel:  # what crossed the links in time, frame by frame
        say("neighbours fused per frame: " + " ".join(r.get("neighbours_used", "?") for r in reports) + "; heard but late: " +
            " ".join(r["neighbours_missing"] or "-" for r in reports) + "; never received: " +
            " ".join(r["neighbours_silent"] or "-" for r in reports))
    if channel and opts.channel_loss:
        say("packets dropped by the channel: " + ", ".join(f"{m} {channel.dropped(m)}" for m in channel.links))
    code = score.main([str(mcap), "--out", str(opts.out)])
    layout = write_layout(opts.out / "foxglove_layout.json", ego)
    say(f"to see it in 3D: open {mcap} in Foxglove and import the layout {layout} (prediction | ground truth, cameras)")
    recorded = message_counts(mcap).get(topics.EGO_OCCUPANCY, 0)
    if recorded != published:
        say(f"error: the recording holds {recorded} of the {published} /ego/occupancy messages published")
        return 1
    say(f"the recording holds all {published} /ego/occupancy messages; done in {time.monotonic() - t0:.0f} s")
    return code


entry = run(main)
