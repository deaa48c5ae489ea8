"""Static checks of every Python file: a name removed in one place and still used in another fails here, not in a node at run time."""

from __future__ import annotations

from pathlib import Path

from pyflakes.api import checkPath
from pyflakes.reporter import Reporter

REPO = Path(__file__).resolve().parents[2]
TREES = ("src/co3sop_nodes", "tests", "ros2_ws/benchmarks")


class Collect(Reporter):
    def __init__(self):
        self.found: list[str] = []

    def unexpectedError(self, filename, msg):
        self.found.append(f"{filename}: {msg}")

    def syntaxError(self, filename, msg, lineno, offset, text):
        self.found.append(f"{filename}:{lineno}: {msg}")

    def flake(self, message):
        self.found.append(str(message))


def test_pyflakes_finds_nothing():
    report = Collect()
    files = sorted(p for tree in TREES for p in (REPO / tree).rglob("*.py") if "build" not in p.parts)
    assert files
    for path in files:
        checkPath(str(path), report)
    assert not report.found, "\n".join(report.found)
