"""What every command-line tool shares: clear errors instead of tracebacks."""

from __future__ import annotations

import sys
from collections.abc import Callable

from co3sop_nodes.common.allocation import keep_freed_memory
from co3sop_nodes.common.errors import Co3sopError


def run(main: Callable[[list[str] | None], int]) -> Callable[[], None]:
    """Wraps a tool's main: a Co3sopError prints `<tool>: error: <message>` and exits 2."""

    def entry() -> None:
        prog = sys.argv[0].rsplit("/", 1)[-1]
        keep_freed_memory()  # training and evaluation repeat the same allocations every sample
        try:
            code = main(None)
        except (Co3sopError, OSError) as exc:  # bad input or a file system problem: a message, not a traceback
            print(f"{prog}: error: {exc}", file=sys.stderr)
            code = 2
        except KeyboardInterrupt:
            print(f"{prog}: interrupted", file=sys.stderr)
            code = 130
        sys.exit(code)

    return entry
