"""The learned-code comparison's table, as the benchmark prints it and `report` shows it."""

from __future__ import annotations

import json

from co3sop_nodes.eval.codec_comparison import UNBOUNDED, comparison_table
from co3sop_nodes.eval.report import scan_section, wire_code_section


def run(system, codec, max_bytes, kept, own):
    return {
        "system": system,
        "codec": codec,
        "max_bytes": max_bytes,
        "bytes": 5058.4,
        "miou": 0.4159,
        "alone_miou": 0.4024,
        "gain_kept": {"ratio": kept, "ci95": [kept - 0.1, kept + 0.1]},
        "own_gain_kept": {"ratio": own, "ci95": [own - 0.1, own + 0.1]},
    }


MEASURED = {
    "title": "tiny-lidar 51.2m, test",
    "reference": "runs/control/model.pt",
    "runs": [
        run("transform", "int4-request8KB-pca8-zstd", 8192, 0.55, 0.55),
        run("learned K=4 (x)", f"int4-request{UNBOUNDED // 1024}KB-learned-zstd", UNBOUNDED, 1.15, 0.82),
    ],
}


def test_each_run_is_a_row_with_both_shares_and_a_request_with_no_budget_reads_as_such():
    lines = comparison_table(MEASURED)
    assert lines[0] == "tiny-lidar 51.2m, test; reference `runs/control/model.pt`" and len(lines) == 4 + 2
    assert (
        lines[-2]
        == "| transform | int4-request8KB-pca8-zstd | 8,192 | 5,058 | 41.59 | 40.24 | 55 [45, 65] | 55 [45, 65] |"
    )
    assert lines[-1].startswith("| learned K=4 (x) | int4-request-all-learned-zstd | none |")
    assert lines[-1].endswith("| 115 [105, 125] | 82 [72, 92] |")


def test_the_report_shows_test_comparisons_only(tmp_path):
    assert wire_code_section(tmp_path) == []
    (tmp_path / "codec").mkdir()
    (tmp_path / "codec" / "learned-51.2m-validate.json").write_text(json.dumps({**MEASURED, "title": "validate"}))
    (tmp_path / "codec" / "learned-51.2m-test.json").write_text(json.dumps(MEASURED))
    text = "\n".join(wire_code_section(tmp_path))
    assert "## A code learned for the V2X wire" in text and "tiny-lidar 51.2m, test" in text
    assert "validate" not in text.split("\n\n", 2)[2]


def test_the_report_shows_the_scans_test_comparisons_beside_the_learned_codes(tmp_path):
    (tmp_path / "codec" / "scan-bytes").mkdir(parents=True)
    assert scan_section(tmp_path) == []
    scans = {**MEASURED, "runs": [*MEASURED["runs"], run("scan", "scan7KB-zstd", 7950, 1.0, 1.0)]}
    (tmp_path / "codec" / "scan-51.2m-control-validate.json").write_text(json.dumps({**scans, "title": "validate"}))
    (tmp_path / "codec" / "scan-51.2m-control-test.json").write_text(json.dumps(scans))
    (tmp_path / "codec" / "scan-bytes" / "tiny-lidar-bench-test.json").write_text("[]")  # another kind, elsewhere
    text = "\n".join(scan_section(tmp_path))
    assert text.startswith("## The sender's scan instead of its features") and "validate" not in text
    assert "| scan | scan7KB-zstd | 7,950 | 5,058 | 41.59 | 40.24 | 100 [90, 110] | 100 [90, 110] |" in text
    assert wire_code_section(tmp_path) == []  # the learned codes' section reads its own files only
