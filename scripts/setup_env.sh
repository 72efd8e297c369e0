#!/usr/bin/env bash
# Creates the project virtual environment with every runtime and test dependency.
# Uses a system rclpy (a sourced ROS 2 Jazzy install) when one is present, else the
# ROS 2 Jazzy wheels from PyPI.
set -euo pipefail
venv=${1:-.venv}
python=${PYTHON:-python3}

if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then
  echo "setup: installing Debian's libusb-1.0-0 (needed by open3d)"
  sudo_cmd=""
  if [ "$(id -u)" != 0 ]; then sudo_cmd="sudo"; fi
  $sudo_cmd apt-get update -qq && $sudo_cmd apt-get install -y -qq libusb-1.0-0 \
    || echo "setup: WARNING could not install libusb-1.0-0; open3d (ICP refinement) will be unavailable"
fi

if [ ! -x "$venv/bin/python" ]; then
  if $python -c "import rclpy" 2>/dev/null; then
    $python -m venv --system-site-packages "$venv"
  else
    $python -m venv "$venv"
  fi
fi
pip="$venv/bin/python -m pip"
# This machine's pip config names local indexes that may not exist; their warnings are noise.
quiet() {
  local status
  set +e
  "$@" 2>&1 | grep -v "is ignored: it is neither"
  status=${PIPESTATUS[0]}
  set -e
  return "$status"
}
quiet $pip install -q --upgrade pip
quiet $pip install -q numpy scipy rosbags tqdm matplotlib pillow pyyaml pytest pytest-xdist hypothesis ruff==0.17.6 open3d-cpu threadpoolctl
if ! "$venv/bin/python" -c "import rclpy, visualization_msgs.msg, diagnostic_msgs.msg, nav_msgs.msg, std_srvs.srv, lifecycle_msgs.msg" 2>/dev/null; then
  quiet $pip install -q "ros-jazzy-rclpy[fastrtps]" ros-jazzy-sensor-msgs ros-jazzy-geometry-msgs \
    ros-jazzy-nav-msgs ros-jazzy-std-msgs ros-jazzy-visualization-msgs ros-jazzy-diagnostic-msgs \
    ros-jazzy-std-srvs ros-jazzy-lifecycle-msgs
fi
# colcon builds and tests the package as on a ROS 2 workspace (test_ros_processes.py builds it).
quiet $pip install -q colcon-common-extensions || echo "setup: colcon not installed; the colcon build test will be skipped"
# GTSAM: the pose graph of slam-eval and the pose_graph node (optional; both name it when missing).
quiet $pip install -q gtsam || echo "setup: gtsam not installed; slam-eval and pose_graph will be unavailable"
# LZF: PCD files saved as DATA binary_compressed (PCL's compressed writer, map editors).
quiet $pip install -q python-neo-lzf || echo "setup: python-neo-lzf not installed; compressed PCD files will be refused"
# Dask distributed: suite and build-map across processes or machines (--scheduler).
quiet $pip install -q "dask[distributed]" || echo "setup: dask not installed; --scheduler will be unavailable"
quiet $pip install -q --no-deps -e .
"$venv/bin/python" -c "import numpy, scipy, rosbags, yaml, PIL, pytest, xdist" && [ -x "$venv/bin/ruff" ] \
  || { echo "setup: the environment is incomplete" >&2; exit 1; }
echo "setup: environment ready in $venv"
