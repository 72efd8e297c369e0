"""Loop closures over DDS as their consumers read them: LIO-SAM's two-value message with its
subscriber's QoS, and the pose_graph example back end behind the localiser."""

from __future__ import annotations

import numpy as np
import pytest
from nav_msgs.msg import Odometry, Path
from rclpy.qos import QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray

from mf_lpr_ros.core.pose import planar, pose_matrix
from mf_lpr_ros.core.pose_graph import absolute_trajectory_error
from mf_lpr_ros.errors import ParameterFault
from mf_lpr_ros.evaluation.slam import DriftModel, with_planar
from mf_lpr_ros.io.messages import stamp_to_seconds
from mf_lpr_ros.live.node_settings import LIO_SAM_TOPIC
from mf_lpr_ros.ros.localiser import LocaliserNode
from mf_lpr_ros.ros.messages import (
    decode_loop_closure,
    loop_closure_message,
    odometry_message,
    points_to_pointcloud2,
    seconds_to_stamp,
)
from mf_lpr_ros.sim.synthetic import route, scan_world

START_S = 1000.0
PERIOD_S = 0.1
EXCLUDE_RECENT_S = 5.0
# What LIO-SAM's mapOptimization subscribes with (best effort, keep last 1).
LIO_SAM_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=1,
                         reliability=QoSReliabilityPolicy.BEST_EFFORT)


@pytest.fixture(scope="module")
def two_laps(world):
    """Scans of two laps (the second 1 m aside), true poses and a drifted odometry."""
    rng = np.random.default_rng(21)
    trajectory = np.vstack([route(80), route(80, lateral_offset_m=1.0)])
    scans = [scan_world(world, x, y, yaw, rng) for x, y, yaw in trajectory]
    truth = np.stack([pose for _, pose in scans])
    drift = DriftModel(scale_error=0.02, yaw_bias_deg_per_m=0.05, seed=3)
    odometry = with_planar(truth, drift.apply(planar(truth)))
    return [points for points, _ in scans], truth, odometry


def _drive(ros_graph, localiser, scans, odometry) -> None:
    clouds = ros_graph.publisher(PointCloud2, "points")
    poses = ros_graph.publisher(Odometry, "odom")
    ros_graph.wait_for_subscribers(clouds)
    ros_graph.wait_for_subscribers(poses)
    for index, (points, pose) in enumerate(zip(scans, odometry)):
        stamp = seconds_to_stamp(START_S + index * PERIOD_S)
        poses.publish(odometry_message(stamp, "odom", "velodyne", pose))
        clouds.publish(points_to_pointcloud2(points, stamp, "velodyne"))
        searched = localiser.counters["scans_searched"]
        assert ros_graph.wait_for(lambda: localiser.counters["scans_searched"] > searched, 20)
    # The last search (and the closures it publishes, late ones included) has finished.
    assert ros_graph.wait_for(localiser.is_idle, 20)


def test_lio_sam_format_reaches_a_subscriber_configured_as_lio_sam(ros_graph, two_laps):
    scans, truth, odometry = two_laps
    localiser = ros_graph.start(LocaliserNode, preset="kitti", mode="loop_closure",
                                pose_source="odom", exclude_recent_s=EXCLUDE_RECENT_S,
                                loop_closure_format=["lio_sam", "mf_lpr"])
    lio_sam: list = []
    ros_graph.node.create_subscription(Float64MultiArray, LIO_SAM_TOPIC, lio_sam.append,
                                       LIO_SAM_QOS)
    closures = ros_graph.collect(Float64MultiArray, "loop_closure")
    _drive(ros_graph, localiser, scans, odometry)
    assert ros_graph.wait_for(lambda: len(closures) == localiser.counters["closures_published"])
    assert len(closures) >= 20
    # The first matches of the revisit, confirmed by the ones after them, are published too.
    confirmed_later = localiser.counters["closures_confirmed_later"]
    assert confirmed_later >= 2
    assert localiser.counters["closures_published"] == \
        localiser.counters["matches_accepted"] + confirmed_later
    expected = {(round(stamp_to_seconds(c["query_stamp"]), 6),
                 round(stamp_to_seconds(c["reference_stamp"]), 6)): c["reference_T_query"]
                for c in map(decode_loop_closure, closures)}
    # Best effort, depth 1: LIO-SAM may miss some; every one it gets is exactly two stamps.
    assert len(lio_sam) >= 0.8 * len(closures)
    for message in lio_sam:
        assert len(message.data) == 2 and not message.layout.dim
        query_s, reference_s = message.data
        stamps = (round(query_s, 6), round(reference_s, 6))
        assert stamps in expected
        assert query_s - reference_s >= EXCLUDE_RECENT_S
        # Both stamps are scans of this session, and the closure is geometrically true: the
        # transform published with them puts the query where it was relative to the
        # reference (a weak match vouched for may name a reference several metres away).
        query, reference = (int(round((s - START_S) / PERIOD_S)) for s in (query_s, reference_s))
        truly = np.linalg.inv(truth[reference]) @ truth[query]
        assert np.linalg.norm(expected[stamps][:2, 3] - truly[:2, 3]) < 0.5


