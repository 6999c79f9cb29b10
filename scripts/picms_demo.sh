#!/usr/bin/env bash
# Set up (if needed) and run the simulated PiCMS cell end to end: stage, cameras, tracker,
# MCAP recorder and the Pixel Probe calibration node over DDS, then the offline calibration of
# the recording; prints both against the simulator's truth. Options go to picms_demo, e.g.
#   bash scripts/picms_demo.sh --seed 3 --dwell 3
set -euo pipefail
# shellcheck disable=SC1091
source "$(dirname "${BASH_SOURCE[0]}")/prepare.sh"
exec "$ROOT/ros_ws/install/picms_nodes/lib/picms_nodes/picms_demo" --out "$ROOT/out/picms" --bags "$ROOT/bags" "$@"
