"""ros2_ws/run_protocol.sh, the documented command behind results.md, on a dataset small enough for seconds a step:
each kind of preset gets its stages and its evaluations, and a second run finds them done."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from executables import executable

ROOT = Path(__file__).resolve().parents[2]
PRESETS = {  # preset: (evidence the protocol must leave, evidence it must not)
    "tiny-lidar": (
        ["tiny-lidar_51.2m_collaboration.json", "tiny-lidar_51.2m_inputs.json", "ego-stage/evaluation.json"],
        ["alone"],
    ),
    "tiny-sscnet": (
        ["alone/evaluation.json", "tiny-sscnet_51.2m_inputs.json"],
        ["tiny-sscnet_51.2m_collaboration.json"],
    ),
    "tiny-sscnet-early": (
        ["tiny-sscnet-early_51.2m_collaboration.json", "tiny-sscnet-early_51.2m_inputs.json"],
        ["ego-stage", "alone"],
    ),
}


def test_the_protocol_trains_and_scores_each_kind_of_preset_and_resumes(tmp_path):
    data = tmp_path / "data"
    made = subprocess.run(
        [
            executable("generate"),
            "--out",
            str(data),
            "--splits",
            "train=1",
            "test=2",
            "--frames",
            "2",
            "--cavs",
            "2",
            "--image-size",
            "64x48",
            "--lidar-steps",
            "128",
            "--vehicles",
            "8",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert made.returncode == 0, made.stderr
    env = {
        **os.environ,
        "DATA": str(data),
        "RUNS": str(tmp_path / "runs"),
        "RESULTS": str(tmp_path / "results"),
        "PRESETS": " ".join(PRESETS),
        "RANGES": "51.2m",
        "SEEDS": "1",
        "EGO_STEPS": "1",
        "FUSION_STEPS": "1",
        "FIRST_SEED_ABLATIONS": "inputs",
        "DEVICE": "cpu",
    }
    protocol = [str(ROOT / "ros2_ws" / "run_protocol.sh"), "train", "evaluate"]
    done = subprocess.run(protocol, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    for name, (present, absent) in PRESETS.items():
        run = tmp_path / "results" / f"{name}-51.2m-s1"
        assert all((run / p).is_file() for p in present), sorted(p.name for p in run.rglob("*"))
        assert not any((run / a).exists() for a in absent), sorted(p.name for p in run.rglob("*"))
    assert (
        tmp_path / "runs" / "tiny-lidar-51.2m-s1-ego" / "model.pt"
    ).is_file()  # two stages for the collaborative model only
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == [
        "tiny-lidar-51.2m-s1",
        "tiny-lidar-51.2m-s1-ego",
        "tiny-sscnet-51.2m-s1",
        "tiny-sscnet-early-51.2m-s1",
    ]
    written = {p: p.stat().st_mtime_ns for p in tmp_path.glob("r*/**/*") if p.is_file()}
    again = subprocess.run(protocol, env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert {
        p: p.stat().st_mtime_ns for p in tmp_path.glob("r*/**/*") if p.is_file()
    } == written  # nothing trained or scored twice
    assert again.stdout.count(": trained") == 4 and "tiny-lidar-51.2m-s1: collaboration evaluated" in again.stdout
