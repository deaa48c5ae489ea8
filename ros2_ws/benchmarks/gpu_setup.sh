# Sourced by the GPU benchmark scripts (gpu_graph.sh, gpu_train.sh) with their arguments BUNDLE.tar.xz TARGET_PYTHON
# LOGS: unpacks the bundle packed elsewhere (ros2_ws/offline_bundle.sh pack), enters the workspace with the target's
# Python and its CUDA PyTorch, and writes the machine's GPU and core count to LOGS/machine.txt. Sets `logs`.
bundle="$(realpath "$1")" target="$2" logs="$(realpath "$3")"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
bash "$here/ros2_ws/offline_bundle.sh" unpack "$bundle" "$target" || exit 1
cd /tmp/co3sop-offline || exit 1
set +u
# shellcheck disable=SC1091
. ros2_ws/env.sh
set -u
export PYTHONUNBUFFERED=1
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader; nproc; } | tee "$logs/machine.txt"
