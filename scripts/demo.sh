#!/usr/bin/env bash
# Set up (if needed) and run the simulated CT cell end to end: render -> publish -> detect ->
# solve -> error map -> record -> report, each node in its own process over DDS.
# Options go to ct_demo, e.g.  bash scripts/demo.sh --positions 19 --projections 36
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
# shellcheck disable=SC1091
source "$ROOT/scripts/env.sh"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( ( $$ + RANDOM ) % 100 + 1 ))}"
export MPLBACKEND=Agg
cd "$ROOT"
exec "$ROOT/ros_ws/install/ct_calib_nodes/lib/ct_calib_nodes/ct_demo" --out "$ROOT/out" --bags "$ROOT/bags" "$@"
