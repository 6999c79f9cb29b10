# Source this file to get the project's ROS 2 environment in the current shell:
#   source scripts/env.sh
# It activates .venv (which plays the part of /opt/ros/jazzy), sources the
# workspace overlay and keeps DDS discovery on this machine.
_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export VIRTUAL_ENV="$_root/.venv"
export PATH="$VIRTUAL_ENV/bin:$PATH"
export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
# install/setup.bash reads unset variables; relax nounset while sourcing it
_had_u=0; case $- in *u*) _had_u=1; set +u;; esac
# shellcheck disable=SC1091
source "$_root/ros_ws/install/setup.bash"
[ $_had_u = 1 ] && set -u
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export METRO_ROOT="$_root"
unset _root _had_u
