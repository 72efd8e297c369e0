"""Submaps through the localiser node: ~/relocalise waits until the window is complete (or its
timeout) and says which it used; without odometry the node describes single scans."""

from __future__ import annotations

import dataclasses
import json
import threading

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from test_relocalise_service import _call
from test_ros_nodes import errors

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.pose import planar
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.live.pose_buffer import PairedScan
from mf_lpr_ros.ros.localiser import LocaliserNode
from mf_lpr_ros.ros.messages import odometry_message, points_to_pointcloud2, seconds_to_stamp
from mf_lpr_ros.sim.synthetic import route, scan_world

SPARSE_DROPOUT = 0.97
WINDOW_M = 4.0


@pytest.fixture(scope="module")
def submap_map(tmp_path_factory, world):
    """A map of a sparse sensor's traversal, each reference from its last 4 m of scans."""
    base = preset("default")
    config = dataclasses.replace(base, descriptor=dataclasses.replace(base.descriptor,
                                                                      submap_m=WINDOW_M))
    path = tmp_path_factory.mktemp("maps") / "submaps.mfmap"
    builder = MapBuilder(config, path)
    rng = np.random.default_rng(1)
    for index, (x, y, yaw) in enumerate(route(300)):
        points, pose = scan_world(world, x, y, yaw, rng, dropout=SPARSE_DROPOUT)
        builder.offer(PairedScan(index, 10.0 + 0.1 * index, points, pose))
    builder.save()
    return path


class PosedStream:
    """Publishes odometry and then the scan for each trajectory row at ~10 Hz, round and round,
    until stopped; remembers the truth of each stamp."""

    def __init__(self, ros_graph, world, trajectory: np.ndarray, odometry: bool = True) -> None:
        self.clouds = ros_graph.publisher(PointCloud2, "points")
        self.odometry = ros_graph.publisher(Odometry, "odom") if odometry else None
        ros_graph.wait_for_subscribers(self.clouds)
        if self.odometry is not None:
            ros_graph.wait_for_subscribers(self.odometry)
        self.world, self.trajectory = world, trajectory
        self.truth: dict[float, np.ndarray] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        rng = np.random.default_rng(2)
        index, stamp = 0, 500.0
        while not self._stop.wait(0.1):
            x, y, yaw = self.trajectory[index % len(self.trajectory)]
            points, pose = scan_world(self.world, x, y, yaw, rng, dropout=SPARSE_DROPOUT)
            self.truth[round(stamp, 3)] = planar(pose)
            message_stamp = seconds_to_stamp(stamp)
            if self.odometry is not None:
                self.odometry.publish(odometry_message(message_stamp, "odom", "velodyne", pose))
            self.clouds.publish(points_to_pointcloud2(points, message_stamp, "velodyne"))
            stamp += 0.1
            index += 1

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *_):
        self._stop.set()
        self._thread.join()


def test_a_request_is_answered_from_a_complete_window(ros_graph, world, submap_map):
    node = ros_graph.start(LocaliserNode, map_path=str(submap_map), pose_source="odom",
                           request_timeout_s=60.0)
    client = ros_graph.node.create_client(Trigger, "/localiser/relocalise")
    moving = route(300, lateral_offset_m=1.5, reverse=True)
    with PosedStream(ros_graph, world, moving) as stream:
        reply = _call(ros_graph, client, timeout_s=90.0)
    assert reply.success, reply.message
    answer = json.loads(reply.message)
    assert answer["described_from"].startswith("complete submap of")
    travelled = float(answer["described_from"].rsplit("over ", 1)[1].split(" m")[0])
    assert travelled >= WINDOW_M - 0.6
    translation, yaw = errors(np.array([answer["x"], answer["y"], answer["yaw"]]),
                              stream.truth[round(answer["stamp"], 3)])
    assert translation < 2.0 and yaw < 5.0
    assert node.localiser.submap is not None


def test_a_robot_standing_still_is_answered_from_a_partial_window_at_the_timeout(
        ros_graph, world, submap_map):
    ros_graph.start(LocaliserNode, map_path=str(submap_map), pose_source="odom",
                    request_timeout_s=3.0, **{"search.consistency_min_support": 0})
    client = ros_graph.node.create_client(Trigger, "/localiser/relocalise")
    standing = route(300, lateral_offset_m=1.5, reverse=True)[100:101]
    with PosedStream(ros_graph, world, standing) as stream:
        reply = _call(ros_graph, client)
    assert reply.success, reply.message
    answer = json.loads(reply.message)
    assert answer["described_from"].startswith("partial submap of")
    translation, _ = errors(np.array([answer["x"], answer["y"], answer["yaw"]]),
                            stream.truth[round(answer["stamp"], 3)])
    assert translation < 2.0


def test_without_odometry_the_node_describes_single_scans(ros_graph, world, submap_map):
    node = ros_graph.start(LocaliserNode, map_path=str(submap_map))
    assert node.localiser.submap is not None
    with PosedStream(ros_graph, world, route(300)[:50], odometry=False):
        assert ros_graph.wait_for(lambda: node.counters["scans_searched"] >= 3)
    assert node.last.described_from == "single scan"
