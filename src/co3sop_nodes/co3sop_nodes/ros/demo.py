"""The demo: the node graph on a small scenario as processes, its lifecycle driven, the bag played, the
recording scored (`demo` on the command line explains each step; co3sop_nodes.cli.demo)."""

from __future__ import annotations

import contextlib
import json
import math
import os
import resource
import signal
import subprocess
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from ament_index_python.packages import get_package_prefix

from co3sop_nodes.common import topics
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.data.bags import open_reader, read_scans
from co3sop_nodes.eval.scoring import message_counts, score_recording
from co3sop_nodes.inference import pace
from co3sop_nodes.inference.checkpoint import DEFAULT_MODEL, load_graph_model, resolve_checkpoint
from co3sop_nodes.ros.dds import channel_environment, channel_profiles, v2x_priority_port
from co3sop_nodes.ros.graph import NodeSpec, answers_requests, bag_contents, car_of, describe, played_topics
from co3sop_nodes.ros.supervisor import Supervisor
from co3sop_nodes.sim.generation import GenerateOptions, generate, scenario_name
from co3sop_nodes.v2x.channel import Channel, Link
from co3sop_nodes.v2x.ego_pairing import PairingConfig
from co3sop_nodes.viz.foxglove import write_layout

# a scene whose three CAVs all stay within 30 m of the ego over its 10 frames (most seeds spread them 50-100 m
# apart, where a 51.2 m grid shares little); chosen by that rule alone, before scoring, and in no split
DEMO_SEED = 11
DEMO_FRAMES = 10
DEMO_SCENARIO = {
    "splits": ["test=1"],
    "cavs": "3",
    "seed": DEMO_SEED,
    "image_size": "320x240",
    "lidar_steps": 512,
}


def say(text: str) -> None:
    print(f"[demo] {text}", flush=True)


def executable(name: str) -> str:
    """A co3sop_nodes executable, found as `ros2 run` finds it."""
    return str(Path(get_package_prefix("co3sop_nodes"), "lib", "co3sop_nodes", name))


class Process:
    """A child process whose output is echoed with a prefix (or swallowed, but for its last warnings, kept to explain
    a failure)."""

    def __init__(self, label: str, argv: list[str], echo: bool = True, env: dict[str, str] | None = None):
        self.label = label
        self._echo = echo
        self.warnings: deque[str] = deque(maxlen=3)
        self.proc = subprocess.Popen(
            argv,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, **(env or {})},
            start_new_session=True,
        )  # Ctrl-C on the demo reaches the demo only; it stops the children
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            if "[WARN]" in line or "[ERROR]" in line:
                self.warnings.append(line.strip())
            if self._echo:
                print(f"  [{self.label}] {line.rstrip()}", flush=True)

    def cpu_seconds(self) -> float | None:
        """CPU time (user + system, every thread) the process has used so far; None once it has exited, or without
        Linux's /proc."""
        try:
            stat = Path(f"/proc/{self.proc.pid}/stat").read_text()
        except OSError:
            return None
        fields = stat.rsplit(")", 1)[1].split()  # after "pid (name)": state, ppid, ...; utime and stime 12th and 13th
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

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


def warned(*processes: Process | None) -> str:
    """The last warnings of `processes`, for an error message ("" if none warned)."""
    lines = [f"[{p.label}] {w}" for p in processes if p is not None for w in p.warnings]
    return "; their last warnings:\n  " + "\n  ".join(lines) if lines else ""


def bag_period(bag: Path, frames: int) -> float:
    """Seconds between a bag's frames (0.1 for a 10 Hz bag)."""
    reader = open_reader(bag)
    with reader:
        return (reader.end_time - reader.start_time) / 1e9 / max(1, frames - 1) if frames > 1 else 0.1


