"""The map_builder and localiser nodes on real rclpy over Fast DDS."""

from __future__ import annotations

import math

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Float64MultiArray

from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import planar, pose_matrix, wrap_angle
from mf_lpr_ros.errors import ParameterFault
from mf_lpr_ros.ros.localiser import LocaliserNode
from mf_lpr_ros.ros.map_builder import MapBuilderNode
from mf_lpr_ros.ros.messages import (
    decode_loop_closure,
    odometry_message,
    points_to_pointcloud2,
    seconds_to_stamp,
)
from mf_lpr_ros.sim.synthetic import route, scan_world


def planar_of_message(message: PoseWithCovarianceStamped) -> np.ndarray:
    p, q = message.pose.pose.position, message.pose.pose.orientation
    return planar(pose_matrix(np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w])))


def errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return (float(np.hypot(*(estimate[:2] - truth[:2]))),
            abs(math.degrees(float(wrap_angle(estimate[2] - truth[2])))))


def test_relocalise_mode_publishes_accurate_poses_and_closures(ros_graph, synthetic_map):
    path, queries = synthetic_map
    node = ros_graph.start(LocaliserNode, preset="kitti", map_path=str(path),
                           publish_mode="continuous")
    poses = ros_graph.collect(PoseWithCovarianceStamped, "relocalisation")
    closures = ros_graph.collect(Float64MultiArray, "loop_closure")
    publisher = ros_graph.publisher(PointCloud2, "points")
    ros_graph.wait_for_subscribers(publisher)
    reference_map = ReferenceMap.load(path)
    for index, (points, truth) in enumerate(queries):
        publisher.publish(points_to_pointcloud2(points, seconds_to_stamp(500.0 + index),
                                                "velodyne"))
        assert ros_graph.wait_for(lambda: len(poses) == index + 1 and len(closures) == index + 1)
        message = poses[-1]
        assert message.header.frame_id == "map"
        assert message.header.stamp == seconds_to_stamp(500.0 + index)
        translation, yaw = errors(planar_of_message(message), planar(truth))
        assert translation < 0.5 and yaw < 2.0
        covariance = np.array(message.pose.covariance).reshape(6, 6)
        assert covariance[0, 0] > 0 and covariance[1, 1] > 0 and covariance[5, 5] > 0
        assert np.allclose(covariance, covariance.T)

        closure = decode_loop_closure(closures[-1])
        assert closure["query_stamp"] == message.header.stamp
        reference = closure["reference_index"]
        expected = seconds_to_stamp(float(reference_map.stamps[reference]))
        assert closure["reference_stamp"] == expected
        composed = reference_map.poses[reference] @ closure["reference_T_query"]
        assert errors(planar(composed), planar_of_message(message))[0] < 1e-3
        assert 0.45 <= closure["confidence"] <= 1.0
    # The search thread counts a match after publishing it.
    assert ros_graph.wait_for(lambda: node.counters["matches_accepted"] == len(queries))


def _relocaliser(ros_graph, map_path):
    """A relocalise-mode localiser on map_path, its published poses, a publisher of scans."""
    node = ros_graph.start(LocaliserNode, preset="kitti", map_path=str(map_path),
                           publish_mode="continuous")
    poses = ros_graph.collect(PoseWithCovarianceStamped, "relocalisation")
    publisher = ros_graph.publisher(PointCloud2, "points")
    ros_graph.wait_for_subscribers(publisher)
    return node, poses, publisher


def _cloud(points: np.ndarray, stamp: float, *, dtype: str = "<f4", extra_bytes: int = 0,
           fields: str = "xyz", big_endian: bool = False) -> PointCloud2:
    """A PointCloud2 with a chosen coordinate type, byte order and padding per point."""
    size = np.dtype(dtype).itemsize
    point_step = 3 * size + extra_bytes
    records = np.zeros((len(points), point_step), dtype=np.uint8)
    for axis in range(3):
        records[:, axis * size:(axis + 1) * size] = np.ascontiguousarray(
            points[:, axis].astype(dtype)).view(np.uint8).reshape(-1, size)
    datatype = PointField.FLOAT64 if size == 8 else PointField.FLOAT32
    message = PointCloud2(height=1, width=len(points), point_step=point_step,
                          row_step=point_step * len(points), is_bigendian=big_endian,
                          data=records.tobytes(), is_dense=False)
    message.header.stamp = seconds_to_stamp(stamp)
    message.header.frame_id = "velodyne"
    message.fields = [PointField(name=name, offset=i * size, datatype=datatype, count=1)
                      for i, name in enumerate(fields)]
    return message


