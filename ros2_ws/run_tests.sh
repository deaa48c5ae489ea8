#!/usr/bin/env bash
# The README's test command: idempotent set-up, then the default test suite
# (unit tests without DDS, integration tests over real DDS). Extra arguments go
# to pytest. "No tests collected" is a failure, not a pass.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$ROOT/ros2_ws/bootstrap.sh"
# shellcheck disable=SC1091
. "$ROOT/ros2_ws/env.sh"
cd "$ROOT"
set +e
python -m pytest -c tests/pytest.ini tests "$@"
code=$?
set -e
if [ "$code" -eq 5 ]; then
  echo "run_tests: error: pytest collected no tests" >&2
  exit 1
fi
exit "$code"
