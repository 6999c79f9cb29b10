# Sourced by demo.sh, picms_demo.sh and test.sh (not by users): set up if needed, then the project's
# environment for a self-contained run. Discovery stays on this machine and the run gets its own DDS
# domain (unless ROS_DOMAIN_ID is set), so concurrent runs or a neighbour's nodes never see each
# other's traffic; plots render without a display.
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
# shellcheck disable=SC1091
source "$ROOT/scripts/env.sh"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( ( $$ + RANDOM ) % 100 + 1 ))}"
export MPLBACKEND="${MPLBACKEND:-Agg}"
cd "$ROOT"
