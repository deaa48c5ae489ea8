# Source this file to use the workspace: the virtual environment, the built
# packages, and the project's DDS settings. bootstrap.sh must have run once.
# Every variable set here is only a default: export your own value first to
# override it (e.g. ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET for several hosts).

CO3SOP_WS="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
export CO3SOP_WS
export CO3SOP_ROOT="$(dirname "$CO3SOP_WS")"
export COLCON_DEFAULTS_FILE="${COLCON_DEFAULTS_FILE:-$CO3SOP_WS/colcon_defaults.yaml}"

# shellcheck disable=SC1091
. "$CO3SOP_WS/.venv/bin/activate"
# The venv is a ROS install prefix: its share/ and lib/ hold the Jazzy packages.
export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$VIRTUAL_ENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
export LD_LIBRARY_PATH="$VIRTUAL_ENV/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
if [ -f "$CO3SOP_WS/install/setup.bash" ]; then
  # setup.bash reads unset variables; keep `set -u` callers working.
  case $- in *u*) set +u; . "$CO3SOP_WS/install/setup.bash"; set -u ;; *) . "$CO3SOP_WS/install/setup.bash" ;; esac
fi

export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# No multicast on these machines: discover peers on this host unless told otherwise.
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
# The shipped Fast DDS profile (large shared-memory segment); the nodes also
# apply it themselves when started by `ros2 run`.
export FASTRTPS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE:-$CO3SOP_ROOT/src/co3sop_nodes/config/fastdds.xml}"
