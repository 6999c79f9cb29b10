#!/usr/bin/env bash
# Set up (if needed) and run the simulated CT cell end to end: render -> publish -> detect ->
# solve -> error map -> record -> report, each node in its own process over DDS; then the
# PiCMS cell: calibration, measurement of the targets part program, report (picms_measure_demo).
# Options go to ct_demo, e.g.  bash scripts/demo.sh --positions 19 --projections 36
set -euo pipefail
# shellcheck disable=SC1091
source "$(dirname "${BASH_SOURCE[0]}")/prepare.sh"
rc=0
"$ROOT/ros_ws/install/ct_calib_nodes/lib/ct_calib_nodes/ct_demo" --out "$ROOT/out" --bags "$ROOT/bags" "$@" || rc=$?
# The PiCMS cell: calibrate a simulated cell, measure the chrome-targets part program, write
# measurement.json and report.md (tables, Figs 13-16 style plots) under out/picms_measure/<stamp>/.
# PICMS_DEMO=0 skips it; PICMS_DEMO_ARGS passes options (e.g. "--program flange --seed 3").
if [ "${PICMS_DEMO:-1}" != "0" ]; then
  # shellcheck disable=SC2086
  nice "$ROOT/ros_ws/install/picms_nodes/lib/picms_nodes/picms_measure_demo" --out "$ROOT/out/picms_measure" \
    ${PICMS_DEMO_ARGS:-} || rc=$((rc == 0 ? 1 : rc))
fi
exit "$rc"
