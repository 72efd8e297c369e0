"""The nodes as processes (what `ros2 run` starts), and the package's install layout."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2

from mf_lpr_ros.map_store import ReferenceMap
from mf_lpr_ros.ros.messages import odometry_message, points_to_pointcloud2, seconds_to_stamp
from mf_lpr_ros.synthetic import route, scan_world

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _start(executable: str, *ros_args: str) -> subprocess.Popen:
    # Unbuffered log lines: a SIGKILL must not swallow "saved N references" already written.
    environment = {**os.environ, "RCUTILS_LOGGING_BUFFERED_STREAM": "0"}
    return subprocess.Popen([str(BIN / executable), "--ros-args", *ros_args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=environment)


def _publish_traversal(ros_graph, world, count: int, until=lambda: False) -> int:
    clouds = ros_graph.publisher(PointCloud2, "points")
    odometry = ros_graph.publisher(Odometry, "odom")
    ros_graph.wait_for_subscribers(clouds)
    ros_graph.wait_for_subscribers(odometry)
    rng = np.random.default_rng(2)
    for index, (x, y, yaw) in enumerate(route(count)):
        points, pose = scan_world(world, x, y, yaw, rng)
        stamp = seconds_to_stamp(50.0 + index)
        odometry.publish(odometry_message(stamp, "map", "velodyne", pose))
        clouds.publish(points_to_pointcloud2(points, stamp, "velodyne"))
        time.sleep(0.05)
        if until():
            return index + 1
    return count


def test_sigint_saves_the_map(ros_graph, world, tmp_path):
    map_path = tmp_path / "built.mfmap"
    process = _start("map_builder", "-p", "preset:=kitti", "-p", f"map_path:={map_path}",
                     "-p", "save_period_s:=100.0")
    _publish_traversal(ros_graph, world, 20)
    time.sleep(1.0)
    process.send_signal(signal.SIGINT)
    output = process.communicate(timeout=30)[0]
    assert process.returncode == 0, output
    reference_map = ReferenceMap.load(map_path)
    assert len(reference_map) == 20, output  # scans ~11 m apart: every one is a reference
    assert f"saved 20 references to {map_path}" in output


def test_killing_map_builder_leaves_the_last_saved_map_loadable(ros_graph, world, tmp_path):
    map_path = tmp_path / "killed.mfmap"
    process = _start("map_builder", "-p", "preset:=kitti", "-p", f"map_path:={map_path}",
                     "-p", "save_period_s:=0.2")
    try:
        _publish_traversal(ros_graph, world, 40, until=lambda: map_path.exists()
                           and len(ReferenceMap.load(map_path)) >= 5)
    finally:
        process.send_signal(signal.SIGKILL)
        output = process.communicate(timeout=30)[0]
    acknowledged = [int(n) for n in re.findall(r"saved (\d+) references", output)]
    assert acknowledged, output
    reference_map = ReferenceMap.load(map_path)
    # The kill can land between a save's rename and its log line: the map may hold more than the
    # last line acknowledges, never less.
    assert len(reference_map) >= max(acknowledged[-1], 5)
    assert not list(tmp_path.glob("*.tmp*"))


@pytest.mark.parametrize("arguments,name", [
    (["-p", "search.top_n:=0"], "top_n"),
    (["-p", "map_path:=/nonexistent/map.mfmap"], "map.mfmap"),
    (["-p", "descriptor.density_mode:=pixels"], "density_mode"),
])
def test_localiser_process_refuses_bad_start_up_with_status_2(arguments, name):
    process = _start("localiser", *arguments)
    output = process.communicate(timeout=30)[0]
    assert process.returncode == 2
    assert name in output


def test_colcon_style_install_puts_files_where_ros2_run_looks(tmp_path):
    """ament_python under colcon runs `setup.py install` with a prefix; do the same."""
    source = tmp_path / "src"
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(
        ".venv", ".git", "build", "install", "log", "*.egg-info", "__pycache__", "out"))
    prefix = tmp_path / "install"
    result = subprocess.run(
        [sys.executable, "setup.py", "-q", "build", "--build-base", str(tmp_path / "build"),
         "install", "--prefix", str(prefix), "--single-version-externally-managed",
         "--record", str(tmp_path / "record.txt")],
        cwd=source, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    for executable in ("map_builder", "localiser", "mf-lpr"):
        path = prefix / "lib" / "mf_lpr_ros" / executable
        assert path.is_file() and os.access(path, os.X_OK), f"{path} missing"
    share = prefix / "share" / "mf_lpr_ros"
    assert (share / "package.xml").is_file()
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "mf_lpr_ros").is_file()
    assert {p.name for p in (share / "launch").glob("*.launch.py")} == {
        "map_builder.launch.py", "localiser.launch.py"}
    assert {p.stem for p in (share / "config").glob("*.yaml")} >= {"default", "kitti", "handheld"}
    site = next(prefix.glob("lib/python3*/site-packages"))
    environment = {**os.environ, "PYTHONPATH": str(site)}
    help_text = subprocess.run([str(prefix / "lib" / "mf_lpr_ros" / "mf-lpr"), "--help"],
                               capture_output=True, text=True, env=environment, cwd=tmp_path)
    assert help_text.returncode == 0 and "replay" in help_text.stdout


def test_launch_files_name_installed_executables_and_presets():
    for launch_file in (REPO / "launch").glob("*.launch.py"):
        text = launch_file.read_text()
        compile(text, str(launch_file), "exec")
        executable = re.search(r'executable="(\w+)"', text).group(1)
        assert executable in {"map_builder", "localiser"}
        assert "config/{value['preset']}.yaml" in text
