#!/usr/bin/env bash
# Set up (if needed) and run every test. Extra arguments go to pytest, e.g.
#   bash scripts/test.sh -k mcap
# Tests run in TEST_WORKERS worker processes (default 2, pytest-xdist; whole files per worker so
# module fixtures are built once; each worker has its own DDS domain, see tests/conftest.py).
# TEST_WORKERS=0 runs them in this process.
set -euo pipefail
# shellcheck disable=SC1091
source "$(dirname "${BASH_SOURCE[0]}")/prepare.sh"
echo "[test] ROS_DOMAIN_ID=$ROS_DOMAIN_ID ROS_AUTOMATIC_DISCOVERY_RANGE=$ROS_AUTOMATIC_DISCOVERY_RANGE"
workers="${TEST_WORKERS:-2}"
if [ "$workers" = 0 ]; then
  exec python -m pytest "$@"
fi
exec python -m pytest -n "$workers" --dist loadfile "$@"
