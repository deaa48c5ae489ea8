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
Namespaces are removed on exit, SIGINT and SIGTERM included. What the cars send
to the machine's side (the recorder, this launcher's diagnostics) is off the radio.

With --egos all every CAV runs an ego besides its vehicle (in its namespace:
/cav_N/ego/occupancy), fed its own car's features losslessly on board
(voxel_features/local) and the others' through their V2X codec; each vehicle
answers every ego's request map (parameter request_answer: one message for
each, or one for all); the score gives each ego's table and the mean.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from co3sop_nodes.cli.common import run
from co3sop_nodes.model.path import PRECISIONS
from co3sop_nodes.ros.demo import DemoOptions, run_demo
from co3sop_nodes.ros.graph import EGOS

DEFAULTS = DemoOptions()  # the library's defaults are the command's


def _parameters(items: list[str], option: str, parser: argparse.ArgumentParser) -> dict[str, str]:
    """NAME:=VALUE items, as `ros2 run ... -p` takes them."""
    pairs = [item.partition(":=") for item in items]
    bad = [item for item, (name, sep, _) in zip(items, pairs) if not (name and sep)]
    if bad:
        parser.error(f"{option} {bad[0]!r}: expected NAME:=VALUE")
    return {name: value for name, _, value in pairs}


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="demo", description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--bag", type=Path, help="a CAV bag to play (default: the generated demo scenario)")
    parser.add_argument("--data", type=Path, default=DEFAULTS.data, help="where the demo scenario is generated")
    parser.add_argument("--bags", type=Path, default=DEFAULTS.bags, help="where the demo scenario's bag is written")
    parser.add_argument("--out", type=Path, default=DEFAULTS.out, help="recording, score and pictures")
    parser.add_argument(
        "--frames",
        type=int,
        default=DEFAULTS.frames,
        help="10 Hz frames of the generated demo scenario (the same "
        "town and traffic, longer; generated once per length)",
    )
    parser.add_argument(
        "--rate", type=float, help="playback rate, 1 = real time (default: what this machine keeps up with, measured)"
    )
    parser.add_argument(
        "--vehicles",
        type=int,
        default=DEFAULTS.vehicles,
        help="vehicle processes (the first CAVs of the bag; the first is the ego)",
    )
    parser.add_argument(
        "--model",
        default=DEFAULTS.model,
        help=f"checkpoint of every node: a shipped one by name (tiny-lidar: collaborative LiDAR; tiny: "
        f"camera; small: the larger, GPU-trained camera model) or a path "
        f"(default: {DEFAULTS.model})",
    )
    parser.add_argument(
        "--params",
        nargs="*",
        default=[],
        help="parameters of the other vehicles, e.g. codec.dtype:=int8 (the V2X codec; the ego's own encoder "
        "is lossless)",
    )
    parser.add_argument("--ego-params", nargs="*", default=[], help="parameters of the ego node, e.g. threads:=2")
    parser.add_argument(
        "--precision",
        default=DEFAULTS.precision,
        choices=PRECISIONS,
        help="inference precision of every node (auto: what the "
        "machine computes fast; float32 on CPUs without AMX or AVX-512 BF16)",
    )
    parser.add_argument(
        "--device", default=DEFAULTS.device, help="where every node's model runs: cpu, cuda, cuda:N, auto"
    )
    parser.add_argument("--quiet", action="store_true", help="do not echo the nodes' output")
    parser.add_argument(
        "--channel-rate",
        type=float,
        metavar="MBIT",
        help="run over an emulated V2X channel: each CAV in its own network namespace, transmitting at most MBIT "
        "Mbit/s of real time (the link runs at MBIT x --rate); needs root, iproute2 and nftables",
    )
    parser.add_argument(
        "--channel-loss",
        type=float,
        default=DEFAULTS.channel_loss,
        metavar="PERCENT",
        help="with --channel-rate: share of each CAV's packets dropped at random (default 0)",
    )
    parser.add_argument(
        "--channel-shared",
        action="store_true",
        help="with --channel-rate: every CAV transmits on one shared medium of that rate (together, as on one radio "
        "channel), not each on a link of its own",
    )
    parser.add_argument(
        "--channel-multicast",
        action="store_true",
        help="with --channel-rate: feature messages go to one multicast group, each sent once for every ego it "
        "reaches (as a radio broadcasts), not as a copy to each",
    )
    parser.add_argument(
        "--channel-maps-first",
        action="store_true",
        help="with --channel-shared and --channel-multicast: the egos' request maps cross the medium before the "
        "features waiting on it (as 802.11p sends short control frames first)",
    )
    parser.add_argument(
        "--channel-answer-ms",
        type=float,
        metavar="MS",
        help="with --channel-rate: how long a DDS reader waits after a heartbeat before it asks for what it misses, "
        "ms of real time (default: the shared medium's queue, 200, with --channel-shared; else Fast DDS's 5)",
    )
    parser.add_argument(
        "--egos",
        choices=EGOS,
        default=DEFAULTS.egos,
        help="which CAVs run an ego: the first (default) or all, each then also a collaborator of the others",
    )
    opts = parser.parse_args(args)
    channel_options = (
        opts.channel_loss,
        opts.channel_shared,
        opts.channel_multicast,
        opts.channel_answer_ms is not None,
    )
    if opts.channel_rate is None and any(channel_options):
        parser.error(
            "--channel-loss, --channel-shared, --channel-multicast and --channel-answer-ms need --channel-rate"
        )
    if opts.channel_maps_first and not (opts.channel_shared and opts.channel_multicast):
        parser.error("--channel-maps-first needs --channel-shared and --channel-multicast (a group's port goes first)")
    if opts.channel_answer_ms is not None and not 0 <= opts.channel_answer_ms <= 10_000:
        parser.error(f"--channel-answer-ms {opts.channel_answer_ms}: 0 to 10000")
    if opts.rate is not None and not opts.rate > 0:
        parser.error(f"--rate {opts.rate}: must be above 0")
    if opts.frames < 1:
        parser.error(f"--frames {opts.frames}: at least 1")
    if opts.vehicles < 1:
        parser.error(f"--vehicles {opts.vehicles}: at least 1 (the ego's)")
    params = _parameters(opts.params, "--params", parser)
    ego_params = _parameters(opts.ego_params, "--ego-params", parser)
    return run_demo(DemoOptions(**{**vars(opts), "params": params, "ego_params": ego_params}))


entry = run(main)
