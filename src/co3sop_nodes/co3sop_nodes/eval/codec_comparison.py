"""Learned wire codes against the transform codec at the same bytes: the table of a comparison's runs
(ros2_ws/benchmarks/bench_learned_codec.py measures them; `report` shows the `test` ones)."""

from __future__ import annotations

UNBOUNDED = 2**31 - 1  # the largest codec.max_bytes: every requested voxel fits


def label(run: dict) -> str:
    """A run's codec as a reader reads it (a request with no budget: every voxel the ego asked for)."""
    return run["codec"].replace(f"request{UNBOUNDED // 1024}KB", "request-all")


def comparison_table(measured: dict) -> list[str]:
    """Markdown lines: the comparison's title and reference, then one row per system and codec (bytes, mIoU 1..23,
    its model alone, the gain kept against the reference's alone and its own gain kept, each with its 95 %
    interval)."""

    def interval(r: dict) -> str:
        return f"{100 * r['ratio']:.0f} [{100 * r['ci95'][0]:.0f}, {100 * r['ci95'][1]:.0f}]"

    def limit(r: dict) -> str:
        return "none" if r["max_bytes"] in (0, UNBOUNDED) else f"{r['max_bytes']:,}"

    return [
        f"{measured['title']}; reference `{measured['reference']}`",
        "",
        "| system | codec | codec.max_bytes | bytes per neighbour-frame | mIoU 1..23 | its model alone | "
        "gain kept vs the reference alone (%) [95 % interval] | its own gain kept (%) [95 % interval] |",
        "|---|---|---:|---:|---:|---:|---|---|",
        *(
            f"| {r['system']} | {label(r)} | {limit(r)} | {r['bytes']:,.0f} | {100 * r['miou']:.2f} | "
            f"{100 * r['alone_miou']:.2f} | {interval(r['gain_kept'])} | {interval(r['own_gain_kept'])} |"
            for r in measured["runs"]
        ),
    ]
