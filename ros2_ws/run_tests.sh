#!/usr/bin/env bash
# The README's test command: idempotent set-up, then the default test suite
# (unit tests without DDS, integration tests over real DDS). Extra arguments go
# to pytest. "No tests collected" is a failure, not a pass.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$ROOT/ros2_ws/bootstrap.sh"
# Foxglove's own readers (npm) for the test that every recording and bag decodes as Foxglove decodes it
FOX="$ROOT/tests/foxglove"
if [ "$(cat "$FOX/node_modules/.co3sop-lock" 2>/dev/null)" != "$(sha256sum "$FOX/package-lock.json" | cut -c1-16)" ]; then
  command -v npm >/dev/null || { echo "run_tests: error: npm (Node.js 18 or newer) is needed for Foxglove's readers: apt-get install nodejs npm" >&2; exit 2; }
  echo "[bootstrap] npm ci in tests/foxglove (Foxglove's MCAP and ROS 2 readers)"
  npm ci --prefix "$FOX" --no-audit --no-fund --loglevel=error
  sha256sum "$FOX/package-lock.json" | cut -c1-16 > "$FOX/node_modules/.co3sop-lock"
fi
# nftables for the emulated V2X channel's loss rules (tests/integration/test_channel.py; ip and tc come with iproute2)
if ! command -v nft >/dev/null || ! command -v tc >/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "[bootstrap] apt-get install nftables iproute2 (the emulated V2X channel)"
    apt-get install -y -qq nftables iproute2 >/dev/null || { apt-get update -qq && apt-get install -y -qq nftables iproute2 >/dev/null; }
  else
    echo "run_tests: error: the emulated V2X channel's tests need nft and tc, as root: apt-get install nftables iproute2" >&2
    exit 2
  fi
fi
# shellcheck disable=SC1091
. "$ROOT/ros2_ws/env.sh"
cd "$ROOT"
set +e
# Two worker processes (pytest-xdist): most tests wait on processes they started, so one core alone idles half
# the time. Each test goes to whichever worker is free.
python -m pytest -c src/co3sop_nodes/setup.cfg --rootdir tests --durations=30 -n 2 --dist worksteal tests "$@"
code=$?
set -e
if [ "$code" -eq 5 ]; then
  echo "run_tests: error: pytest collected no tests" >&2
  exit 1
fi
exit "$code"