def measured_rate(
    model,
    vehicles: int,
    period: float,
    egos: int = 1,
    scans: bool = False,
    scan: np.ndarray | None = None,
    vehicle_model=None,
) -> float:
    """The playback rate this machine keeps up with for `vehicles` vehicles and `egos` egos (model.pace; with
    `scans`, each ego also encoding its neighbours' scans; a LiDAR model's vehicle measured on `scan`, on
    `vehicle_model` where the vehicle nodes run a path of their own), to 2 digits."""
    cost = pace.frame_cost(model, scan=scan, vehicles=vehicle_model)
    n = pace.cores()
    rate = math.floor(100 * pace.sustainable_rate(cost, vehicles, period, n, egos=egos, scans=scans)) / 100
    say(
        f"measured per frame on one thread: vehicle {1e3 * cost.vehicle_s:.0f} ms, ego {1e3 * cost.ego_s:.0f} ms, "
        f"the recorder's pictures {1e3 * cost.recording_s:.0f} ms"
        + (" and a vehicle half per neighbour's scan" if scans else "")
        + f"; {vehicles} vehicles + {egos} ego{'s' if egos > 1 else ''} on {n} cores keep up with rate {rate:g} "
        f"(a frame every {period / max(rate, 0.01):.2f} s"
        + ("" if rate >= 1 else f", bound by {pace.rate_bound(cost, vehicles, n, egos=egos, scans=scans)}")
        + ")"
    )
    return max(rate, 0.01)


def vehicle_model(model, checkpoint: Path, device: str, precision: str, what: str = "--"):
    """The model as the vehicle nodes run it, on `precision` (auto: as a vehicle takes it, int8 where its int8 layers
    are tuned for it): `model` itself where that is the path it holds, else a copy of it on the vehicles' path.
    `what`: how the option is spelt in errors."""
    path = model.vehicle_path(device, precision, what=what)
    return model if path == model.path else load_graph_model(checkpoint)[0].use(path)


def ensure_scenario(opts) -> Path:
    if opts.bag:
        return opts.bag
    data, bags = (
        (opts.data, opts.bags)
        if opts.frames == DEMO_FRAMES
        else (opts.data / f"{opts.frames}f", opts.bags / f"{opts.frames}f")
    )
    bag = bags / "test" / scenario_name("test", 0, DEMO_SEED)
    if not (bag / "metadata.yaml").exists():
        say(
            f"no demo scenario of {opts.frames} frames yet: generating one (3 CAVs) into {data} and {bags} "
            f"(about {max(1, round(opts.frames / 10))} minute(s))"
        )
        generate(GenerateOptions(out=data, bags=bags, frames=opts.frames, workers=pace.cores(), **DEMO_SCENARIO))
    return bag


@dataclass
class DemoOptions:
    """What `demo` runs; its options, as the command line names them."""

    bag: Path | None = None
    data: Path = Path("data/demo")
    bags: Path = Path("bags/demo")
    out: Path = Path("results/demo")
    frames: int = DEMO_FRAMES
    rate: float | None = None
    vehicles: int = 3
    model: str = DEFAULT_MODEL
    params: dict = field(default_factory=dict)
    ego_params: dict = field(default_factory=dict)
    precision: str = "auto"
    device: str = "cpu"
    quiet: bool = False
    channel_rate: float | None = None
    channel_loss: float = 0.0
    channel_shared: bool = False
    channel_multicast: bool = False
    channel_answer_ms: float | None = None  # None: the shared medium's queue time, or Fast DDS's own
    channel_maps_first: bool = False  # the egos' request maps cross the shared medium first
    egos: str = "first"


