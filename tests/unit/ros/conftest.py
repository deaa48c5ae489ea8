"""The node glue's unit tests: a node logger's stand-in, so they need no DDS."""

from __future__ import annotations

import pytest


class Lines:
    """What was logged, by level, as rclpy's logger takes it."""

    def __init__(self):
        self.warnings: list[str] = []
        self.errors: list[str] = []

    def warning(self, text: str) -> None:
        self.warnings.append(text)

    def error(self, text: str) -> None:
        self.errors.append(text)


@pytest.fixture
def logger() -> Lines:
    return Lines()
