"""Submaps through the localiser node: ~/relocalise waits until the window is complete (or its
timeout) and says which it used; without odometry the node describes single scans."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from test_relocalise_service import ScanStream, _answer_and_errors, _call

from mf_lpr_ros.config import preset
from mf_lpr_ros.live.localiser import UNLEVELLED
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.live.pose_buffer import PairedScan
from mf_lpr_ros.ros.localiser import LocaliserNode
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


def posed_stream(ros_graph, world, trajectory: np.ndarray, odometry: bool = True) -> ScanStream:
    """Sparse scans along trajectory, streamed with their odometry (or without)."""
    rng = np.random.default_rng(2)
    scans = [scan_world(world, x, y, yaw, rng, dropout=SPARSE_DROPOUT) for x, y, yaw in trajectory]
    clouds = ros_graph.publisher(PointCloud2, "points")
    ros_graph.wait_for_subscribers(clouds)
    odometry_publisher = ros_graph.publisher(Odometry, "odom") if odometry else None
    if odometry_publisher is not None:
        ros_graph.wait_for_subscribers(odometry_publisher)
    return ScanStream(clouds, scans, odometry=odometry_publisher)


def test_a_request_is_answered_from_a_complete_window(ros_graph, world, submap_map):
    node = ros_graph.start(LocaliserNode, map_path=str(submap_map), pose_source="odom",
                           request_timeout_s=60.0)
    client = ros_graph.node.create_client(Trigger, "/localiser/relocalise")
    moving = route(300, lateral_offset_m=1.5, reverse=True)
    with posed_stream(ros_graph, world, moving) as stream:
        answer, translation, yaw = _answer_and_errors(_call(ros_graph, client, timeout_s=90.0),
                                                      stream)
    assert answer["described_from"].startswith("complete submap of")
    travelled = float(answer["described_from"].rsplit("over ", 1)[1].split(" m")[0])
    assert travelled >= WINDOW_M - 0.6
    assert translation < 2.0 and yaw < 5.0
    assert node.localiser.submap is not None


def test_a_robot_standing_still_is_answered_from_a_partial_window_at_the_timeout(
        ros_graph, world, submap_map):
    ros_graph.start(LocaliserNode, map_path=str(submap_map), pose_source="odom",
                    request_timeout_s=3.0, **{"search.consistency_min_support": 0})
    client = ros_graph.node.create_client(Trigger, "/localiser/relocalise")
    standing = np.repeat(route(300, lateral_offset_m=1.5, reverse=True)[100:101], 30, axis=0)
    with posed_stream(ros_graph, world, standing) as stream:
        answer, translation, _ = _answer_and_errors(_call(ros_graph, client), stream)
    assert answer["described_from"].startswith("partial submap of")
    assert translation < 2.0


def test_without_odometry_the_node_describes_single_scans(ros_graph, world, submap_map):
    node = ros_graph.start(LocaliserNode, map_path=str(submap_map))
    assert node.localiser.submap is not None
    with posed_stream(ros_graph, world, route(300)[:50], odometry=False):
        assert ros_graph.wait_for(lambda: node.counters["scans_searched"] >= 3)
    assert node.last.described_from == "single scan"


def test_without_odometry_a_livox_map_is_searched_with_single_unlevelled_scans(
        ros_graph, world, tmp_path):
    """The livox preset levels its submaps: a node given no pose_source used to refuse to
    start; it now describes each scan alone and as the sensor held it, and says so."""
    path = tmp_path / "livox.mfmap"
    builder = MapBuilder(preset("livox"), path)
    rng = np.random.default_rng(1)
    for index, (x, y, yaw) in enumerate(route(300)):
        points, pose = scan_world(world, x, y, yaw, rng, dropout=SPARSE_DROPOUT)
        builder.offer(PairedScan(index, 10.0 + 0.1 * index, points, pose))
    builder.save()
    node = ros_graph.start(LocaliserNode, map_path=str(path))
    assert node.localiser.map.params.level and node.localiser.submap is not None
    with posed_stream(ros_graph, world, route(300)[:50], odometry=False):
        assert ros_graph.wait_for(lambda: node.counters["scans_searched"] >= 3)
    assert node.last.described_from == "single scan" + UNLEVELLED
