"""`recover`: make an MCAP recording readable again after the recorder crashed.

    ros2 run co3sop_nodes recover results/demo/demo.mcap [--out fixed.mcap]

Copies every complete message (all but at most the chunk in progress at the
crash) into a complete, indexed MCAP, in place by default (atomically).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from co3sop_nodes.cli.common import run
from co3sop_nodes.data.recording import recover


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="recover", description=__doc__.split("\n\n")[1])
    parser.add_argument("recording", type=Path)
    parser.add_argument("--out", type=Path, help="write here instead of replacing the recording")
    opts = parser.parse_args(args)
    result = recover(opts.recording, opts.out)
    state = "was complete" if result.complete else f"was damaged ({result.problem})"
    print(f"recover: {opts.recording} {state}; {result.messages} messages kept in {opts.out or opts.recording}")
    for topic, n in sorted(result.topics.items()):
        print(f"  {topic}: {n}")
    return 0


entry = run(main)
