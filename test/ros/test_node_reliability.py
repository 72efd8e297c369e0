"""The map builder node under faults: a full disk, an unwritable path, bad poses, scans it
cannot use."""

from __future__ import annotations

import dataclasses
import os
import re
import resource
import signal
import subprocess
import sys
import time

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.auto_params import SAMPLE_SCANS
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.prefilter_cache import cache_path
from mf_lpr_ros.core.references import PASSED_OVER_KEY
from mf_lpr_ros.core.search import MatchedFilterIndex
from mf_lpr_ros.ros.map_builder import MapBuilderNode
from mf_lpr_ros.ros.messages import odometry_message, points_to_pointcloud2, seconds_to_stamp
from mf_lpr_ros.sim.synthetic import scan_world

BIN = os.path.dirname(sys.executable)


def _limit_file_size(limit: int):
    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)   # EFBIG errors instead of a signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def _posed_scan_publishers(ros_graph):
    """Publishers of scans and odometry, each matched by a subscriber."""
    clouds = ros_graph.publisher(PointCloud2, "points")
    odometry = ros_graph.publisher(Odometry, "odom")
    ros_graph.wait_for_subscribers(clouds)
    ros_graph.wait_for_subscribers(odometry)
    return clouds, odometry


def _publish_scans_along_a_street(ros_graph, world, count: int):
    """count scans of the world 3 m apart along x, each with its odometry, stamped 10 s on,
    one a second; returns the odometry publisher."""
    clouds, odometry = _posed_scan_publishers(ros_graph)
    rng = np.random.default_rng(3)
    for index in range(count):
        points, pose = scan_world(world, 3.0 * index, 0.0, 0.0, rng)
        stamp = seconds_to_stamp(10.0 + index)
        odometry.publish(odometry_message(stamp, "map", "velodyne", pose))
        clouds.publish(points_to_pointcloud2(points, stamp, "velodyne"))
    return odometry


