"""A vehicle's sensor messages grouped into frames by header stamp (ROS-free; the vehicle node feeds it).

Topics carry no order between them: a frame's images, camera infos, pose and
points arrive interleaved with the next frame's. A frame is complete when every
part is in and `complete(parts)` agrees (the vehicle also needs its cameras'
mounts from /tf_static). Complete frames come out oldest first, each once; a
part older than the last frame out is stale, and a frame that a newer one
overtook, or that is still incomplete when `max_pending` newer frames wait,
is dropped as incomplete.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Drop:
    part: str | None  # the part the message or frame concerns (None: the frame as a whole)
    kind: str  # "stale" | "incomplete"
    reason: str


@dataclass
class Frame:
    stamp: int  # ns
    first_wall_ns: int  # when its first part arrived
    parts: dict[str, object] = field(default_factory=dict)


class FrameAssembly:
    def __init__(
        self,
        parts: Iterable[str],
        max_pending: int = 10,
        complete: Callable[[dict], bool] = lambda parts: True,
        requirement: str = "requirement",
    ):
        self.parts = tuple(parts)
        self.requirement = requirement  # what `complete` checks, for the drop reason
        self.max_pending = max_pending
        self._complete = complete
        self._pending: dict[int, Frame] = {}
        self.last_stamp = -1  # of the last frame out

    def add(self, part: str, stamp: int, msg, wall_ns: int) -> tuple[list[Frame], list[Drop]]:
        """One message; the frames it completes (oldest first) and what it made drop."""
        if part not in self.parts:
            raise ValueError(f"unknown part {part!r} (parts: {', '.join(self.parts)})")
        if stamp <= self.last_stamp:
            return [], [
                Drop(part, "stale", f"stamp {stamp} is not newer than the last encoded frame {self.last_stamp}")
            ]
        self._pending.setdefault(stamp, Frame(stamp, wall_ns)).parts[part] = msg  # a repeat replaces the earlier copy
        ready, drops = self.ready()
        while len(self._pending) > self.max_pending:  # a frame that never completes must not pile up
            old = self._pending.pop(min(self._pending))
            drops.append(self._incomplete(old, f"after {self.max_pending} newer frames"))
        return ready, drops

    def ready(self) -> tuple[list[Frame], list[Drop]]:
        """The frames complete now, oldest first (call again when `complete` may have changed its mind)."""
        out, drops = [], []
        for stamp in sorted(self._pending):
            frame = self._pending[stamp]
            if all(p in frame.parts for p in self.parts) and self._complete(frame.parts):
                del self._pending[stamp]
                out.append(frame)
                self.last_stamp = stamp
        for stamp in [s for s in self._pending if s < self.last_stamp]:  # overtaken: can never come out
            drops.append(
                self._incomplete(self._pending.pop(stamp), f"when the newer frame {self.last_stamp} was complete")
            )
        return out, drops

    def _incomplete(self, frame: Frame, when: str) -> Drop:
        lacking = [p for p in self.parts if p not in frame.parts]
        what = f"no {', '.join(lacking)}" if lacking else f"no {self.requirement}"
        return Drop(lacking[0] if lacking else None, "incomplete", f"frame {frame.stamp} incomplete ({what}) {when}")
