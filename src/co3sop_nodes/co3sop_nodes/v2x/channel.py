"""An emulated V2X channel on one machine (ROS-free): network namespaces joined through a bridge.

Each CAV (the ego with its own encoder and recorder, each neighbour's vehicle
node) runs in its own network namespace, linked by a veth pair to a bridge in a
hub namespace; the machine's own namespace (the simulator: player, launcher)
joins the bridge unshaped. A CAV's radio is its namespace's transmit side:
rate-limited by a token bucket (tc `tbf`) and, where a loss rate is given,
thinned by an nftables rule on its device's egress dropping that share of its
packets at random (`numgen random`). With a shared medium, every CAV's transmissions also pass through one
queue for all of them together, as on one radio channel: what enters the hub's bridge from any CAV for the radio
is redirected to one device (an `ifb`) whose token bucket carries it at the medium's rate, once per transmission
(a multicast frame the bridge then copies to every CAV crossed the medium once). CAVs transmitting at once wait
for each other, as a radio's senders wait for a free channel (an ideal MAC: no collisions, no back-off slots);
what waits longer than the medium's queue is dropped. UDP to `priority_ports` crosses the medium before anything
else waiting, as 802.11p's access categories send short control frames first (the demo puts the egos' request maps
there).
Every byte between CAVs then crosses a shaped link, over UDP:
the processes use a Fast DDS profile without shared memory (which would bypass
the link, /dev/shm being shared by all namespaces). The radio carries what a CAV
sends to the other CAVs (their addresses, or multicast); what it sends to the
machine's side (the recorder, the launcher's diagnostics: each car's own log in
a real deployment; any address of the machine a participant announces) leaves
unshaped, is never lost, and the shared medium does not count it.

Latency: this kernel has no `netem`, so no fixed propagation delay is added
(at V2X distances it is about 1 us per 300 m); the delay that matters, the time
a burst of feature fragments waits for the link, comes from the token bucket
itself (a queue of at most `queue_ms` at the link rate, then tail drop).

Clean-up: namespaces carry the launcher's pid in their names. `Channel` removes
them on exit (including exceptions and the SIGINT/SIGTERM the launcher turns
into exceptions), a detached reaper process removes them if the launcher dies
without unwinding (SIGKILL), and `remove_stale` removes those of any launcher
that is no longer alive.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass

from co3sop_nodes.common.errors import Co3sopError

PREFIX = "co3sop-"  # every namespace this module makes: co3sop-<launcher pid>-<member>
# DDS discovery (RTPS metatraffic: the ports of the standard mapping, 7400 + 250 domain + 2 participant + 10 for
# unicast, 7400 + 250 domain for multicast, are even; user data goes to odd ones) is off the radio: its timers run on
# the wall clock, which a slowed play rate does not slow, so on a link scaled by the play rate it would take that
# many times its real share; every car joining at once would otherwise hold the first frames
DISCOVERY_U32 = ("match", "ip", "protocol", "17", "0xff", "match", "ip", "dport", "0", "0x1")
_NAME = re.compile(rf"^{PREFIX}(\d+)-")
# an HTB class that never holds a packet back: HTB only sorts; where there is a pace, a token bucket sets it
UNBOUNDED_CLASS = ("htb", "rate", "10gbit", "burst", "1mb", "cburst", "1mb", "quantum", "60000")


class ChannelError(Co3sopError):
    pass


@dataclass(frozen=True)
class Link:
    """A CAV's radio: what it can transmit."""

    rate_mbit: float  # link rate, Mbit/s
    loss: float = 0.0  # share of transmitted packets dropped, 0..1
    queue_ms: float = 200.0  # the longest a packet waits in the token bucket's queue before it is dropped

    def __post_init__(self):
        if not self.rate_mbit > 0:
            raise ChannelError(f"link rate must be positive, got {self.rate_mbit} Mbit/s")
        if not 0 <= self.loss < 1:
            raise ChannelError(f"loss must be in [0, 1), got {self.loss}")