def test_full_disk_is_reported_and_the_map_stays_in_memory(ros_graph, world, tmp_path):
    map_path = tmp_path / "full.mfmap"
    process = subprocess.Popen(
        [os.path.join(BIN, "map_builder"), "--ros-args", "-p", "preset:=kitti",
         "-p", f"map_path:={map_path}", "-p", "save_period_s:=0.3", "-p", "keep_clouds:=true"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env={**os.environ, "RCUTILS_LOGGING_BUFFERED_STREAM": "0"},
        preexec_fn=_limit_file_size(3_000_000))
    clouds, odometry = _posed_scan_publishers(ros_graph)
    rng = np.random.default_rng(0)
    for index in range(40):
        points, pose = scan_world(world, 3.0 * index - 60, 0.0, 0.0, rng)
        stamp = seconds_to_stamp(10.0 + index)
        odometry.publish(odometry_message(stamp, "map", "velodyne", pose))
        clouds.publish(points_to_pointcloud2(points, stamp, "velodyne"))
        time.sleep(0.08)
    time.sleep(1.0)
    process.send_signal(signal.SIGINT)
    output = process.communicate(timeout=30)[0]
    assert process.returncode == 0, output
    assert "could not save the map" in output and "stay in memory" in output
    saved = [int(n) for n in re.findall(r"saved (\d+) references", output)]
    done = int(re.search(r"map_builder done: \d+ scans, (\d+) references", output).group(1))
    assert saved and done == 40 and saved[-1] < done          # kept in memory beyond the disk
    assert len(ReferenceMap.load(map_path)) == saved[-1]      # the last good save is intact


def test_bad_poses_are_refused_and_building_goes_on(ros_graph, world, tmp_path):
    builder = ros_graph.start(MapBuilderNode, preset="kitti", map_path=str(tmp_path / "m.mfmap"))
    clouds, odometry = _posed_scan_publishers(ros_graph)
    rng = np.random.default_rng(1)
    bad = []
    nan_pose = np.eye(4)
    nan_pose[0, 3] = np.nan
    bad.append(odometry_message(seconds_to_stamp(5.0), "map", "velodyne", nan_pose))
    stretched = odometry_message(seconds_to_stamp(5.5), "map", "velodyne", np.eye(4))
    stretched.pose.pose.orientation.w = 1.5                   # not a unit quaternion
    bad.append(stretched)
    for message in bad:
        odometry.publish(message)
    assert ros_graph.wait_for(lambda: builder.counters["poses_rejected"] == 2)
    for index in range(6):
        points, pose = scan_world(world, 3.0 * index, 0.0, 0.0, rng)
        stamp = seconds_to_stamp(10.0 + index)
        odometry.publish(odometry_message(stamp, "map", "velodyne", pose))
        clouds.publish(points_to_pointcloud2(points, stamp, "velodyne"))
    odometry.publish(odometry_message(seconds_to_stamp(12.5), "map", "velodyne", np.eye(4)))
    jump = np.eye(4)
    jump[0, 3] = 900.0
    odometry.publish(odometry_message(seconds_to_stamp(15.5), "map", "velodyne", jump))
    assert ros_graph.wait_for(lambda: builder.counters["poses_rejected"] == 3
                              and builder.poses.jumps == 1 and len(builder.builder.map) == 6)


def test_an_unwritable_map_path_is_reported_and_the_map_kept(ros_graph, world):
    builder = ros_graph.start(MapBuilderNode, preset="kitti",
                              map_path="/proc/mf_lpr_read_only/map.mfmap")
    _publish_scans_along_a_street(ros_graph, world, 3)
    assert ros_graph.wait_for(lambda: len(builder.builder.map) == 3)
    assert not builder.save()
    assert builder.counters["save_failures"] == 1 and builder.builder.unsaved == 3


def test_map_builder_node_with_preset_auto_derives_then_builds(ros_graph, world, tmp_path):
    map_path = tmp_path / "auto.mfmap"
    builder = ros_graph.start(MapBuilderNode, preset="auto", map_path=str(map_path))
    clouds, odometry = _posed_scan_publishers(ros_graph)
    rng = np.random.default_rng(3)
    n_scans = SAMPLE_SCANS + 3
    for index in range(n_scans):
        points, pose = scan_world(world, 3.0 * index - 20.0, 2.0, 0.1, rng)
        stamp = seconds_to_stamp(10.0 + index)
        odometry.publish(odometry_message(stamp, "map", "velodyne", pose))
        clouds.publish(points_to_pointcloud2(points, stamp, "velodyne"))
    odometry.publish(odometry_message(seconds_to_stamp(10.0 + n_scans), "map", "velodyne",
                                      np.eye(4)))
    # The first SAMPLE_SCANS scans wait for the derivation, then all become references.
    assert ros_graph.wait_for(lambda: len(builder.builder.map) == n_scans)
    builder.finish()
    saved = ReferenceMap.load(map_path)
    assert len(saved) == n_scans and not cache_path(map_path).exists()
    assert saved.metadata["auto"]["sensor_profile"]["ground_below_sensor_m"] > 1.5
    # A dense 360-degree sensor: the default voxel and band, its levelling decided (upright).
    assert "as given (a dense 360-degree sensor)" in saved.metadata["auto"]["choice"]
    assert saved.params == dataclasses.replace(preset("default").descriptor, level=False)


def test_a_finished_map_whose_search_reads_spectra_on_demand_has_its_cache_beside_it(
        ros_graph, world, tmp_path):
    """As build-map does: the node's last save of a map searched with its spectra on demand
    (forced here; over 50,000 references by default) writes the prefilter's features beside
    it, and a localiser's first index loads them. Periodic saves write none: a map still
    growing would compute them again at every save."""
    map_path = tmp_path / "large.mfmap"
    builder = ros_graph.start(MapBuilderNode, preset="kitti", map_path=str(map_path),
                              **{"search.reference_spectra": "on_demand"})
    odometry = _publish_scans_along_a_street(ros_graph, world, 4)
    odometry.publish(odometry_message(seconds_to_stamp(14.0), "map", "velodyne", np.eye(4)))
    assert ros_graph.wait_for(lambda: len(builder.builder.map) == 4)
    assert builder.save() and not cache_path(map_path).exists()
    builder.finish()
    search = builder.builder.config.search
    index = MatchedFilterIndex(ReferenceMap.load(map_path), search)
    assert index.prefilter_cache_status.startswith("loaded from")


def test_scans_the_node_could_not_use_are_listed_in_the_map(ros_graph, world, tmp_path):
    """An empty message (rejected at decoding) and a scan with nothing inside the descriptor's
    window (refused when described) are noted in the saved map's metadata, numbered as they
    arrived, as build-map notes the scans it passes over; the next scan is the reference."""
    map_path = tmp_path / "noted.mfmap"
    builder = ros_graph.start(MapBuilderNode, preset="kitti", map_path=str(map_path))
    clouds, odometry = _posed_scan_publishers(ros_graph)
    rng = np.random.default_rng(5)
    for index in range(5):
        points, pose = scan_world(world, 3.0 * max(index - 2, 0), 0.0, 0.0, rng)
        if index == 0:
            points = points[:0]
        elif index == 1:
            points = points + np.array([900.0, 0.0, 0.0], dtype=points.dtype)
        stamp = seconds_to_stamp(10.0 + index)
        odometry.publish(odometry_message(stamp, "map", "velodyne", pose))
        clouds.publish(points_to_pointcloud2(points, stamp, "velodyne"))
    odometry.publish(odometry_message(seconds_to_stamp(15.0), "map", "velodyne", np.eye(4)))
    assert ros_graph.wait_for(lambda: len(builder.builder.map) == 3
                              and builder.counters["scans_rejected"] == 2)
    builder.finish()
    saved = ReferenceMap.load(map_path)
    noted = saved.metadata[PASSED_OVER_KEY]
    assert noted["count"] == 2
    assert [(scan["scan"], scan["stamp"], scan["source"]) for scan in noted["scans"]] == [
        (0, 10.0, "map_builder"), (1, 11.0, "map_builder")]
    assert "empty" in noted["scans"][0]["why"]
    assert "window" in noted["scans"][1]["why"]
    assert saved.source_indices.tolist() == [2, 3, 4]


def test_a_stream_of_scans_in_a_foreign_frame_is_counted_each_and_logged_once(ros_graph,
                                                                               tmp_path):
    """A driver publishing in the wrong frame at 10 Hz: every scan counted and listed, the
    warning not repeated for each (a scan's stamp must not make the same problem look new)."""
    builder = ros_graph.start(MapBuilderNode, preset="kitti", map_path=str(tmp_path / "m.mfmap"),
                              sensor_frame_id="velodyne")
    warnings = []

    class Recording:
        def __getattr__(self, name):
            return lambda *args, **kwargs: None

        def warning(self, text):
            warnings.append(text)

    builder.get_logger = Recording
    clouds = ros_graph.publisher(PointCloud2, "points")
    ros_graph.wait_for_subscribers(clouds)
    points = np.random.default_rng(6).uniform(-20, 20, (500, 3)).astype(np.float32)
    for index in range(5):
        clouds.publish(points_to_pointcloud2(points, seconds_to_stamp(10.0 + 0.1 * index),
                                             "os_lidar"))
    assert ros_graph.wait_for(lambda: builder.counters["scans_rejected"] == 5)
    assert builder.builder.map.metadata[PASSED_OVER_KEY]["count"] == 5
    assert warnings == ["scan rejected: frame 'os_lidar' is not the configured sensor_frame_id "
                        "'velodyne'"]
