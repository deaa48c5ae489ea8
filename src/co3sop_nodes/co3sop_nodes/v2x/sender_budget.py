"""A sender's byte budget on a rate-limited link: the bytes each message may take (ROS-free).

`codec.max_bytes` alone caps every message at that many bytes. With
`codec.burst_bytes` above it, max_bytes becomes the average a sender may spend
per message to one receiver and burst_bytes the most one message may take:
what a message leaves unspent is saved for the next ones, up to burst_bytes.
This is a token bucket, as a link shaper (Linux tc `tbf`, the emulated
channel's) carries a link's average rate with bursts up to its bucket; a
frame that needs more than average can then take what quieter frames left.
As tbf's, the bucket starts full: the first message to a receiver (sent
before any request map from it has arrived, so with no idea of what it
lacks) may take burst_bytes, and any N messages take at most
burst_bytes + (N - 1) x max_bytes together.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from co3sop_nodes.common.errors import CodecError
from co3sop_nodes.v2x.codec import FeatureCodecConfig
from co3sop_nodes.v2x.scan import ScanCodecConfig

# what a budget caps: a feature codec's or a scan codec's messages (each has max_bytes and burst_bytes)
Codec = FeatureCodecConfig | ScanCodecConfig


@dataclass
class ByteBudget:
    """The budget of one sender towards one receiver."""

    rate: int  # bytes per message on average (codec.max_bytes)
    burst: int  # the most one message may take (codec.burst_bytes)
    saved: int | None = None  # bytes earlier messages left unspent, carried over (None: full, burst - rate)

    def __post_init__(self) -> None:
        if self.saved is None:
            self.saved = self.burst - self.rate

    def allowance(self) -> int:
        """The bytes the next message may take."""
        return min(self.burst, self.rate + self.saved)

    def spend(self, used: int) -> None:
        """A message of `used` bytes (at most the allowance) was sent."""
        allowance = self.allowance()
        if not 0 <= used <= allowance:
            raise CodecError(f"a message of {used} bytes overspends its allowance of {allowance}")
        self.saved = allowance - used

    def config(self, cfg: Codec) -> Codec:
        """`cfg` for the next message: its max_bytes the allowance."""
        return replace(cfg, max_bytes=self.allowance())


def budget_for(cfg: Codec) -> ByteBudget | None:
    """A fresh budget where `cfg` averages its max_bytes over messages (burst_bytes set); None where each message is
    capped alone."""
    return ByteBudget(cfg.max_bytes, cfg.burst_bytes) if cfg.burst_bytes else None


class SenderBudgets:
    """A sender's budgets, one per receiver (None: the messages for every receiver, sent before any asked for its
    own): a receiver's own budget starts where the messages for every receiver left it, as it got those too."""

    def __init__(self, cfg: Codec):
        self.cfg = cfg
        self._budgets: dict[int | None, ByteBudget | None] = {}

    def of(self, receiver: int | None) -> ByteBudget | None:
        """The budget towards `receiver`; None where `cfg` caps each message alone."""
        if receiver not in self._budgets:
            shared = self._budgets.get(None)
            self._budgets[receiver] = replace(shared) if shared is not None else budget_for(self.cfg)
        return self._budgets[receiver]

    def config(self, receiver: int | None) -> Codec:
        """`cfg` for the next message to `receiver`: its max_bytes the allowance where the budget is a rate."""
        budget = self.of(receiver)
        return budget.config(self.cfg) if budget else self.cfg

    def spend(self, receiver: int | None, used: int) -> None:
        """A message of `used` bytes went to `receiver`."""
        budget = self.of(receiver)
        if budget:
            budget.spend(used)
