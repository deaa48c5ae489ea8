#!/usr/bin/env bash
# The training data pipeline on a GPU (BENCHMARKS.md, "Streaming data"): on a machine whose Python 3.12 holds a CUDA
# build of PyTorch and that reaches no registry, from a bundle packed elsewhere (ros2_ws/offline_bundle.sh pack):
#
#   ros2_ws/benchmarks/gpu_train.sh BUNDLE.tar.xz TARGET_PYTHON LOGS
#
# Unpacks the bundle, runs the GPU test of the training samples in page-locked memory, generates a set at the
# real dataset's sizes on the machine's cores (the one the CPU figures were measured on), then measures for
# `small` and the untrained `paper` preset the samples per second the pipeline delivers alone and training takes,
# the share of step time spent waiting for data and the peak GPU memory: with half the cores as DataLoader
# workers, reading the preprocessed-input cache (after a first pass fills it), then decoding every sample. Each
# step's output goes to LOGS.
set -uo pipefail
# shellcheck source=ros2_ws/benchmarks/gpu_setup.sh
. "$(dirname "${BASH_SOURCE[0]}")/gpu_setup.sh" "$@"
timeout 120 python -m pytest -q -c src/co3sop_nodes/setup.cfg --rootdir tests -p no:cacheprovider \
  tests/unit/train/test_dataset.py -k cuda 2>&1 | tee "$logs/pytest_cuda.log"
cores="$(nproc)"
workers=$((cores / 2 > 2 ? cores / 2 : 2))
timeout 300 ros2_ws/install/co3sop_nodes/lib/co3sop_nodes/generate --real-size --out /tmp/real --splits train=3 \
  --frames 5 --cavs 2-4 --vehicles 20 --workers "$cores" --seed 7 >"$logs/generate-real.log" 2>&1 \
  || { tail -n 5 "$logs/generate-real.log"; exit 1; }
pipeline() {
  local name="$1"; shift
  timeout 240 python ros2_ws/benchmarks/bench_train_step.py --pipeline --device cuda --data /tmp/real --splits train \
    --presets small paper --steps 40 --workers "$workers" "$@" 2>&1 | tee "$logs/pipeline-$name.log"
}
pipeline cached --cache /tmp/real-cache
pipeline decoding