def test_lio_sam_format_is_refused_outside_loop_closure_mode(ros_graph, tmp_path):
    with pytest.raises(ParameterFault, match="lio_sam needs mode loop_closure"):
        ros_graph.start(LocaliserNode, preset="kitti", map_path=str(tmp_path / "none.mfmap"),
                        loop_closure_format=["lio_sam"])
    with pytest.raises(ParameterFault, match="loop_closure_format"):
        ros_graph.start(LocaliserNode, preset="kitti", mode="loop_closure", pose_source="odom",
                        loop_closure_format=["rtabmap"])


def _path_planar(message: Path) -> np.ndarray:
    return np.array([planar(pose_matrix(
        np.array([p.pose.position.x, p.pose.position.y, p.pose.position.z]),
        np.array([p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z,
                  p.pose.orientation.w]))) for p in message.poses])


def test_pose_graph_node_removes_drift_and_is_not_bent_by_a_planted_closure(ros_graph,
                                                                            two_laps):
    pytest.importorskip("gtsam", reason="gtsam not installed (pip install gtsam)")
    from mf_lpr_ros.ros.pose_graph import PoseGraphNode

    scans, truth, odometry = two_laps
    localiser = ros_graph.start(LocaliserNode, preset="kitti", mode="loop_closure",
                                pose_source="odom", exclude_recent_s=EXCLUDE_RECENT_S)
    back_end = ros_graph.start(PoseGraphNode, keyframe_spacing_m=0.0, publish_period_s=0.2)
    paths = ros_graph.collect(Path, "path")
    _drive(ros_graph, localiser, scans, odometry)
    assert ros_graph.wait_for(lambda: back_end.counters["closures_received"]
                              == localiser.counters["closures_published"] >= 20)
    assert ros_graph.wait_for(lambda: paths and len(paths[-1].poses) == len(scans))
    path_stamps = [stamp_to_seconds(p.header.stamp) for p in paths[-1].poses]
    assert np.allclose(path_stamps, START_S + np.arange(len(scans)) * PERIOD_S)
    assert paths[-1].header.frame_id == "odom"
    truth_planar, odometry_planar = planar(truth), planar(odometry)
    before = absolute_trajectory_error(odometry_planar, truth_planar)
    after = absolute_trajectory_error(_path_planar(paths[-1]), truth_planar)
    assert after < before / 3, (before, after)
    # The counter counts a closure as it arrives, before the graph has taken it in.
    assert ros_graph.wait_for(lambda: back_end.graph.graph.closures_used
                              == back_end.counters["closures_received"])

    # A look-alike closure that slipped through: scan 150 "is" scan 40, 60 m away.
    planted = loop_closure_message(seconds_to_stamp(START_S + 150 * PERIOD_S), 40,
                                   START_S + 40 * PERIOD_S, np.eye(4), np.eye(3) * 0.01, 1.0, 0.9)
    received = len(paths)
    ros_graph.publisher(Float64MultiArray, "loop_closure").publish(planted)
    assert ros_graph.wait_for(lambda: back_end.counters["closures_received"]
                              == localiser.counters["closures_published"] + 1)
    assert ros_graph.wait_for(lambda: len(paths) > received + 1)
    bent = absolute_trajectory_error(_path_planar(paths[-1]), truth_planar)
    assert bent == pytest.approx(after, abs=0.05)
    assert not back_end.graph.graph.closures[-1].active
    assert np.linalg.norm(truth[150, :2, 3] - truth[40, :2, 3]) > 30
