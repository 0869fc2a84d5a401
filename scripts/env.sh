# Source this file (". scripts/env.sh") to use the project's ROS workspace and venv.
_aft_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck disable=SC1091
source "$_aft_root/catkin_ws/devel/setup.bash"
export PATH="$_aft_root/.venv/bin:$PATH"
export ROS_PYTHON_VERSION=3
export ROS_HOME="${ROS_HOME:-$_aft_root/.ros}"
unset _aft_root
