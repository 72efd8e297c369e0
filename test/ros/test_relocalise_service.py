"""Relocalisation on request (nav2's way): the ~/relocalise Trigger service, one pose per
request with AMCL's QoS, ranked candidates, the latched last pose, and the timeout."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.qos import QoSDurabilityPolicy, QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from test_ros_nodes import errors, planar_of_message

from mf_lpr_ros.core.pose import planar
from mf_lpr_ros.io.messages import stamp_to_seconds
from mf_lpr_ros.ros.localiser import LocaliserNode
from mf_lpr_ros.ros.messages import odometry_message, points_to_pointcloud2, seconds_to_stamp

# nav2 AMCL's /initialpose subscription: reliable, volatile.
AMCL_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=10,
                      reliability=QoSReliabilityPolicy.RELIABLE,
                      durability=QoSDurabilityPolicy.VOLATILE)
LATE_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=1,
                      reliability=QoSReliabilityPolicy.RELIABLE,
                      durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)


class ScanStream:
    """Publishes the query scans round and round at ~10 Hz until stopped (each after its
    odometry, when an odometry publisher is given); remembers the truth of each stamp."""

    def __init__(self, publisher, queries, first_stamp: float = 500.0, odometry=None) -> None:
        self.publisher, self.queries, self.odometry = publisher, queries, odometry
        self.truth: dict[float, np.ndarray] = {}
        self._stamp = first_stamp
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        index = 0
        while not self._stop.wait(0.1):
            points, pose = self.queries[index % len(self.queries)]
            self.truth[round(self._stamp, 3)] = planar(pose)
            stamp = seconds_to_stamp(self._stamp)
            if self.odometry is not None:
                self.odometry.publish(odometry_message(stamp, "odom", "velodyne", pose))
            self.publisher.publish(points_to_pointcloud2(points, stamp, "velodyne"))
            self._stamp += 0.1
            index += 1

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *_):
        self._stop.set()
        self._thread.join()


def _call(ros_graph, client, timeout_s: float = 30.0) -> Trigger.Response:
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    assert ros_graph.wait_for(future.done, timeout_s)
    return future.result()


def _answer_and_errors(reply: Trigger.Response, stream: ScanStream) -> tuple[dict, float, float]:
    """A successful reply's JSON answer, and its translation and yaw errors against the truth
    of the scan it answers from."""
    assert reply.success, reply.message
    answer = json.loads(reply.message)
    translation, yaw = errors(np.array([answer["x"], answer["y"], answer["yaw"]]),
                              stream.truth[round(answer["stamp"], 3)])
    return answer, translation, yaw


def test_each_request_publishes_one_accurate_pose_with_amcls_qos(ros_graph, synthetic_map):
    path, queries = synthetic_map
    node = ros_graph.start(LocaliserNode, preset="kitti", map_path=str(path))
    assert node.settings.publish_mode == "on_request"
    poses: list = []
    ros_graph.node.create_subscription(PoseWithCovarianceStamped, "relocalisation",
                                       poses.append, AMCL_QOS)
    candidates = ros_graph.collect(PoseArray, "/localiser/candidates")
    confidences = ros_graph.collect(Float64MultiArray, "/localiser/candidate_confidences")
    client = ros_graph.node.create_client(Trigger, "/localiser/relocalise")
    publisher = ros_graph.publisher(PointCloud2, "points")
    ros_graph.wait_for_subscribers(publisher)
    with ScanStream(publisher, queries) as stream:
        assert ros_graph.wait_for(lambda: node.counters["scans_searched"] >= 10)
        assert poses == []                                   # nothing without a request
        for request in range(3):
            reply = _call(ros_graph, client)
            assert reply.success, reply.message
            answer = json.loads(reply.message)
            assert answer["verification"] == "accepted"
            assert ros_graph.wait_for(lambda: len(poses) == request + 1)
            message = poses[-1]
            assert message.header.frame_id == answer["frame_id"] == "map"
            assert stamp_to_seconds(message.header.stamp) == pytest.approx(answer["stamp"])
            truth = stream.truth[round(answer["stamp"], 3)]
            translation, yaw = errors(planar_of_message(message), truth)
            assert translation < 0.5 and yaw < 2.0
            assert np.allclose([answer["x"], answer["y"]], planar_of_message(message)[:2])
            covariance = np.array(message.pose.covariance).reshape(6, 6)
            for row, col in ((0, 0), (1, 1), (0, 1), (1, 0), (5, 5)):   # slots 0, 7, 1, 6, 35
                assert np.isfinite(covariance[row, col])
            assert covariance[0, 0] > 0 and covariance[1, 1] > 0 and covariance[5, 5] > 0
            searched = node.counters["scans_searched"]
            assert ros_graph.wait_for(lambda: node.counters["scans_searched"] >= searched + 5)
            assert len(poses) == request + 1                 # exactly once per request
    assert ros_graph.wait_for(lambda: len(candidates) >= 3 and len(confidences) >= 3)
    best = candidates[-1].poses[0]
    assert np.allclose([best.position.x, best.position.y],
                       planar_of_message(poses[-1])[:2])
    ranked = confidences[-1].data
    assert len(ranked) == len(candidates[-1].poses) >= 1
    assert confidences[-1].layout.dim[0].label == "confidence"

    # A subscriber that comes late still gets the last pose (transient local).
    late: list = []
    ros_graph.node.create_subscription(PoseWithCovarianceStamped, "relocalisation",
                                       late.append, LATE_QOS)
    assert ros_graph.wait_for(lambda: len(late) == 1, 10)
    assert late[0].header.stamp == poses[-1].header.stamp


def test_a_request_without_a_verified_match_times_out_with_a_reason(ros_graph, synthetic_map):
    path, _ = synthetic_map
    node = ros_graph.start(LocaliserNode, preset="kitti", map_path=str(path),
                           request_timeout_s=1.0)
    client = ros_graph.node.create_client(Trigger, "/localiser/relocalise")
    reply = _call(ros_graph, client)
    assert not reply.success and "request_timeout_s" in reply.message
    assert node.counters["requests_timed_out"] == 1


def test_a_robot_standing_still_is_answered_at_the_timeout_by_a_match_odometry_never_confirmed(
        ros_graph, synthetic_map):
    """A lost robot often stands still when it asks. Its matches never gather odometry support
    (supporters come from queries a metre apart), so none is verified; at request_timeout_s the
    reply gives the last match that passed every other test, publishes it once, and says
    which test it lacks."""
    path, queries = synthetic_map
    node = ros_graph.start(LocaliserNode, preset="kitti", map_path=str(path), pose_source="odom",
                           request_timeout_s=2.0)
    poses = ros_graph.collect(PoseWithCovarianceStamped, "relocalisation")
    client = ros_graph.node.create_client(Trigger, "/localiser/relocalise")
    clouds, odometry = ros_graph.publisher(PointCloud2, "points"), ros_graph.publisher(
        Odometry, "odom")
    ros_graph.wait_for_subscribers(clouds)
    ros_graph.wait_for_subscribers(odometry)
    with ScanStream(clouds, queries[4:5], odometry=odometry) as stream:
        answer, translation, yaw = _answer_and_errors(_call(ros_graph, client), stream)
    assert answer["verification"].startswith("odometry consistency: 0 earlier match(es) agree")
    assert translation < 0.5 and yaw < 2.0
    assert ros_graph.wait_for(lambda: len(poses) == 1) and node.counters["poses_published"] == 1
    assert node.counters["matches_accepted"] == 0


def test_a_request_searches_wider_where_the_candidate_stage_leaves_the_place_out(
        ros_graph, synthetic_map):
    """A robot the candidate stage fails (here the prefilter ranks the map's places in reverse
    and one candidate is searched: a wrong place, and nothing to tell it from) gets nothing
    published from its stream of scans (no closure is confirmed, so under search.prefilter_retry
    "revisits" none is searched again); a ~/relocalise call searches its scans again over the
    wider list (a request always does; here every reference) and answers with the right pose."""
    path, queries = synthetic_map
    node = ros_graph.start(LocaliserNode, preset="kitti", map_path=str(path),
                           **{"search.prefilter_top_k": 1, "search.prefilter_expand_m": 0.0})
    prefilter = node.localiser.index.prefilter
    ranking = prefilter.top
    prefilter.top = lambda image, k, stop=None: ranking(image, len(prefilter), stop)[::-1][:k]
    client = ros_graph.node.create_client(Trigger, "/localiser/relocalise")
    publisher = ros_graph.publisher(PointCloud2, "points")
    ros_graph.wait_for_subscribers(publisher)
    with ScanStream(publisher, queries) as stream:
        assert ros_graph.wait_for(lambda: node.counters["scans_searched"] >= 10)
        assert node.counters["matches_accepted"] == 0
        assert node.last.match.searched is not None and len(node.last.match.searched) == 1
        reply = _call(ros_graph, client)
        assert reply.success, reply.message
        answer = json.loads(reply.message)
        translation, yaw = errors(np.array([answer["x"], answer["y"], answer["yaw"]]),
                                  stream.truth[round(answer["stamp"], 3)])
        assert translation < 0.5 and yaw < 2.0