def missing_tools() -> list[str]:
    """What this machine lacks to build a channel (empty when it can): root, iproute2, tc, nftables."""
    missing = [] if os.geteuid() == 0 else ["root (network namespaces need CAP_NET_ADMIN)"]
    for tool, package in (("ip", "iproute2"), ("tc", "iproute2"), ("nft", "nftables")):
        if shutil.which(tool) is None:
            missing.append(f"{tool} (Debian package {package})")
    return missing


def _run(*argv: str, ns: str | None = None, check: bool = True) -> subprocess.CompletedProcess:
    cmd = ["ip", "netns", "exec", ns, *argv] if ns else list(argv)
    done = subprocess.run(cmd, capture_output=True, text=True)
    if check and done.returncode != 0:
        raise ChannelError(f"`{' '.join(cmd)}` failed: {done.stderr.strip() or done.stdout.strip()}")
    return done


def namespaces() -> list[str]:
    """Every network namespace of this machine, by name."""
    out = _run("ip", "netns", "list", check=False).stdout
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _pids(ns: str) -> list[int]:
    return [int(p) for p in _run("ip", "netns", "pids", ns, check=False).stdout.split()]


def remove(names: list[str], grace: float = 3.0) -> None:
    """Stop what still runs inside the namespaces (SIGTERM, then SIGKILL after `grace` s), then delete them (their
    veth ends, the bridge and the machine's end of the link go with them)."""
    running = [pid for name in names for pid in _pids(name)]
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in running:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
        deadline = time.monotonic() + grace
        while (running := [pid for pid in running if _alive(pid)]) and time.monotonic() < deadline:
            time.sleep(0.1)
        if not running:
            break
    for name in names:
        _run("ip", "netns", "delete", name, check=False)


def host_link(pid: int) -> str:
    """The machine's end of launcher `pid`'s channel (a veth whose peer sits on the hub's bridge)."""
    return f"c3s{pid}"[:15]


def remove_launcher(pid: int) -> None:
    """Everything launcher `pid`'s channel made: its namespaces (and what runs in them), its link on the machine
    (deleted at once: a namespace's devices otherwise go only when the kernel gets round to it)."""
    _run("ip", "link", "delete", host_link(pid), check=False)
    remove([n for n in namespaces() if n.startswith(f"{PREFIX}{pid}-")])


def remove_stale() -> list[int]:
    """Remove the channels of launchers that are no longer running; their pids."""
    stale = sorted({int(m.group(1)) for n in namespaces() if (m := _NAME.match(n)) and not _alive(int(m.group(1)))})
    for pid in stale:
        remove_launcher(pid)
    return stale


