#!/usr/bin/env bash
# The README's main command: idempotent set-up, then the demo graph: a small
# generated scenario (made once) played into player + 3 vehicles + ego +
# recorder, separate processes over DDS; then the score table and pictures.
# Arguments go to `demo` (e.g. --params codec.dtype:=int8, --bag BAG).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$ROOT/ros2_ws/bootstrap.sh"
# shellcheck disable=SC1091
. "$ROOT/ros2_ws/env.sh"
cd "$ROOT"
LIB="$(python -c 'from ament_index_python.packages import get_package_prefix as p; print(p("co3sop_nodes"))')/lib/co3sop_nodes"
exec "$LIB/demo" "$@"
