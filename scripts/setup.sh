#!/usr/bin/env bash
# Idempotent set-up: Debian's ROS 1 packages, the venv, pip packages, catkin build.
# Each step is skipped when already done; the catkin build is incremental.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

APT_PACKAGES=(
  ros-core catkin python3-rospy python3-roslaunch python3-rostest python3-rosnode python3-rosservice
  python3-rostopic python3-rosgraph ros-message-generation python3-genpy python3-genmsg python3-gencpp
  python3-genlisp libstd-msgs-dev python3-std-msgs ros-std-msgs python3-std-srvs libstd-srvs-dev
  python3-psutil python3-yaml python3-nacl python3-cryptography python3-venv python3-pip cmake g++ make procps rosbash
  python3-rosbag python3-rosgraph-msgs python3-sensor-msgs python3-geometry-msgs python3-diagnostic-msgs
)

missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$pkg")
  fi
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing ${#missing[@]} Debian packages: ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${missing[@]}" > "$ROOT/.apt-install.log" 2>&1 || {
    tail -30 "$ROOT/.apt-install.log"; echo "setup: apt-get install failed"; exit 1; }
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv on /usr/bin/python3 (with system site packages, for rospy)"
  /usr/bin/python3 -m venv --system-site-packages .venv
fi
want="$(sha256sum requirements.txt | cut -d' ' -f1)"
if [ "$(cat .venv/.requirements.sha256 2>/dev/null)" != "$want" ]; then
  echo "setup: installing requirements.txt into .venv"
  .venv/bin/python -m pip install -q --disable-pip-version-check -r requirements.txt
  echo "$want" > .venv/.requirements.sha256
fi

# Nodes are run by the interpreter catkin writes in their relay scripts: the venv's, which sees
# Debian's rospy and catkin_pkg (system site packages) and the pip packages too.
log="$ROOT/catkin_ws/catkin_make.log"
mkdir -p catkin_ws
# The message packages list their .msg/.srv files with file(GLOB) at configure time: a file added
# or removed since the last configure needs CMake to run again.
sources="$(cd catkin_ws/src && ls -1 */msg/*.msg */srv/*.srv */nodes/* 2>/dev/null | sha256sum | cut -d' ' -f1)"
force=()
if [ "$(cat catkin_ws/build/.aft_sources 2>/dev/null)" != "$sources" ]; then
  force=(--force-cmake)
fi
if (cd catkin_ws && catkin_make "${force[@]}" -DPYTHON_EXECUTABLE="$ROOT/.venv/bin/python3" -DCATKIN_ENABLE_TESTING=OFF > "$log" 2>&1); then
  echo "$sources" > catkin_ws/build/.aft_sources
  echo "setup: catkin workspace built"
else
  tail -40 "$log"; echo "setup: catkin_make failed (full log: $log)"; exit 1
fi

# The project's modules compiled once: the processes a run starts (a few thousand in `make test`)
# then load bytecode instead of compiling each import from source (PYTHONDONTWRITEBYTECODE=1, set on
# this project's machines, keeps Python from caching it itself; a .pyc is checked against its source
# at every import, so an edit is never missed). Measured: 0.09 s of CPU less per node started.
.venv/bin/python -m compileall -q -j 0 catkin_ws/src/*/src catkin_ws/devel/lib/python3/dist-packages tests \
  > /dev/null 2>&1 || echo "setup: compiling the project's bytecode failed (it runs from source)"
