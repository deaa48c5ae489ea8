"""Memory the process keeps: a frame's work with glibc malloc as it is and with the nodes' setting, alternated.

    ros2_ws/benchmarks/bench_allocation.py [--rounds 3] [--repeats 5] [--messages 100]

Run with the workspace environment (`. ros2_ws/env.sh`). Each round runs every measurement twice, in fresh
processes, with `CO3SOP_KEEP_FREED_MEMORY=0` (malloc's defaults) and without (what every node and tool does),
one after the other, since these machines are noisy; the table gives the median over rounds:
1. the shipped tiny-lidar's vehicle half and ego frame (2 neighbours 10 m away, fusion, labels), one thread, CPU
   time, in float32 and in the precision `auto` picks here;
2. the CPU a subscriber spends per 3 MB VoxelFeatures message over DDS (a neighbour's features at the ego),
   sent at 10 Hz by a publisher process, and the same for a 64-byte message (the executor's own cost).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

# one measurement in a fresh process: its result as JSON on the last line of stdout
MODEL = """
import json, sys, time
import numpy as np, torch
from co3sop_nodes.common.allocation import keep_freed_memory
keep_freed_memory()
from co3sop_nodes.inference import pace
from co3sop_nodes.inference.checkpoint import load_model, shipped_checkpoint
from co3sop_nodes.inference.predict import compile_kernels, predict_frame
from co3sop_nodes.model.path import inference_path
torch.set_num_threads(1)
repeats, precision = int(sys.argv[1]), sys.argv[2]
model, _ = load_model(shipped_checkpoint("tiny-lidar.pt"))
model.use(inference_path("cpu", precision))
compile_kernels(model)
def cpu_ms(fn):
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.process_time(); fn(); times.append(time.process_time() - t0)
    return 1e3 * float(np.median(times))
with torch.inference_mode():
    inputs = pace.shaped_inputs(model)
    vehicle = cpu_ms(lambda: model.vehicle(**inputs))
    own = model.vehicle(**inputs)
    others = pace.shaped_neighbours(own)
    ego = cpu_ms(lambda: predict_frame(model, own, np.eye(4), others))
print(json.dumps({"vehicle": vehicle, "ego": ego, "precision": model.path.precision}))
"""

SUBSCRIBER = """
import json, sys, time, rclpy
from co3sop_nodes.common.allocation import keep_freed_memory
keep_freed_memory()
from co3sop_msgs.msg import VoxelFeatures
from rclpy.qos import QoSProfile, ReliabilityPolicy
rclpy.init()
node = rclpy.create_node("bench_allocation_subscriber")
count, start = [0], [0.0]
def on_message(msg):
    if count[0] == 0:
        start[0] = time.process_time()
    count[0] += 1
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
node.create_subscription(VoxelFeatures, "/bench_allocation", on_message, qos)
print("ready", flush=True)
end = time.monotonic() + float(sys.argv[1])
while time.monotonic() < end and count[0] < int(sys.argv[2]):
    rclpy.spin_once(node, timeout_sec=0.05)
print(json.dumps({"messages": count[0], "cpu_ms": 1e3 * (time.process_time() - start[0]) / max(1, count[0] - 1)}))
"""

PUBLISHER = """
import sys, time, rclpy
from co3sop_msgs.msg import VoxelFeatures
from rclpy.qos import QoSProfile, ReliabilityPolicy
rclpy.init()
node = rclpy.create_node("bench_allocation_publisher")
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
pub = node.create_publisher(VoxelFeatures, "/bench_allocation", qos)
msg = VoxelFeatures()
msg.values = bytes(range(256)) * (int(sys.argv[1]) // 256)
while pub.get_subscription_count() == 0:
    time.sleep(0.05)
time.sleep(0.5)
for _ in range(int(sys.argv[2])):
    pub.publish(msg)
    time.sleep(0.1)
time.sleep(1.0)
"""


def _env(keep: bool) -> dict[str, str]:
    return {**os.environ, "CO3SOP_KEEP_FREED_MEMORY": "1" if keep else "0"}


def _run(code: str, args: list[str], keep: bool) -> dict:
    done = subprocess.run(
        [sys.executable, "-c", code, *args], env=_env(keep), capture_output=True, text=True, check=True, timeout=600
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def _subscriber_ms(size: int, messages: int, keep: bool) -> float:
    sub = subprocess.Popen(
        [sys.executable, "-c", SUBSCRIBER, str(messages * 0.1 + 30), str(messages)],
        env=_env(keep),
        stdout=subprocess.PIPE,
        text=True,
    )
    assert sub.stdout.readline().strip() == "ready"
    time.sleep(0.5)
    subprocess.run([sys.executable, "-c", PUBLISHER, str(size), str(messages)], check=True, timeout=600)
    out = json.loads(sub.communicate(timeout=120)[0].strip().splitlines()[-1])
    if out["messages"] < messages:
        raise RuntimeError(f"the subscriber received {out['messages']} of {messages} messages")
    return out["cpu_ms"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--messages", type=int, default=100)
    opts = parser.parse_args()
    rows: dict[str, dict[bool, list[float]]] = {}
    auto = None
    for r in range(opts.rounds):
        for keep in (False, True):
            for precision in ("float32", "auto"):
                out = _run(MODEL, [str(opts.repeats), precision], keep)
                auto = out["precision"] if precision == "auto" else auto
                for stage in ("vehicle", "ego"):
                    name = f"tiny-lidar {'vehicle half' if stage == 'vehicle' else 'ego frame'}, {out['precision']}"
                    rows.setdefault(name, {False: [], True: []})[keep].append(out[stage])
            for label, size in (("3 MB VoxelFeatures", 3 << 20), ("64-byte VoxelFeatures", 64)):
                name = f"subscriber, per {label} at 10 Hz"
                rows.setdefault(name, {False: [], True: []})[keep].append(_subscriber_ms(size, opts.messages, keep))
            print(f"  round {r + 1}, {'kept' if keep else 'malloc defaults'}: done", flush=True)
    print(
        f"### A frame's CPU ms with malloc's defaults and with freed memory kept (median of {opts.rounds} rounds, "
        f"each alternating both; model stages: median of {opts.repeats} frames, one thread; `auto` is {auto} here)"
    )
    print()
    print("| measurement | malloc defaults | memory kept | defaults / kept |")
    print("|---|---:|---:|---:|")
    for name, by in rows.items():
        default, kept = statistics.median(by[False]), statistics.median(by[True])
        print(f"| {name} | {default:.1f} | {kept:.1f} | {default / kept:.2f}x |")


if __name__ == "__main__":
    main()
