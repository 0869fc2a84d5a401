# Source this file (". scripts/env.sh") to use the project's ROS workspace and venv.
_aft_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck disable=SC1091
source "$_aft_root/catkin_ws/devel/setup.bash"
export PATH="$_aft_root/.venv/bin:$PATH"
export ROS_PYTHON_VERSION=3
export ROS_HOME="${ROS_HOME:-$_aft_root/.ros}"
# made here, once: roslaunch makes it unguarded, and two roscores starting together in a fresh clone
# raced (FileExistsError in write_pid_file; CI, bench_ros_buffering)
mkdir -p "$ROS_HOME"
unset _aft_root