def test_hostile_clouds_are_rejected_and_the_localiser_keeps_answering(ros_graph, synthetic_map):
    path, queries = synthetic_map
    node, poses, publisher = _relocaliser(ros_graph, path)
    points, truth = queries[3]
    stamp = iter(np.arange(1000.0, 2000.0))

    bad = [
        _cloud(points, next(stamp), fields="ayz"),                      # no x field
        _cloud(np.full((500, 3), np.nan, np.float32), next(stamp)),     # NaN only
        _cloud(points[:0], next(stamp)),                                # empty
    ]
    short_step = _cloud(points, next(stamp))
    short_step.point_step = 8                                           # smaller than the fields
    truncated = _cloud(points, next(stamp))
    truncated.data = bytes(truncated.data[: len(truncated.data) // 2])  # data shorter than layout
    bad += [short_step, truncated]
    for index, message in enumerate(bad):
        publisher.publish(message)
        assert ros_graph.wait_for(lambda: node.counters["scans_rejected"] == index + 1), \
            f"hostile cloud {index} was not rejected"
    assert not poses

    far = np.random.default_rng(0).uniform(200, 400, (1_000_000, 3)).astype(np.float32)
    valid = [_cloud(points, next(stamp), big_endian=True, dtype=">f4"),  # big-endian
             _cloud(points, next(stamp), dtype="<f8"),                   # float64 coordinates
             _cloud(points, next(stamp), extra_bytes=10),                # unaligned padding
             _cloud(np.vstack([points, far]), next(stamp))]              # 1M points
    for index, message in enumerate(valid):
        publisher.publish(message)
        assert ros_graph.wait_for(lambda: len(poses) == index + 1), \
            f"valid cloud {index} unanswered"
        translation, yaw = errors(planar_of_message(poses[-1]), planar(truth))
        assert translation < 0.5 and yaw < 2.0
    assert node.counters["scans_rejected"] == len(bad)


def test_newest_scan_only_under_a_burst(ros_graph, synthetic_map):
    path, queries = synthetic_map
    node, poses, publisher = _relocaliser(ros_graph, path)
    messages = [points_to_pointcloud2(queries[i % len(queries)][0], seconds_to_stamp(3000.0 + i),
                                      "velodyne") for i in range(40)]
    for message in messages:
        publisher.publish(message)
    last_stamp = messages[-1].header.stamp
    assert ros_graph.wait_for(lambda: poses and poses[-1].header.stamp == last_stamp, 60)
    ros_graph.wait_for(lambda: False, 0.5)
    searched, dropped = node.counters["scans_searched"], node.counters["scans_dropped"]
    assert dropped > 0 and searched < 40
    assert searched + dropped == node.counters["scans_received"]


def test_loop_closure_mode_grows_its_map_from_posed_scans(ros_graph, world):
    node = ros_graph.start(LocaliserNode, preset="kitti", mode="loop_closure",
                           pose_source="odom", exclude_recent_s=20.0)
    closures = ros_graph.collect(Float64MultiArray, "loop_closure")
    clouds = ros_graph.publisher(PointCloud2, "points")
    odometry = ros_graph.publisher(Odometry, "odom")
    ros_graph.wait_for_subscribers(clouds)
    ros_graph.wait_for_subscribers(odometry)
    rng = np.random.default_rng(4)
    laps = np.vstack([route(30), route(30)[:8]])      # a lap, then the start again
    for index, (x, y, yaw) in enumerate(laps):
        points, pose = scan_world(world, x, y, yaw, rng)
        stamp = seconds_to_stamp(10.0 + index)
        clouds.publish(points_to_pointcloud2(points, stamp, "velodyne"))
        odometry.publish(odometry_message(stamp, "odom", "velodyne", pose))
        assert ros_graph.wait_for(lambda: node.counters["scans_searched"] +
                                  node.counters["scans_dropped"] >= index + 1)
    ros_graph.wait_for(lambda: False, 0.5)
    decoded = [decode_loop_closure(c) for c in closures]
    revisits_closed = {c["query_stamp"].sec - 10 for c in decoded} & set(range(30, len(laps)))
    assert len(revisits_closed) >= 6
    for closure in decoded:
        query_index = closure["query_stamp"].sec - 10
        reference_index = closure["reference_stamp"].sec - 10
        assert query_index - reference_index >= 20     # exclude_recent_s respected
        truth = np.linalg.inv(scan_pose(laps[reference_index])) @ scan_pose(laps[query_index])
        translation, yaw = errors(planar(closure["reference_T_query"]), planar(truth))
        assert translation < 0.5 and yaw < 2.0
    assert node.localiser.reference_count == len(laps)  # every scan moved >= 2 m: a reference


def scan_pose(xy_yaw: np.ndarray) -> np.ndarray:
    x, y, yaw = xy_yaw
    return pose_matrix(np.array([x, y, 0.0]), np.array([0, 0, math.sin(yaw / 2),
                                                        math.cos(yaw / 2)]))


@pytest.mark.parametrize("overrides,name", [
    ({"search.top_n": 0}, "top_n"),
    ({"descriptor.voxel_size": -1.0}, "voxel_size"),
    ({"mode": "guess"}, "mode"),
    ({"mode": "loop_closure"}, "pose_source"),
    ({"map_path": ""}, "map_path"),
    ({"extrinsic": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0]}, "extrinsic"),
    ({"preset": "mars"}, "preset"),
    ({"preset": "auto", "mode": "loop_closure", "pose_source": "odom"}, "preset: auto"),
    ({"descriptor.voxel_size": 0.5}, "voxel_size: map has 0.4"),
])
def test_bad_parameters_are_refused_by_name(ros_graph, synthetic_map, overrides, name):
    parameters = {"preset": "kitti", "map_path": str(synthetic_map[0]), **overrides}
    with pytest.raises(ParameterFault, match=name):
        ros_graph.start(LocaliserNode, **parameters)


def test_map_builder_refuses_to_overwrite_unless_told(ros_graph, synthetic_map, tmp_path):
    with pytest.raises(ParameterFault, match="if_exists"):
        ros_graph.start(MapBuilderNode, map_path=str(synthetic_map[0]))
    with pytest.raises(ParameterFault, match="pose_source"):
        ros_graph.start(MapBuilderNode, map_path=str(tmp_path / "m.mfmap"), pose_source="gps")


def test_reliable_qos_receives_from_reliable_publishers_only(ros_graph, synthetic_map):
    path, queries = synthetic_map
    node = ros_graph.start(LocaliserNode, preset="kitti", map_path=str(path), reliable_qos=True,
                           publish_mode="continuous")
    poses = ros_graph.collect(PoseWithCovarianceStamped, "relocalisation")
    best_effort = ros_graph.publisher(PointCloud2, "points", reliable=False)
    reliable = ros_graph.publisher(PointCloud2, "points", reliable=True)
    ros_graph.wait_for_subscribers(reliable)
    assert best_effort.get_subscription_count() == 0    # incompatible QoS: never connected
    reliable.publish(points_to_pointcloud2(queries[0][0], seconds_to_stamp(7000.0), "velodyne"))
    assert ros_graph.wait_for(lambda: len(poses) == 1)
    assert node.counters["scans_received"] == 1


def test_stamps_and_frames_that_do_not_fit_are_refused(ros_graph, synthetic_map):
    path, queries = synthetic_map
    node = ros_graph.start(LocaliserNode, preset="kitti", map_path=str(path),
                           sensor_frame_id="velodyne", publish_mode="continuous")
    poses = ros_graph.collect(PoseWithCovarianceStamped, "relocalisation")
    publisher = ros_graph.publisher(PointCloud2, "points")
    ros_graph.wait_for_subscribers(publisher)
    points = queries[0][0]
    cases = [(points_to_pointcloud2(points, seconds_to_stamp(100.0), "velodyne"), True),
             (points_to_pointcloud2(points, seconds_to_stamp(99.0), "velodyne"), False),   # older
             (points_to_pointcloud2(points, seconds_to_stamp(101.0), "os_lidar"), False),  # frame
             (points_to_pointcloud2(points, seconds_to_stamp(node.now_seconds() + 3600),
                                    "velodyne"), False),                                   # future
             (points_to_pointcloud2(points, seconds_to_stamp(102.0), "velodyne"), True)]
    for index, (message, valid) in enumerate(cases):
        publisher.publish(message)
        answered = sum(v for _, v in cases[:index + 1])
        assert ros_graph.wait_for(lambda: len(poses) == answered
                                  and node.counters["scans_received"] == index + 1)
    ros_graph.wait_for(lambda: False, 0.3)
    assert node.counters["scans_rejected"] == 3 and len(poses) == 2
