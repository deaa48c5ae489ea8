#!/usr/bin/env bash
# Idempotent set-up from nothing: virtual environment with the pinned wheels,
# the CMake path fix-up, and `colcon build` of both packages. A second run with
# nothing changed only re-checks stamps and lets colcon find nothing to do.
set -euo pipefail
WS="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$WS"
PYTHON="${PYTHON:-python3}"
VENV="$WS/.venv"
step() { printf '[bootstrap] %s\n' "$*"; }

if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
  echo "[bootstrap] error: the pinned wheels (torch's CPU build among them) are for CPython 3.11; $PYTHON is" \
    "$("$PYTHON" -V 2>&1). A Python 3.12 with its own (CUDA) PyTorch: ros2_ws/offline_bundle.sh." >&2
  exit 2
fi
if [ ! -x "$VENV/bin/python" ]; then
  step "creating virtual environment $VENV"
  "$PYTHON" -m venv "$VENV"
fi

req_hash="$(sha256sum requirements.txt fix_cmake_paths.py | sha256sum | cut -c1-16)"
stamp="$VENV/.co3sop-requirements"
if [ "$(cat "$stamp" 2>/dev/null)" != "$req_hash" ]; then
  step "installing pinned wheels (first run: a few minutes)"
  # --no-deps: the lock is complete, and nothing may pull a CUDA build of torch.
  "$VENV/bin/pip" install -qq --disable-pip-version-check --no-deps -r requirements.txt
  "$VENV/bin/python" fix_cmake_paths.py "$VENV"
  echo "$req_hash" > "$stamp"
else
  step "virtual environment up to date"
fi

# shellcheck disable=SC1091
. "$WS/env.sh"
# tf2_msgs (for /tf and /tf_static) has no PyPI wheel: build our copy of its
# TFMessage unless an underlay (e.g. /opt/ros/jazzy) already provides it.
paths=(../src)
have_tf2_msgs=0
IFS=: read -ra prefixes <<< "${AMENT_PREFIX_PATH:-}"
for prefix in "${prefixes[@]}"; do
  case "$prefix" in "$WS"/install*) continue ;; esac
  [ -f "$prefix/share/tf2_msgs/package.xml" ] && have_tf2_msgs=1
done
[ "$have_tf2_msgs" = 1 ] || paths+=(vendor)
step "colcon build"
colcon build --base-paths "${paths[@]}" >"$WS/.colcon-build.out" 2>&1 || { cat "$WS/.colcon-build.out" >&2; exit 1; }
tail -n 1 "$WS/.colcon-build.out"
