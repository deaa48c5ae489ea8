#!/usr/bin/env bash
# The node graph on a GPU (BENCHMARKS.md, "The node graph on a GPU"): on a machine whose Python 3.12 holds a CUDA
# build of PyTorch and that reaches no registry, from a bundle packed elsewhere (ros2_ws/offline_bundle.sh pack):
#
#   ros2_ws/benchmarks/gpu_graph.sh BUNDLE.tar.xz TARGET_PYTHON LOGS
#
# Unpacks the bundle, runs the GPU graph tests (every node's model on CUDA against the CPU's float32 reference)
# while the demo's 100-frame scenario is generated on the CPU, then sweeps the play rate of the demo graph (player,
# 3 vehicles, ego, recorder; `--device cuda`, precision auto) for tiny-lidar, small and the untrained paper preset.
# Each step's output goes to LOGS.
set -uo pipefail
# shellcheck source=ros2_ws/benchmarks/gpu_setup.sh
. "$(dirname "${BASH_SOURCE[0]}")/gpu_setup.sh" "$@"
python -c 'from co3sop_nodes.ros.demo import DemoOptions, ensure_scenario; ensure_scenario(DemoOptions(frames=100))' \
  >"$logs/generate.log" 2>&1 &
generating=$!
timeout 240 python -m pytest -q -s -c src/co3sop_nodes/setup.cfg --rootdir tests -p no:cacheprovider \
  tests/integration/test_graph.py -k cuda 2>&1 | tee "$logs/pytest_cuda.log"
wait "$generating" || { tail -n 5 "$logs/generate.log"; exit 1; }
sweep() {
  local name="$1"; shift
  timeout 240 python ros2_ws/benchmarks/bench_graph.py --device cuda --frames 100 --out "results/gpu/$name" "$@" 2>&1 \
    | tee "$logs/graph-$name.log"
}
sweep tiny-lidar --model tiny-lidar --rates 1 2
sweep small --model small --rates 1 2
sweep paper --untrained paper --rates 0.25 0.5  # three vehicle halves share the GPU: below 1.0
