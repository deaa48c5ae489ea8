#!/usr/bin/env bash
# The README's main command: idempotent set-up, then the demo.
# Until the node graph lands this is the DDS smoke demo: `sample_stream`
# publishes synthetic voxel features for two vehicles and an occupancy grid,
# and `monitor` (a separate process) reports rate, wire size, compression
# ratio, decode time and the decoded grids.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$ROOT/ros2_ws/bootstrap.sh"
# shellcheck disable=SC1091
. "$ROOT/ros2_ws/env.sh"
FRAMES="${FRAMES:-50}"
LIB="$(python -c 'from ament_index_python.packages import get_package_prefix as p; print(p("co3sop_nodes"))')/lib/co3sop_nodes"

"$LIB/monitor" --count $((FRAMES * 3)) --duration 120 --period 2 &
monitor=$!
trap 'kill -INT $monitor 2>/dev/null || true' EXIT
"$LIB/sample_stream" --agents 1 2 --frames "$FRAMES" --rate 10 --dtype int8 --selection topk --wait-subscribers 20
wait "$monitor"
trap - EXIT
echo "[demo] done: ${FRAMES} frames from 2 vehicles crossed DDS and decoded."