def run_demo(opts: DemoOptions) -> int:
    """The graph on the demo scenario (generated once) or `opts.bag`, recorded and scored; 0 when the recording
    holds every prediction the ego published."""
    signal.signal(
        signal.SIGTERM, _interrupt
    )  # SIGTERM unwinds like Ctrl-C: the children are stopped, namespaces removed
    t0 = time.monotonic()
    checkpoint = resolve_checkpoint(opts.model, "--model")
    model, _ = load_graph_model(checkpoint)  # refused here, before any node starts, if the graph cannot run it
    path = model.ego_path(opts.device, opts.precision, what="--")  # refused here if the machine lacks the device
    sensors = model.cfg.modality
    bag = ensure_scenario(opts)
    cavs, frames = bag_contents(bag)
    cavs = cavs[: opts.vehicles]
    ego = cavs[0]
    opts.out.mkdir(parents=True, exist_ok=True)
    mcap = opts.out / "demo.mcap"
    egos = cavs if opts.egos == "all" else [ego]
    say(f"bag {bag}: {frames} frames; vehicles {cavs}, ego{'s' if len(egos) > 1 else ''} {egos}; recording to {mcap}")
    model.use(path)
    missing = f" ({model.int8_missing()})" if path.int8 and not model.path.int8 else ""
    # the vehicle nodes' precision: the ego's or their own, from --params
    own = "precision" in opts.params
    vehicles = vehicle_model(
        model, checkpoint, opts.device, opts.params.get("precision", opts.precision), "--params " if own else "--"
    )
    on_own = f"; the vehicles on {vehicles.path.describe()}" if vehicles is not model else ""
    say(f"model {checkpoint} ({sensors}); inference on {model.path.describe()}{missing}{on_own}")
    if opts.rate is None:
        scans = opts.params.get("send") == "scan"
        scan = next(iter(read_scans(bag, 1)), None) if model.cfg.modality == "lidar" else None
        # sending scans, the vehicle halves run in the egos, on theirs
        on = model if scans else vehicles
        opts.rate = measured_rate(model, len(cavs), bag_period(bag, frames), len(egos), scans, scan, on)
    channel, profiles = (
        _open_channel(opts, bag, frames, cavs, egos, sensors) if opts.channel_rate is not None else (None, None)
    )
    with channel or contextlib.nullcontext():
        return _graph(opts, checkpoint, sensors, bag, cavs, frames, mcap, channel, profiles, t0)


def _open_channel(
    opts: DemoOptions, bag: Path, frames: int, cavs: list[int], egos: list[int], sensors: str
) -> tuple[Channel, Path]:
    """The emulated V2X channel of `opts` (not yet built: a context manager) and its Fast DDS profiles, everything
    on it slowed with the play rate; sets this process's DDS environment and the egos' waits."""
    # rate and queue in real time: at play rate r a link carries r times the bytes per second, and a packet
    # may wait 1 / r times as long (200 ms of real time)
    link = Link(opts.channel_rate * opts.rate, opts.channel_loss / 100, Link.queue_ms / opts.rate)
    first = (v2x_priority_port(),) if opts.channel_maps_first else ()
    channel = Channel(
        {car_of(c, cavs): link for c in cavs}, shared=link if opts.channel_shared else None, priority_ports=first
    )
    requests = [topics.ego_output(topics.EGO_REQUEST, c if opts.egos == "all" else None) for c in egos]
    # what every CAV hears: the vehicles' features or scans and the egos' request maps
    sent = [t(c) for c in cavs for t in (topics.voxel_features, topics.voxel_scan)]
    multicast = [*sent, *requests] if opts.channel_multicast else []
    # on a shared medium a reader answers a heartbeat after the medium's queue time: answered at once, it names
    # fragments that still arrive, and their repairs crowd the medium (BENCHMARKS.md); on a link of its own, a
    # lost fragment is asked for again at Fast DDS's own delay
    answer_after = Link.queue_ms / 1000 if opts.channel_shared else None
    if opts.channel_answer_ms is not None:
        answer_after = opts.channel_answer_ms / 1000
    # off the radio, at Fast DDS's own timers: the egos' outputs and /diagnostics (to the machine's side), each car's
    # sensors (the simulator stands for them: the player's last messages must be repaired before it exits) and an
    # ego's own features on board
    outputs = [topics.EGO_OCCUPANCY, topics.EGO_POINTS, topics.EGO_TRUTH_POINTS]
    harness = [topics.ego_output(t, c if opts.egos == "all" else None) for t in outputs for c in egos]
    harness += [*played_topics(cavs, sensors), topics.CLOCK, topics.DIAGNOSTICS]
    harness += [topics.local_features(c) for c in egos] if opts.egos == "all" else []
    profiles = channel_profiles(
        opts.out / "dds", 1 / opts.rate, answer_after, multicast, harness, requests if opts.channel_maps_first else ()
    )
    # the egos' waits for the link, slowed as it is: a neighbour's frame may take a frame of real time on it,
    # and a neighbour is live while it was heard within five (where the ego's own defaults are shorter)
    frame = bag_period(bag, frames) / opts.rate
    waits = {"max_wait": max(PairingConfig.max_wait_s, frame)}
    waits["neighbour_timeout"] = max(PairingConfig.neighbour_timeout_ns / 1e9, 5 * frame)
    opts.ego_params = {**{k: round(v, 3) for k, v in waits.items()}, **opts.ego_params}
    os.environ.update(channel_environment(None, profiles))  # before any DDS participant, the supervisor's included
    say(
        f"emulated V2X channel: each CAV transmits at {link.rate_mbit:g} Mbit/s ({opts.channel_rate:g} "
        f"Mbit/s of real time "
        f"at rate {opts.rate:g}), {opts.channel_loss:g} % of its packets lost"
        + ("; all of them together on one medium of that rate" if opts.channel_shared else "")
        + ("; features and request maps multicast, each sent once for all" if opts.channel_multicast else "")
        + ("; request maps cross the medium first" if opts.channel_maps_first else "")
        + f"; egos wait up to {opts.ego_params['max_wait']:g} s for a neighbour's frame"
        + ("" if answer_after is None else f"; DDS readers answer a heartbeat after {1e3 * answer_after:g} ms")
    )
    return channel, profiles


