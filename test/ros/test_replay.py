"""mf-lpr replay: bags onto live topics, ROS 1 bags converted to their ROS 2 form."""

from __future__ import annotations

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2

from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.io.messages import pose_message_to_matrix, stamp_to_seconds
from mf_lpr_ros.io.pointcloud import pointcloud2_to_xyz
from mf_lpr_ros.ros.replay import replay_bag

CLOUD = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"


@pytest.fixture
def ros1_bag(tmp_path, rng):
    """A ROS 1 bag with three clouds on /velodyne_points and odometry on /odom."""
    store = get_typestore(Stores.ROS1_NOETIC)
    types = store.types
    path = tmp_path / "drive.bag"
    clouds, poses = [], []
    with Writer(path) as writer:
        cloud_connection = writer.add_connection("/velodyne_points", CLOUD, typestore=store)
        odom_connection = writer.add_connection("/odom", ODOMETRY, typestore=store)
        for index in range(3):
            stamp = types["builtin_interfaces/msg/Time"](sec=100 + index, nanosec=250_000_000)
            header = types["std_msgs/msg/Header"](seq=index, stamp=stamp, frame_id="velodyne")
            points = rng.normal(0, 10, (50, 3)).astype("<f4")
            fields = [types["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
                      for i, n in enumerate("xyz")]
            cloud = types[CLOUD](header=header, height=1, width=50, fields=fields,
                                 is_bigendian=False, point_step=12, row_step=600,
                                 data=np.frombuffer(points.tobytes(), np.uint8), is_dense=True)
            position = types["geometry_msgs/msg/Point"](x=float(index), y=2.0, z=0.0)
            orientation = types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
            pose = types["geometry_msgs/msg/PoseWithCovariance"](
                pose=types["geometry_msgs/msg/Pose"](position=position, orientation=orientation),
                covariance=np.zeros(36))
            zero = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
            twist = types["geometry_msgs/msg/TwistWithCovariance"](
                twist=types["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                covariance=np.zeros(36))
            odometry = types[ODOMETRY](header=header, child_frame_id="velodyne", pose=pose,
                                       twist=twist)
            time_ns = (100 + index) * 10**9 + 250_000_000
            writer.write(cloud_connection, time_ns, store.serialize_ros1(cloud, CLOUD))
            writer.write(odom_connection, time_ns, store.serialize_ros1(odometry, ODOMETRY))
            clouds.append(points)
            poses.append(index)
    return path, clouds


def test_ros1_bag_is_replayed_as_ros2_messages(ros_graph, ros1_bag):
    path, clouds = ros1_bag
    received = ros_graph.collect(PointCloud2, "/velodyne_points")
    odometry = ros_graph.collect(Odometry, "/odom")
    report = replay_bag(path, rate=20.0, node=ros_graph.node, wait_for_subscribers=1,
                        progress=False)
    assert report.published == {"/velodyne_points": 3, "/odom": 3}
    assert ros_graph.wait_for(lambda: len(received) == 3 and len(odometry) == 3, 10)
    for index, message in enumerate(received):
        assert stamp_to_seconds(message.header.stamp) == pytest.approx(100.25 + index)
        assert message.header.frame_id == "velodyne"
        assert np.array_equal(pointcloud2_to_xyz(message), clouds[index])
    assert [pose_message_to_matrix(m)[0, 3] for m in odometry] == [0.0, 1.0, 2.0]


def test_replay_names_missing_topics(ros_graph, ros1_bag):
    with pytest.raises(DatasetError, match="/lidar"):
        replay_bag(ros1_bag[0], topics=["/lidar"], node=ros_graph.node, progress=False)
    with pytest.raises(ValueError, match="rate"):
        replay_bag(ros1_bag[0], rate=0.0, node=ros_graph.node, progress=False)


def test_replay_command_line(ros1_bag, capsys):
    from mf_lpr_ros.cli import main

    assert main(["replay", str(ros1_bag[0]), "--rate", "50", "--quiet", "--topics",
                 "/velodyne_points", "--ros-args", "-r", "__node:=replayer"]) == 0
    printed = capsys.readouterr().out
    assert "published 3 messages on /velodyne_points" in printed and "/odom" not in printed
