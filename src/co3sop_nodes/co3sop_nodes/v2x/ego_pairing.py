"""The ego's frames paired with its neighbours' by stamp, and how long each waits for them (ROS-free; the
ego node feeds it and fuses what it hands out).

Each of the ego's own frames waits, at most `max_wait` s after it arrived, for
every live neighbour whose frame within `tolerance` of its stamp has not come
yet (a neighbour that already sent a newer frame has skipped it). A neighbour
is live while it has a publisher and has been heard from within
`neighbour_timeout`; silence is counted from the later of its discovery and
the ego's first own frame, so sensors that start long after the graph do not
make every neighbour look silent, and a publisher that never sends stops
costing max_wait once the ego's frames have flowed for neighbour_timeout.
The ego stays current: of the own frames ready to fuse (nothing left to wait
for), the newest is handed out and the older ones are skipped (counted), so a
graph fed faster than it fuses keeps its latency bounded instead of queueing.
An own frame stops waiting once a newer own frame has come (it waited a whole
frame period), and at most `max_pending` wait. A neighbour whose frame of that
stamp never came (it skipped it, being slower than its sensors, or it is late)
is fused with its nearest frame within `max_age` of the stamp instead, placed
by its own pose at its own stamp (`nearest`). With `stay_current` off, every
own frame is fused, oldest first, each waiting up to max_wait (a recording of
every frame of a bag played faster than the ego fuses). A neighbour's frame
older than the last one fused by more than that can no longer pair and is
stale. Sources are keyed by anything hashable and ordered (the ego node keys
them by topic, as it knows a neighbour's topic before its vehicle id).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")
K = TypeVar("K")  # a source's key: vehicle id or topic


@dataclass(frozen=True)
class PairingConfig:
    tolerance_ns: int = 50_000_000
    max_wait_s: float = 2.0
    neighbour_timeout_ns: int = 5_000_000_000
    history: int = 8  # frames kept per agent
    max_pending: int = 3  # own frames waiting at once; one more ends the oldest's wait
    stay_current: bool = True  # the newest ready own frame, older ones skipped; False: every one, oldest first
    max_age_ns: int = (
        500_000_000  # a neighbour's frame this far from the ego's stamp is fused when none within tolerance is
    )

    @property
    def reach_ns(self) -> int:
        """How far from an ego frame's stamp a neighbour's frame may still be fused."""
        return max(self.tolerance_ns, self.max_age_ns)


class Pairing(Generic[K, T]):
    def __init__(self, ego: K, cfg: PairingConfig = PairingConfig()):
        self.ego, self.cfg = ego, cfg
        self._frames: dict[K, deque[tuple[int, T]]] = {}  # agent -> (stamp, item), arrival order
        self._last_heard: dict[K, int] = {}  # agent -> wall ns of its last frame, or of its discovery
        self._pending: deque[tuple[int, float]] = deque()  # own frames to fuse: (stamp, monotonic deadline)
        self._first_own_ns: int | None = None
        self.last_fused = -1
        self.skipped = 0  # own frames passed over for a newer one

    def discovered(self, agent: K, wall_ns: int) -> None:
        """A neighbour's publisher appeared: it is waited for from now on."""
        self._last_heard.setdefault(agent, wall_ns)

    def forget(self, agent: K) -> None:
        """`agent` is gone (its id moved elsewhere): its frames are dropped and it is no longer waited for."""
        self._frames.pop(agent, None)
        self._last_heard.pop(agent, None)

    def stale(self, stamp: int) -> bool:
        """Too old to pair with any frame still to fuse."""
        return stamp < self.last_fused - self.cfg.reach_ns

    def repeated(self, stamp: int) -> bool:
        """An own frame with this stamp was fused already (or one no newer), or waits to be: fusing it again would
        publish the same frame twice."""
        return stamp <= self.last_fused or any(s == stamp for s, _ in self._pending)

    def add(self, agent: K, stamp: int, item: T, wall_ns: int, monotonic: float) -> None:
        """An accepted frame of `agent` (the ego's own frames are then waiting to be fused)."""
        self._frames.setdefault(agent, deque(maxlen=self.cfg.history)).append((stamp, item))
        self._last_heard[agent] = wall_ns
        if agent == self.ego:
            if self._first_own_ns is None:
                self._first_own_ns = wall_ns
            self._pending.append((stamp, monotonic + self.cfg.max_wait_s))
            for i in range(len(self._pending) - self.cfg.max_pending):  # the oldest beyond the bound wait no more
                self._pending[i] = (self._pending[i][0], min(self._pending[i][1], monotonic))

    def match(self, agent: K, stamp: int) -> T | None:
        """The agent's frame nearest `stamp`, if within the tolerance."""
        best = min(self._frames.get(agent, ()), key=lambda f: abs(f[0] - stamp), default=None)
        return best[1] if best is not None and abs(best[0] - stamp) <= self.cfg.tolerance_ns else None

    def nearest(self, agent: K, stamp: int) -> T | None:
        """The agent's frame nearest `stamp`, if within max_age (or the tolerance, if larger): what is fused when the
        frame of that stamp never came."""
        best = min(self._frames.get(agent, ()), key=lambda f: abs(f[0] - stamp), default=None)
        return best[1] if best is not None and abs(best[0] - stamp) <= self.cfg.reach_ns else None

    def heard(self) -> list[K]:
        """Neighbours that sent at least one accepted frame, by id."""
        return sorted(a for a in self._frames if a != self.ego)

    def live(self, wall_ns: int, has_publisher: Callable[[K], bool]) -> list[K]:
        """Neighbours still waited for: with a publisher, heard from within neighbour_timeout."""
        start = wall_ns if self._first_own_ns is None else self._first_own_ns
        return [
            a
            for a, heard in self._last_heard.items()
            if a != self.ego and wall_ns - max(heard, start) < self.cfg.neighbour_timeout_ns and has_publisher(a)
        ]

    def next_due(self, wall_ns: int, monotonic: float, has_publisher: Callable[[K], bool]) -> int | None:
        """The stamp of the newest own frame ready to fuse now, taken off the queue with every own frame not newer
        than it (those are skipped, counted in `skipped`); None while every frame still waits."""
        live = self.live(wall_ns, has_publisher) if self._pending else []

        newest = max((s for s, _ in self._pending), default=None)

        def ready(stamp: int, deadline: float) -> bool:
            if monotonic >= deadline or (self.cfg.stay_current and stamp < newest):
                return True
            return not any(
                self.match(a, stamp) is None and all(s < stamp for s, _ in self._frames.get(a, ())) for a in live
            )

        if not self.cfg.stay_current:
            chosen = 0 if self._pending and ready(*self._pending[0]) else None
        else:
            chosen = max(
                (i for i, f in enumerate(self._pending) if ready(*f)),
                key=lambda i: (self._pending[i][0], i),
                default=None,
            )
        if chosen is None:
            return None
        stamp = self._pending[chosen][0]
        kept = deque(
            f for i, f in enumerate(self._pending) if i != chosen and (f[0] > stamp or not self.cfg.stay_current)
        )
        self.skipped += len(self._pending) - 1 - len(kept)
        self._pending = kept
        return stamp

    def fused(self, stamp: int) -> None:
        """`stamp` was fused: frames that can no longer pair with a later one are forgotten."""
        self.last_fused = max(self.last_fused, stamp)
        for frames in self._frames.values():
            while frames and frames[0][0] < stamp - self.cfg.reach_ns:
                frames.popleft()