def frames_accounted(supervisor: Supervisor, ego: NodeSpec) -> int:
    """An ego's own frames fused, or skipped to stay current by the ego or by its own encoder (from their latest
    /diagnostics: the newest frame is never skipped, so the last report counts every skip before it)."""
    fused = supervisor.reports(status_of(ego))
    encoder = supervisor.reports(f"vehicle cav_{ego.parameters['ego_id']}")
    return (
        len(fused)
        + (int(fused[-1].get("skipped", 0)) if fused else 0)
        + (int(encoder[-1].get("skipped", 0)) if encoder else 0)
    )


class QuietMedium:
    """Callable for Supervisor.wait: the shared medium carried less than `share` of its rate over the last `window`
    s. What the nodes send as they start crosses the medium too (among it ROS's graph information, the user data
    topic ros_discovery_info: every node's endpoints, to every other participant), and at a slowed rate it may still
    be queued when the V2X links are up: the bag's first frames would wait behind it."""

    def __init__(
        self, channel: Channel, share: float = 0.1, window: float = 2.0, every: float = 0.25, clock=time.monotonic
    ):
        self.channel, self.share, self.window, self.every, self.clock = channel, share, window, every, clock
        self.samples: deque[tuple[float, int]] = deque()  # (monotonic s, bytes carried so far), oldest first

    def __call__(self) -> bool:
        now = self.clock()
        if self.samples and now - self.samples[-1][0] < self.every:
            return False
        carried = self.channel.carried_by_medium()
        self.samples.append((now, carried))
        while len(self.samples) > 1 and now - self.samples[1][0] >= self.window:
            self.samples.popleft()  # the first sample left is the newest one at least `window` s old
        since, before = self.samples[0]
        rate = self.channel.shared.rate_mbit * 1e6 / 8  # bytes/s
        return now - since >= self.window and (carried - before) / (now - since) < self.share * rate


