"""A memo of computed outputs whose memory is bounded, so a pass over a dataset of any size fits."""

from __future__ import annotations

from collections.abc import Callable


class BoundedCache(dict):
    """A dict that keeps what it is given while the entries' bytes fit `max_bytes`, then keeps nothing more.

    It never evicts: passes over a dataset in one order (evaluation's ablations, training epochs) then hit on
    every entry it kept, where a least-recently-used cache smaller than the pass would hit on none.
    """

    def __init__(self, max_bytes: int, size: Callable[[object], int]):
        super().__init__()
        self.max_bytes, self.size, self.bytes = max_bytes, size, 0

    def __setitem__(self, key, value) -> None:
        if key in self:
            return
        size = self.size(value)
        if self.bytes + size <= self.max_bytes:
            super().__setitem__(key, value)
            self.bytes += size
