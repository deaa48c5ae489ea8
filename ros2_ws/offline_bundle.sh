#!/usr/bin/env bash
# The node graph for a machine with no package registry whose own Python 3.12 holds a CUDA build of PyTorch
# (a GPU server, a cloud image): packed here, unpacked there.
#
#   ros2_ws/offline_bundle.sh pack BUNDLE.tar.xz [BAG_DIR...]     here: Python 3.12 (PYTHON=...) and PyPI reachable
#   ros2_ws/offline_bundle.sh unpack BUNDLE.tar.xz TARGET_PYTHON  there: e.g. /opt/torch/.venv/bin/python3
#   cd /tmp/co3sop-offline && . ros2_ws/env.sh                     there: then as anywhere (demo, bench_graph, tests)
#
# pack builds the workspace in ROOT with the pinned wheels for CPython 3.12 but torch (the target brings its own)
# and writes its virtual environment, colcon build and install, and BAG_DIRs into one archive, leaving out what
# the target's Python already has (numpy, matplotlib, pillow, ...), build tools and headers. unpack, run from a
# checkout of the same commit, extracts it at the same ROOT (the environment and colcon's symlink install name
# absolute paths) beside that checkout's sources, points the environment at TARGET_PYTHON's interpreter and
# appends that Python's own packages (its torch) to the search path.
set -euo pipefail
ROOT=/tmp/co3sop-offline
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
say() { printf '[offline_bundle] %s\n' "$*"; }
die() { printf '[offline_bundle] error: %s\n' "$*" >&2; exit 2; }

# The checkout's sources (what colcon's symlink install points into), without its own environment and build.
sources() {
  tar -C "$1" --exclude='ros2_ws/.venv' --exclude='ros2_ws/install' --exclude='ros2_ws/build' --exclude='ros2_ws/log' \
    -cf - src tests ros2_ws | tar -C "$2" -xf -
}

pack() {
  local bundle="$1"; shift
  local python="${PYTHON:-python3.12}" bag
  for bag in "$@"; do [ -d "$REPO/$bag" ] || die "$bag: no such folder in $REPO (BAG_DIRs are relative to it)"; done
  "$python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' 2>/dev/null \
    || die "PYTHON=$python is not CPython 3.12 (the target's version)"
  rm -rf "$ROOT" && mkdir -p "$ROOT"
  sources "$REPO" "$ROOT"
  say "virtual environment for $("$python" -V) in $ROOT/ros2_ws/.venv"
  "$python" -m venv "$ROOT/ros2_ws/.venv"
  grep -v '^torch==' "$REPO/ros2_ws/requirements.txt" > "$ROOT/ros2_ws/.requirements-notorch.txt"
  # sdist-only pins (empy) are built into wheels here: the target cannot build them without a registry
  "$ROOT/ros2_ws/.venv/bin/pip" install -qq --disable-pip-version-check --no-deps \
    -r "$ROOT/ros2_ws/.requirements-notorch.txt"
  "$ROOT/ros2_ws/.venv/bin/python" "$ROOT/ros2_ws/fix_cmake_paths.py" "$ROOT/ros2_ws/.venv"
  say "colcon build"
  (cd "$ROOT/ros2_ws" && set +u && . ./env.sh && colcon build --base-paths ../src vendor >.colcon-build.out 2>&1) \
    || { cat "$ROOT/ros2_ws/.colcon-build.out" >&2; exit 1; }
  for bag in "$@"; do
    mkdir -p "$ROOT/$(dirname "$bag")" && cp -r "$REPO/$bag" "$ROOT/$bag"
  done
  local site="ros2_ws/.venv/lib/python3.12/site-packages"
  local -a leave_out=()
  local p
  # the target's Python has these (a torch image does), or they only build and lint
  for p in numpy numpy.libs numpy-* matplotlib matplotlib-* mpl_toolkits PIL pillow.libs pillow-* sympy sympy-* \
    mpmath mpmath-* networkx networkx-* fontTools fonttools-* kiwisolver kiwisolver-* contourpy contourpy-* pip \
    pip-* docutils docutils-* ruff ruff-* coverage \
    coverage-* colcon_* colcon-*; do
    leave_out+=(--exclude="$site/$p")
  done
  say "writing $bundle"
  # hard links: the ROS wheels install each shared library under three names (no symbolic links in a wheel)
  # ... and the auditwheel copies of libcrypto and others, one per ROS wheel
  "$python" - "$ROOT/ros2_ws/.venv/lib" <<'PY'
import hashlib, os, pathlib, sys
first = {}
for path in sorted(pathlib.Path(sys.argv[1]).rglob("*.so*")):
    if path.is_file() and not path.is_symlink():
        digest = hashlib.sha256(path.read_bytes()).digest()
        if digest in first:
            path.unlink()
            os.link(first[digest], path)
        else:
            first[digest] = path
PY
  tar -C "$ROOT" "${leave_out[@]}" --exclude='ros2_ws/.venv/include' --exclude='ros2_ws/.venv/share/*/cmake' \
    --exclude='ros2_ws/.venv/bin/ruff' --exclude='ros2_ws/build/*/CMakeFiles' --exclude='*.o' --exclude='__pycache__' \
    -I 'xz -T2' -cf "$bundle" ros2_ws/.venv ros2_ws/install ros2_ws/build "$@"
  say "$(du -h "$bundle" | cut -f1) in $bundle"
}

unpack() {
  local bundle="$1" target="$2"
  [ -f "$bundle" ] || die "$bundle: no such bundle (make one with: $0 pack BUNDLE.tar.xz)"
  "$target" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' || die "$target is not CPython 3.12"
  rm -rf "$ROOT" && mkdir -p "$ROOT" && tar -C "$ROOT" -xJf "$bundle"
  sources "$REPO" "$ROOT"
  local venv="$ROOT/ros2_ws/.venv" base
  base="$("$target" -c 'import sys; print(sys._base_executable)')"
  sed -i "s|^home = .*|home = $(dirname "$base")|" "$venv/pyvenv.cfg"
  ln -sf "$base" "$venv/bin/python3.12"
  # after the environment's own packages: the target's torch (and numpy, matplotlib, ...)
  "$target" -c 'import site; print("\n".join(site.getsitepackages()))' \
    > "$venv/lib/python3.12/site-packages/zz_target_python.pth"
  "$venv/bin/python" -c 'import torch, rclpy; print(f"torch {torch.__version__}, CUDA {torch.cuda.is_available()}")'
  say "ready: cd $ROOT && . ros2_ws/env.sh"
}

case "${1:-}" in
  pack) [ $# -ge 2 ] || die "usage: $0 pack BUNDLE.tar.xz [BAG_DIR...]"; shift; pack "$@" ;;
  unpack) [ $# -eq 3 ] || die "usage: $0 unpack BUNDLE.tar.xz TARGET_PYTHON"; unpack "$2" "$3" ;;
  *) die "usage: $0 pack BUNDLE.tar.xz [BAG_DIR...] | unpack BUNDLE.tar.xz TARGET_PYTHON" ;;
esac