def status_of(ego: NodeSpec) -> str:
    """The name an ego's status has on /diagnostics: its node's name ("ego", "cav_3/ego")."""
    return ego.node.lstrip("/")


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _graph(
    opts,
    checkpoint: Path,
    sensors: str,
    bag: Path,
    cavs: list[int],
    frames: int,
    mcap: Path,
    channel: Channel | None,
    profiles: Path | None,
    t0: float,
) -> int:
    """The nodes started (inside the channel's namespaces where there is one), the bag played, the recording scored."""
    echo = not opts.quiet
    every = opts.egos == "all"
    common = {
        "checkpoint": checkpoint,
        "autostart": False,  # the demo drives the lifecycle
        "device": opts.device,
        "precision": opts.precision,
    }
    graph = describe(
        bag,
        cavs,
        sensors,
        mcap,
        opts.rate,
        egos=opts.egos,
        common=common,
        ego_params=opts.ego_params,
        vehicle_params=opts.params,
    )

    def start(spec: NodeSpec, label: str) -> Process:
        """A node started in its car: on a channel, in that car's namespace with its DDS profile."""
        argv = [*spec.prefix, executable(spec.executable), *spec.ros_arguments()]
        if channel and spec.car is not None:
            return Process(label, channel.wrap(spec.car, argv), echo, channel_environment(spec.car, profiles))
        return Process(label, argv, echo)

    recorder = start(graph.recorder, "recorder")
    nodes = {spec.node: start(spec, f"ego {spec.parameters['ego_id']}" if every else "ego") for spec in graph.egos}
    for spec in graph.vehicles:
        nodes[spec.node] = start(spec, f"vehicle {spec.parameters['id']}")
    player = None
    supervisor = Supervisor(
        "demo",
        alive=lambda: next(
            (
                f"{p.label} exited with code {p.proc.returncode}"
                for p in [recorder, *nodes.values()]
                if p.proc.poll() is not None
            ),
            None,
        ),
    )
    try:
        say("configuring the nodes (each loads the model), then activating them")
        supervisor.bring_up(list(nodes))
        # every link up as each end sees it: each ego matched to every vehicle's features or scans (or it fuses that
        # neighbour's first frames without it) and each vehicle's to a reader (what it sends before is lost), each
        # vehicle that answers request maps to every other car's ego's
        sent = {
            v.parameters["id"]: topics.voxel_scan if v.parameters.get("send") == "scan" else topics.voxel_features
            for v in graph.vehicles
        }
        needs = {}
        for ego in graph.egos:
            own = ego.parameters["ego_id"]
            needs[status_of(ego)] = [topics.local_features(c) if every and c == own else sent[c](c) for c in cavs]
            # the nodes' outputs are recorded from their first frame on
            supervisor.wait_subscribed("/recorder", topics.ego_output(topics.EGO_OCCUPANCY, own if every else None))
            if str(ego.parameters.get("request_maps", True)).lower() == "false":
                continue
            request = topics.ego_output(topics.EGO_REQUEST, own if every else None)
            for v in graph.vehicles:
                if v.parameters["id"] != own and answers_requests(v):
                    needs.setdefault(f"vehicle cav_{v.parameters['id']}", []).append(request)
        sends = {
            f"vehicle cav_{c}": [sent[c](c), *([topics.local_features(c)] if every else [])]
            for c in (v.parameters["id"] for v in graph.vehicles)
        }
        supervisor.wait_subscribed("/recorder", topics.DIAGNOSTICS)
        supervisor.wait(
            "every V2X link up (each ego matched to every vehicle, each vehicle to every other ego)",
            lambda: all(supervisor.linked(s, needs.get(s, ()), sends.get(s, ())) for s in {*needs, *sends}),
            timeout=120,
        )
        if channel and opts.channel_shared:
            supervisor.wait("the shared medium to fall quiet (the nodes' start crossed it)", QuietMedium(channel), 120)
        say(f"playing the bag at rate {opts.rate}")
        running = {p.label: p for p in [*nodes.values(), recorder]}
        cpu_before = {label: p.cpu_seconds() for label, p in running.items()}
        children_before = resource.getrusage(resource.RUSAGE_CHILDREN)
        player = Process("player", [executable(graph.player.executable), *graph.player.ros_arguments()], echo)
        if player.proc.wait() != 0:
            raise Co3sopError(f"player failed with code {player.proc.returncode}")
        children = resource.getrusage(resource.RUSAGE_CHILDREN)  # the player: the only child that ended meanwhile
        player_cpu = sum(getattr(children, f) - getattr(children_before, f) for f in ("ru_utime", "ru_stime"))
        say(f"bag played; waiting for the ego{'s' if every else ''} to fuse the last frames")
        accounted = lambda: all(frames_accounted(supervisor, ego) >= frames for ego in graph.egos)
        try:
            supervisor.wait(f"every ego to fuse (or skip) all {frames} frames", accounted, timeout=120)
        except Co3sopError as exc:
            counts = ", ".join(f"{status_of(e)} {frames_accounted(supervisor, e)}" for e in graph.egos)
            raise Co3sopError(f"{exc} (frames fused or skipped: {counts}){warned(player, *nodes.values())}") from None
        if not channel:  # on a channel each node runs under a wrapper process, whose own CPU says nothing
            after = {label: p.cpu_seconds() for label, p in running.items()}
            used = {  # without /proc, nothing to say
                label: after[label] - cpu_before[label]
                for label in running
                if after[label] is not None and cpu_before[label] is not None
            }
            say(
                "CPU a frame while the bag played (ms): "
                + ", ".join(f"{label} {1e3 * c / frames:.0f}" for label, c in {"player": player_cpu, **used}.items())
                + " (the player's start included)"
            )
    finally:
        for p in [player, *nodes.values(), recorder]:  # the recorder last, so it sees everything
            if p is not None:
                p.stop()
        supervisor.close()
    # every node's /diagnostics as the launcher received them (beside the recording, which holds what the recorder got)
    statuses = {status_of(ego): supervisor.reports(status_of(ego)) for ego in graph.egos}
    statuses |= {f"vehicle cav_{c}": supervisor.reports(f"vehicle cav_{c}") for c in cavs}
    (opts.out / "diagnostics.json").write_text(json.dumps(statuses, indent=1) + "\n")
    published = 0
    for ego in graph.egos:
        reports = statuses[status_of(ego)]
        published += len(reports)
        skipped = frames_accounted(supervisor, ego) - len(reports)
        say(
            (f"ego {ego.parameters['ego_id']}" if every else "the ego")
            + f" reported {len(reports)} fused frames"
            + (
                f", {skipped} skipped to stay current (the graph fuses slower than rate {opts.rate:g} feeds it)"
                if skipped
                else ""
            )
        )
        if channel:  # what crossed the links in time, frame by frame
            say(
                "  neighbours fused per frame: "
                + " ".join(r.get("neighbours_used", "?") for r in reports)
                + "; heard but late: "
                + " ".join(r["neighbours_missing"] or "-" for r in reports)
                + "; never received: "
                + " ".join(r["neighbours_silent"] or "-" for r in reports)
            )
    say(f"graph stopped after {time.monotonic() - t0:.0f} s")
    if channel and opts.channel_loss:
        say("packets dropped by the channel: " + ", ".join(f"{m} {channel.dropped(m)}" for m in channel.links))
    if channel and opts.channel_shared:
        carried = channel.carried_by_medium()
        say(
            f"the shared medium carried {carried / 1e3:,.1f} KB, {carried / frames / 1e3:,.1f} KB a frame "
            f"({100 * channel.medium_load():.0f} % of what it could carry while the graph ran); "
            f"packets it dropped (more than its queue held): {channel.dropped_by_medium()}"
        )
    code = score_recording(mcap, opts.out)
    layout = write_layout(opts.out / "foxglove_layout.json", cavs[0], every)
    say(f"to see it in 3D: open {mcap} in Foxglove and import the layout {layout} (prediction | ground truth, cameras)")
    counts = message_counts(mcap)
    recorded = sum(n for t, n in counts.items() if topics.is_ego_occupancy(t))
    if recorded != published:
        say(f"error: the recording holds {recorded} of the {published} ego occupancy messages published")
        return 1
    say(f"the recording holds all {published} ego occupancy messages; done in {time.monotonic() - t0:.0f} s")
    return code
