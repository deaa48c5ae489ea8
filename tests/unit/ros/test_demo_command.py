"""`demo`'s channel options are checked before anything starts (parsing only: no node, no namespace)."""

from __future__ import annotations

import pytest

from co3sop_nodes.cli.demo import main


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--channel-answer-ms", "5"], "need --channel-rate"),
        (["--channel-shared"], "need --channel-rate"),
        (["--channel-rate", "6", "--channel-answer-ms", "-1"], "--channel-answer-ms -1.0: 0 to 10000"),
    ],
)
def test_channel_options_are_refused_by_name(argv, message, capsys):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2 and message in capsys.readouterr().err
