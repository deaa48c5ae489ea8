"""Progress bars of long jobs (generation, training, evaluation), on stderr so results on stdout stay clean."""

from __future__ import annotations

import sys

from tqdm import tqdm


def progress(total: int, desc: str, unit: str, disable: bool = False) -> tqdm:
    return tqdm(total=total, desc=desc, unit=unit, dynamic_ncols=True, file=sys.stderr, disable=disable)