class Channel:
    """Namespaces for `links` (member name -> its Link) joined through a bridge; the machine's namespace joins
    unshaped. Use as a context manager; `wrap(member, argv)` runs a command inside a member."""

    def __init__(
        self,
        links: dict[str, Link],
        subnet: str | None = None,
        shared: Link | None = None,
        priority_ports: tuple[int, ...] = (),
    ):
        """`shared`: one medium all members transmit on together (its rate; its loss is each member's own);
        `priority_ports`: UDP destination ports whose packets it carries first."""
        if priority_ports and shared is None:
            raise ChannelError("priority_ports order a shared medium's queue: give the channel one")
        if not links:
            raise ChannelError("a channel needs at least one member")
        if missing := missing_tools():
            raise ChannelError(
                "the emulated V2X channel needs "
                + ", ".join(missing)
                + ("; install with: apt-get install nftables iproute2" if os.geteuid() == 0 else "")
            )
        for name in links:
            if not re.fullmatch(r"[a-z0-9]{1,12}", name):
                raise ChannelError(f"member name {name!r}: 1-12 lower-case letters or digits")
        self.links, self.shared, self.priority_ports = dict(links), shared, tuple(priority_ports)
        self.pid = os.getpid()
        self.hub = f"{PREFIX}{self.pid}-hub"
        # a /24 per launcher, so that channels of concurrent launchers never share addresses
        self.subnet = ipaddress.ip_network(subnet or f"10.{200 + self.pid % 50}.{(self.pid // 50) % 256}.0/24")
        hosts = self.subnet.hosts()
        self.host_address = next(hosts)  # the machine's end
        self.addresses = {name: next(hosts) for name in self.links}
        self._made: list[str] = []
        self.started = 0.0  # time.monotonic() when the channel was built
        self._reaper: subprocess.Popen | None = None

    def namespace(self, member: str) -> str:
        return f"{PREFIX}{self.pid}-{member}"

    def wrap(self, member: str, argv: list[str]) -> list[str]:
        """argv run inside `member`'s namespace."""
        return ["ip", "netns", "exec", self.namespace(member), *argv]

    def __enter__(self) -> Channel:
        remove_stale()
        self.started = time.monotonic()
        try:
            self._build()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _build(self) -> None:
        self._add_namespace(self.hub)
        # the reaper: removes this launcher's namespaces if it dies without unwinding (SIGKILL)
        self._reaper = subprocess.Popen(
            [sys.executable, "-m", "co3sop_nodes.v2x.channel", "--reap", str(self.pid)],
            start_new_session=True,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        prefix = self.subnet.prefixlen
        _run("ip", "link", "add", "br0", "type", "bridge", ns=self.hub)
        _run("ip", "link", "set", "br0", "up", ns=self.hub)
        # the machine's end: a veth whose name carries the pid (root names are shared by every launcher)
        host_if = host_link(self.pid)
        _run("ip", "link", "add", host_if, "type", "veth", "peer", "name", "host", "netns", self.hub)
        self._plug(self.hub, "host")
        _run("ip", "addr", "add", f"{self.host_address}/{prefix}", "dev", host_if)
        _run("ip", "link", "set", host_if, "up")
        for member, link in self.links.items():
            ns = self.namespace(member)
            self._add_namespace(ns)
            _run(
                "ip",
                "link",
                "add",
                "eth0",
                "netns",
                ns,
                "type",
                "veth",
                "peer",
                "name",
                member,
                "netns",
                self.hub,
                ns=self.hub,
            )
            self._plug(self.hub, member)
            _run("ip", "link", "set", "lo", "up", ns=ns)
            _run("ip", "addr", "add", f"{self.addresses[member]}/{prefix}", "dev", "eth0", ns=ns)
            _run("ip", "link", "set", "eth0", "up", ns=ns)
            _run("ip", "route", "add", "default", "dev", "eth0", ns=ns)  # multicast discovery needs a route
            self._shape(ns, link, self.host_address, self.subnet)
        if self.shared is not None:
            self._share(self.shared)

    def _add_namespace(self, ns: str) -> None:
        _run("ip", "netns", "add", ns)
        self._made.append(ns)

    @staticmethod
    def _plug(hub: str, port: str) -> None:
        _run("ip", "link", "set", port, "master", "br0", ns=hub)
        _run("ip", "link", "set", port, "up", ns=hub)

    @staticmethod
    def _shape(ns: str, link: Link, host, subnet) -> None:
        """The radio on eth0's transmit side: an HTB tree whose class for the other CAVs (`subnet` but the machine's
        end `host`, and multicast) leads to the link's token bucket; the rest (the machine's side, discovery) goes
        unlimited."""
        tc = ("tc", "qdisc", "add", "dev", "eth0")
        _run(*tc, "root", "handle", "1:", "htb", "default", "20", ns=ns)
        for cls in ("1:10", "1:20"):
            _run("tc", "class", "add", "dev", "eth0", "parent", "1:", "classid", cls, *UNBOUNDED_CLASS, ns=ns)
        _run(*tc, "parent", "1:10", *_token_bucket(link), ns=ns)
        for prio, (match, action) in enumerate(_radio_filters(host, subnet, ("flowid", "1:20"), ("flowid", "1:10")), 1):
            _run(
                *("tc", "filter", "add", "dev", "eth0", "parent", "1:", "protocol", "ip", "prio", str(prio), "u32"),
                *match,
                *action,
                ns=ns,
            )
        if link.loss > 0:
            per_million = round(link.loss * 1_000_000)
            # on the device's egress, as a radio loses frames: the sender is not told (an output-hook drop would
            # fail its sendto with EPERM)
            rules = (
                'table netdev v2x {\n chain out {\n  type filter hook egress device "eth0" priority 0; policy accept;\n'
                f"{_on_radio(host, subnet)} numgen random mod 1000000 < {per_million} counter drop\n }}\n}}\n"
            )
            _nft(ns, rules)

    def _share(self, medium: Link) -> None:
        """One queue for every member's transmissions: what enters the hub from any member's port for the radio is
        redirected (tc ingress, once per frame, before the bridge copies a multicast one to each port; the machine's
        side and discovery pass) to one device, `air`, whose token bucket sends it on at the medium's rate and
        returns it to the bridge. Members transmitting together wait for each other, as a radio's senders wait for a
        free channel, up to the medium's `queue_ms`; beyond that the medium drops (tail drop, counted)."""
        _run("ip", "link", "add", "air", "type", "ifb", ns=self.hub)
        _run("ip", "link", "set", "air", "up", ns=self.hub)
        _run("tc", "qdisc", "add", "dev", "air", "root", "handle", "1:", *_token_bucket(medium), ns=self.hub)
        if self.priority_ports:
            self._prioritise(medium)
        onto_air = ("action", "mirred", "egress", "redirect", "dev", "air")
        for port in self.links:
            _run("tc", "qdisc", "add", "dev", port, "handle", "ffff:", "ingress", ns=self.hub)
            for prio, (match, action) in enumerate(
                _radio_filters(self.host_address, self.subnet, ("flowid", "ffff:1"), onto_air), 1
            ):
                _run(
                    *("tc", "filter", "add", "dev", port, "parent", "ffff:", "protocol", "ip", "prio", str(prio)),
                    "u32",
                    *match,
                    *action,
                    ns=self.hub,
                )

    def _prioritise(self, medium: Link) -> None:
        """The medium's queue as two, served in order (an HTB of unbounded classes under the token bucket: the
        bucket sets the pace, HTB hands it the first class's packets first): `priority_ports`, then the rest; each
        holds what the medium carries in its `queue_ms`, beyond which it drops."""
        tc = ("tc", "class", "add", "dev", "air", "parent", "10:")
        _run("tc", "qdisc", "add", "dev", "air", "parent", "1:1", "handle", "10:", "htb", "default", "20", ns=self.hub)
        limit = str(int(medium.rate_mbit * 1e6 / 8 * medium.queue_ms / 1000) + _token_bucket_burst(medium))
        for band, prio in (("10", "0"), ("20", "1")):
            _run(*tc, "classid", f"10:{band}", *UNBOUNDED_CLASS, "prio", prio, ns=self.hub)
            _run("tc", "qdisc", "add", "dev", "air", "parent", f"10:{band}", "bfifo", "limit", limit, ns=self.hub)
        for port in self.priority_ports:
            udp = ("match", "ip", "protocol", "17", "0xff", "match", "ip", "dport", str(port), "0xffff")
            _run(
                *("tc", "filter", "add", "dev", "air", "parent", "10:", "protocol", "ip", "prio", "1", "u32"),
                *(*udp, "flowid", "10:10"),
                ns=self.hub,
            )

    def dropped_by_medium(self) -> int:
        """Packets the shared medium dropped so far (more than its queue held: the members together past its rate)."""
        return _qdisc_stat(self.hub, "air", "dropped")

    def carried_by_medium(self) -> int:
        """Bytes the shared medium carried so far (each transmission once)."""
        return _qdisc_stat(self.hub, "air", "bytes")

    def medium_load(self) -> float:
        """The share of what the shared medium could have carried since the channel was built that it carried."""
        if self.shared is None:
            raise ChannelError("this channel has no shared medium")
        seconds = time.monotonic() - self.started
        return self.carried_by_medium() / (self.shared.rate_mbit * 1e6 / 8 * seconds)

    def dropped(self, member: str) -> int:
        """Packets the loss rule dropped on `member`'s transmit side so far."""
        return _counted(self.namespace(member), "netdev", "v2x", "out")

    def close(self) -> None:
        """Remove every namespace and link this channel made (idempotent)."""
        if self._made:
            _run("ip", "link", "delete", host_link(self.pid), check=False)
        remove(list(reversed(self._made)))
        self._made.clear()
        if self._reaper is not None and self._reaper.poll() is None:
            self._reaper.terminate()
            self._reaper.wait(5)
        self._reaper = None


def _on_radio(host, subnet) -> str:
    """nftables rules of a chain whose last rule's matches follow: DDS discovery passes, and the last rule matches what
    goes over the radio: to another CAV (an address of `subnet` but the machine's end `host`) or to a multicast
    group."""
    return f"  udp dport & 1 == 0 accept\n  ip daddr != {host} ip daddr {{ {subnet}, 224.0.0.0/4 }}"


def _token_bucket_burst(link: Link) -> int:
    """A bucket of 10 ms of the rate (the kernel refills it per timer tick) and at least a few full-size packets."""
    return max(4096, int(link.rate_mbit * 1e6 / 8 * 0.01))


def _token_bucket(link: Link) -> tuple[str, ...]:
    """tc's tbf arguments for `link`: its rate, a queue of its `queue_ms` and its bucket."""
    burst = str(_token_bucket_burst(link))
    return ("tbf", "rate", f"{link.rate_mbit * 1000:.0f}kbit", "burst", burst, "latency", f"{link.queue_ms:.0f}ms")


def _radio_filters(host, subnet, harness: tuple[str, ...], radio: tuple[str, ...]) -> list[tuple[tuple, tuple]]:
    """tc u32 (match, action) pairs in priority order: discovery and the machine's end `host` take `harness`, the
    other CAVs (`subnet`) and multicast groups `radio`."""
    return [
        (DISCOVERY_U32, harness),
        (("match", "ip", "dst", f"{host}/32"), harness),
        (("match", "ip", "dst", str(subnet)), radio),
        (("match", "ip", "dst", "224.0.0.0/4"), radio),
    ]


def _qdisc_stat(ns: str, device: str, field: str) -> int:
    """A counter of `device`'s root qdisc ("bytes", "pkt", "dropped"; 0 where there is none)."""
    done = _run("tc", "-s", "qdisc", "show", "dev", device, ns=ns, check=False)
    m = re.search(r"Sent (\d+) bytes (\d+) pkt \(dropped (\d+)", done.stdout)
    return int(m.group(("bytes", "pkt", "dropped").index(field) + 1)) if m else 0


def _nft(ns: str, rules: str) -> None:
    done = subprocess.run(["ip", "netns", "exec", ns, "nft", "-f", "-"], input=rules, capture_output=True, text=True)
    if done.returncode != 0:
        raise ChannelError(f"nftables rules in {ns} failed: {done.stderr.strip()}")


def _counted(ns: str, family: str, table: str, chain: str) -> int:
    """Packets the counter of an nftables chain's rule has counted (0 where there is none)."""
    done = _run("nft", "list", "chain", family, table, chain, ns=ns, check=False)
    m = re.search(r"counter packets (\d+)", done.stdout)
    return int(m.group(1)) if m else 0


def _reap(pid: int) -> None:
    """Wait for launcher `pid` to end, then remove its namespaces."""
    while _alive(pid):
        time.sleep(0.5)
    remove_launcher(pid)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--reap":
        _reap(int(sys.argv[2]))
