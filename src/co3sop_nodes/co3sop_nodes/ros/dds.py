"""DDS settings every Co3SOP process applies, QoS profiles, and the node main loop."""

from __future__ import annotations

import faulthandler
import os
import re
import sys
import time
import xml.etree.ElementTree as ET
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import rclpy
from ament_index_python.packages import get_package_share_directory
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message

from co3sop_nodes.common.errors import Co3sopError, exception_line
from co3sop_nodes.v2x.sender_requests import MAPS_PER_EGO

PACKAGE = "co3sop_nodes"

# Features and predictions are large multi-fragment samples: best effort drops a whole sample when one fragment
# is lost, so reliable with a short queue (a late frame is useless) by default. Over a lossy V2X link best effort
# trades lost frames for no resends (the `features_reliability` parameter; bench_channel.py measures both).
RELIABILITIES = {"reliable": ReliabilityPolicy.RELIABLE, "best_effort": ReliabilityPolicy.BEST_EFFORT}


def features_qos(reliability: str = "reliable", depth: int = 2) -> QoSProfile:
    """The QoS of VoxelFeatures: `reliability` one of RELIABILITIES (a best-effort subscription also matches a
    reliable publisher; a reliable one does not match a best-effort publisher)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=RELIABILITIES[reliability],
        durability=DurabilityPolicy.VOLATILE,
    )


FEATURES_QOS = features_qos()
OCCUPANCY_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=5,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
# Request maps: small, reliable, as many held as a vehicle keeps of each ego (a vehicle behind the ego answers each
# frame with the map made for it, which a depth of one overwrites with the next whenever its executor is late);
# latched, so a vehicle that joins (or matches late) gets each ego's latest requests at once instead of a frame later
REQUEST_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=MAPS_PER_EGO,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# /diagnostics: one status per node per frame; reliable so the recorder and benchmarks see every one
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE)


class DropLog:
    """Counts dropped messages by kind and warns once per burst.

    The first drop of a kind of reason on a topic is logged; repeats within
    `quiet` s of the previous one are only counted (a flood must not flood the
    log), and their number is appended to the next warning of that kind.
    """

    def __init__(self, logger, quiet: float = 2.0, max_keys: int = 1024):
        self.counts: Counter[str] = Counter()
        self._logger, self._quiet, self._max_keys = logger, quiet, max_keys
        self._bursts: dict[tuple[str, str, str], list] = {}  # key -> [monotonic of the last drop, drops not logged]

    def __call__(self, topic: str, kind: str, reason: str) -> None:
        self.counts[kind] += 1
        key = (topic, kind, re.sub(r"\d+", "#", reason))  # "the same reason" whatever the numbers in it
        now = time.monotonic()
        burst = self._bursts.get(key)
        if burst is not None and now - burst[0] < self._quiet:
            burst[0], burst[1] = now, burst[1] + 1
            return
        more = f" ({burst[1]} more like it not logged)" if burst is not None and burst[1] else ""
        if len(self._bursts) >= self._max_keys:  # many distinct reasons: forget the quiet ones
            self._bursts = {k: b for k, b in self._bursts.items() if now - b[0] < self._quiet}
        self._bursts[key] = [now, 0]
        self._logger.warning(f"{topic}: dropped ({kind}): {reason}{more}")

    def values(self) -> dict[str, int]:
        """Diagnostic values: the total and one count per kind."""
        return {"dropped": sum(self.counts.values()), **{f"dropped_{k}": v for k, v in sorted(self.counts.items())}}


def subscribe_foreign(node: Node, msg_type, topic: str, callback: Callable, qos, drops: DropLog, raw: bool = False):
    """A subscription to data another process sends, robust to malformed CDR.

    A typed subscription deserialises inside the executor, where a truncated
    message or a lying length field raises out of spin() and kills the node.
    This one takes the raw bytes and deserialises them here: a message that
    does not deserialise is dropped as "malformed" and counted in `drops`.
    `callback(msg)` gets the message, or `callback(msg, raw)` when `raw`.
    """

    name = node.resolve_topic_name(topic)  # as the graph shows it: after namespace and remapping

    def on_raw(data: bytes) -> None:
        try:
            msg = deserialize_message(data, msg_type)
        except Exception as exc:
            return drops(
                name, "malformed", f"{len(data)} bytes that are not a valid {msg_type.__name__} ({exception_line(exc)})"
            )
        return callback(msg, data) if raw else callback(msg)

    return node.create_subscription(msg_type, topic, on_raw, qos, raw=True)


def matching_qos(node: Node, topic: str, depth: int) -> QoSProfile | None:
    """A subscription QoS every current publisher of `topic` matches, as rosbag2 adapts its own: reliable only
    when every publisher is, transient local only when every publisher is; None while none publishes."""
    offered = [info.qos_profile for info in node.get_publishers_info_by_topic(topic)]
    if not offered:
        return None
    reliable = all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    durable = all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if durable else DurabilityPolicy.VOLATILE,
    )


class SensorSubscriptions:
    """Subscriptions to sensor topics, each made once the topic has a publisher, with the QoS it offers
    (matching_qos): a best-effort camera or LiDAR driver matches as well as a reliable bag player, and a reliable
    publisher keeps its delivery guarantee (a fixed best-effort subscription would lose it)."""

    def __init__(self, node: Node, drops: DropLog, period: float = 0.2):
        self._node, self._drops = node, drops
        self._waiting: list[tuple] = []
        self.subscriptions: dict[str, object] = {}
        self._timer = node.create_timer(period, self._poll)

    def add(self, msg_type, topic: str, callback: Callable, depth: int) -> None:
        self._waiting.append((msg_type, topic, callback, depth))
        self._poll()

    def _poll(self) -> None:
        still = []
        for msg_type, topic, callback, depth in self._waiting:
            qos = matching_qos(self._node, topic, depth)
            if qos is None:
                still.append((msg_type, topic, callback, depth))
                continue
            self.subscriptions[topic] = subscribe_foreign(self._node, msg_type, topic, callback, qos, self._drops)
        self._waiting = still

    def close(self) -> None:
        """Unsubscribes from everything and stops looking for publishers."""
        self._node.destroy_timer(self._timer)
        for sub in self.subscriptions.values():
            self._node.destroy_subscription(sub)
        self.subscriptions, self._waiting = {}, []


def flush_publishers(node: Node, publishers, timeout: float = 5.0) -> None:
    """Waits (at most `timeout` s in all) until reliable subscribers acknowledged everything published:
    a node that exits right after its last publish would otherwise take those messages down with it."""
    deadline = time.monotonic() + timeout
    for pub in publishers:
        if not pub.wait_for_all_acked(Duration(seconds=max(0.0, deadline - time.monotonic()))):
            node.get_logger().warning(f"{pub.topic_name}: not every subscriber acknowledged the last messages")


def fastdds_profile_path(name: str = "fastdds.xml") -> str:
    """A shipped Fast DDS profile; by default the one every process uses (large shared-memory segment)."""
    return os.path.join(get_package_share_directory(PACKAGE), "config", name)


# On a channel with multicast, the readers of feature messages listen on this group: a writer then sends each sample
# once for every reader, as a radio broadcasts (unicast, it sends a copy to each)
V2X_MULTICAST_GROUP = "239.255.67.1"
_PROFILES_NS = "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"
CHANNEL_PROFILES = ("fastdds_onboard.xml", "fastdds_udp.xml")


def v2x_multicast_port() -> int:
    """The group's port: RTPS's user-data multicast port of the domain (odd, as user data's are: the channel keeps
    even ports, discovery's, off the radio)."""
    domain = os.environ.get("ROS_DOMAIN_ID", "").strip()
    return 7401 + 250 * (int(domain) if domain.isdigit() else 0)


def v2x_priority_port() -> int:
    """The group's port for the topics a shared medium carries first (Channel's priority_ports): odd, unused by the
    standard mapping (between the multicast user-data port and the first unicast metatraffic port)."""
    return v2x_multicast_port() + 2


# Fast DDS's reliability timers (its defaults, seconds): the writer's heartbeat period and delays, the reader's
# responses. On a channel slowed by the play rate they run on the wall clock, which the link's rate and queue do
# not: at rate 0.05 a 3 s heartbeat period is 150 ms of the channel's time, and every repair and acknowledgement
# it triggers (of the features, the request maps, and ROS's own graph information, which also crosses the radio)
# adds to a medium already full. channel_profiles scales them as the channel is scaled.
WRITER_TIMES = {"initialHeartbeatDelay": 0.012, "heartbeatPeriod": 3.0, "nackResponseDelay": 0.005}
READER_TIMES = {"initialAcknackDelay": 0.07, "heartbeatResponseDelay": 0.005}


def channel_profiles(
    folder: Path,
    time_scale: float = 1.0,
    answer_s: float | None = None,
    multicast_topics: list[str] = (),
    harness_topics: list[str] = (),
    priority_topics: list[str] = (),
) -> Path:
    """The channel's Fast DDS profiles written to `folder` (which goes to channel_environment): every writer's and
    reader's reliability timers (WRITER_TIMES, READER_TIMES; the default data_writer and data_reader profiles) times
    `time_scale` (1 / the play rate), a reader's answer to a heartbeat after `answer_s` of real time instead of Fast
    DDS's default where given (on a shared medium, its queue time: what a packet may still take to arrive); every
    reader of `multicast_topics` (full names) listens on the V2X multicast group (rmw_fastrtps applies a data_writer
    or data_reader profile named as a publisher's or a subscription's topic), those of `priority_topics` (among them) on
    the group's v2x_priority_port, which a shared medium carries first. `harness_topics` keep Fast DDS's own
    timers: what the cars send to the machine's side (the recorder, the launcher) is off the radio and unslowed, and
    a repair there, slowed, could come after the graph stopped."""
    if not time_scale > 0:
        raise Co3sopError(f"time_scale must be positive, got {time_scale}")
    if stray := set(priority_topics) - set(multicast_topics):
        raise Co3sopError(f"priority topics {sorted(stray)} are not multicast: only a group's port can be put first")
    folder.mkdir(parents=True, exist_ok=True)
    ET.register_namespace("", _PROFILES_NS)
    tag = lambda name: f"{{{_PROFILES_NS}}}{name}"
    reader_times = READER_TIMES if answer_s is None else {**READER_TIMES, "heartbeatResponseDelay": answer_s}

    def times(parent: ET.Element, defaults: dict[str, float], scale: float = time_scale) -> ET.Element:
        element = ET.SubElement(parent, tag("times"))
        for name, seconds in defaults.items():
            sec, nanosec = divmod(round(seconds * scale * 1e9), 1_000_000_000)
            duration = ET.SubElement(element, tag(name))
            ET.SubElement(duration, tag("sec")).text = str(sec)
            ET.SubElement(duration, tag("nanosec")).text = str(nanosec)
        return parent

    for name in CHANNEL_PROFILES:
        tree = ET.parse(fastdds_profile_path(name))
        profiles = tree.getroot().find(tag("profiles"))
        comment = f" {name} with reliability timers x {time_scale:g} (the channel's play rate)"
        tree.getroot().insert(
            0, ET.Comment(comment + (", the radio's readers multicast " if multicast_topics else " "))
        )
        default = {"profile_name": "v2x_default", "is_default_profile": "true"}
        times(ET.SubElement(profiles, tag("data_writer"), **default), WRITER_TIMES)
        times(ET.SubElement(profiles, tag("data_reader"), **default), reader_times)
        for topic in harness_topics:
            times(ET.SubElement(profiles, tag("data_writer"), profile_name=topic), WRITER_TIMES, 1.0)
            times(ET.SubElement(profiles, tag("data_reader"), profile_name=topic), READER_TIMES, 1.0)
        for topic in multicast_topics:
            reader = times(ET.SubElement(profiles, tag("data_reader"), profile_name=topic), reader_times)
            listen = ET.SubElement(reader, tag("multicastLocatorList"))
            udp = ET.SubElement(ET.SubElement(listen, tag("locator")), tag("udpv4"))
            ET.SubElement(udp, tag("address")).text = V2X_MULTICAST_GROUP
            port = v2x_priority_port() if topic in priority_topics else v2x_multicast_port()
            ET.SubElement(udp, tag("port")).text = str(port)
        tree.write(folder / name, encoding="UTF-8", xml_declaration=True)
    return folder


def channel_environment(member: str | None, profiles: Path | None = None) -> dict[str, str]:
    """What a DDS process of an emulated V2X channel (v2x/channel.py) needs: discovery past localhost and the Fast DDS
    profile of where it runs. The ego's car (member "ego": the fusion node, its own encoder, the recorder) and the
    machine's side (None: the simulator, which stands for the ego's sensors too, and the launcher): shared memory
    among themselves, UDP to the neighbours (fastdds_onboard.xml), so the ego's own lossless feature volume never
    crosses a network stack. A neighbour: UDP only (fastdds_udp.xml), so everything it exchanges crosses a link
    (shared memory would bypass them: every namespace sees the same /dev/shm). All UDP takes RTPS messages of at
    most 1400 bytes: Fast DDS sizes its receive buffers by that limit, so a process sending larger datagrams would
    reach nobody. `profiles`: a folder of channel_profiles to take them from instead of the shipped ones."""
    profile = CHANNEL_PROFILES[0] if member in ("ego", None) else CHANNEL_PROFILES[1]
    path = str(profiles / profile) if profiles is not None else fastdds_profile_path(profile)
    return {"FASTRTPS_DEFAULT_PROFILES_FILE": path, "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}


def configure_environment() -> None:
    """Project defaults, applied before rclpy.init(); variables already set win.

    Discovery stays on this host unless ROS_AUTOMATIC_DISCOVERY_RANGE says
    otherwise (SUBNET for several hosts); every participant uses the shipped
    Fast DDS profile unless FASTRTPS_DEFAULT_PROFILES_FILE names another.
    """
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", fastdds_profile_path())


def spin_node(
    make_node: Callable[[], Node], args: list[str] | None = None, prog: str = "", events: bool = False
) -> int:
    """The Jazzy node idiom: init, spin until Ctrl-C or shutdown, always clean up.

    `make_node` may raise SystemExit (e.g. a node that finished its job); its
    code is returned. Bad input (Co3sopError) or a file problem (OSError)
    prints `<prog>: error: <message>` and returns 2, never a traceback.
    `events`: rclpy's EventsExecutor, which takes each message as an event
    where the single-threaded executor rebuilds its wait set (the recorder:
    30 % less CPU a frame; BENCHMARKS.md, "The executor that takes the
    messages"), for a node that takes many messages a frame and whose
    callbacks never raise by design (it logs a raising callback as fatal,
    with its stack).
    A fatal signal (a crash in native code: DDS, PyTorch, a compiled kernel)
    prints every thread's Python stack to standard error before the process
    dies of it, so the node's log says where.
    """
    if not faulthandler.is_enabled():
        faulthandler.enable(all_threads=True)
    try:
        return _spin(make_node, args, events)
    except (Co3sopError, OSError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2


def _spin(make_node: Callable[[], Node], args: list[str] | None, events: bool) -> int:
    configure_environment()
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = make_node()
        if events:
            executor = EventsExecutor(context=node.context)
            executor.add_node(node)
            while node.context.ok():  # its spin() outlives a shutdown by a signal (rclpy 7.1): step, then check
                executor.spin_once(timeout_sec=0.2)
        else:
            rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except SystemExit as done:
        code = int(done.code or 0)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code
