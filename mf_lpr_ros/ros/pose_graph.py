"""pose_graph node: an example SLAM back end for the localiser's loop closures.

    ros2 run mf_lpr_ros pose_graph --ros-args -r odom:=/odometry

Subscribes to odometry (`odom`, nav_msgs/Odometry) and loop closures (`loop_closure`, the
localiser's mf_lpr format); keeps a keyframe every keyframe_spacing_m, adds each closure to a
GTSAM pose graph (mf_lpr_ros/core/pose_graph.py: a false closure is gated out), optimises, and
publishes the optimised keyframe path on `path` (nav_msgs/Path, the odometry's frame).
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from std_msgs.msg import Float64MultiArray, Header

from mf_lpr_ros.core.pose import planar, pose_matrix, quaternion_from_yaw
from mf_lpr_ros.core.pose_graph import KeyframeGraph
from mf_lpr_ros.errors import MissingDependencyError, ParameterFault
from mf_lpr_ros.io.messages import pose_message_to_matrix, stamp_to_seconds
from mf_lpr_ros.live.node_settings import PoseGraphSettings
from mf_lpr_ros.ros.lidar_node import LidarNode, run_node
from mf_lpr_ros.ros.messages import decode_loop_closure, seconds_to_stamp, set_pose
from mf_lpr_ros.ros.qos import sensor_qos


class PoseGraphNode(LidarNode):
    def __init__(self, node_name: str = "pose_graph", **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        settings = PoseGraphSettings.from_values(
            self.declare_node_parameters(PoseGraphSettings.PARAMETERS))
        self.freeze_parameters()
        try:
            self.graph = KeyframeGraph(settings.keyframe_spacing_m)
        except MissingDependencyError as error:
            raise ParameterFault(str(error)) from None
        self.frame_id = ""
        self.create_subscription(Odometry, "odom", self._on_odometry,
                                 sensor_qos(100, settings.reliable))
        self.create_subscription(Float64MultiArray, "loop_closure", self._on_closure, 100)
        self.path_pub = self.create_publisher(Path, "path", 10)
        self.create_timer(settings.publish_period_s, self._publish_path)

    def _on_odometry(self, message: Odometry) -> None:
        self.counters["odometry_received"] += 1
        try:
            pose = planar(pose_message_to_matrix(message))
            self.graph.add_odometry(stamp_to_seconds(message.header.stamp), pose)
        except ValueError as error:
            self.counters["odometry_rejected"] += 1
            self.log_problem("odometry", f"odometry rejected: {error}")
            return
        self.frame_id = self.frame_id or message.header.frame_id

    def _on_closure(self, message: Float64MultiArray) -> None:
        self.counters["closures_received"] += 1
        try:
            closure = decode_loop_closure(message)
            covariance = closure["covariance"][np.ix_([0, 1, 5], [0, 1, 5])]
            self.graph.add_closure(stamp_to_seconds(closure["query_stamp"]),
                                   stamp_to_seconds(closure["reference_stamp"]),
                                   planar(closure["reference_T_query"]), covariance)
        except ValueError as error:
            self.counters["closures_rejected"] += 1
            self.log_problem("closure", f"loop closure not used: {error}")
            return
        self.graph.optimise()
        self.counters["closures_used"] = self.graph.graph.closures_used
        self._publish_path()

    def _publish_path(self) -> None:
        estimate = self.graph.estimate
        if not len(estimate):
            return
        header = Header(stamp=seconds_to_stamp(self.graph.keyframe_stamps[-1]),
                        frame_id=self.frame_id)
        path = Path(header=header)
        for stamp, (x, y, yaw) in zip(self.graph.keyframe_stamps, estimate):
            pose = PoseStamped(header=Header(stamp=seconds_to_stamp(stamp),
                                             frame_id=self.frame_id))
            set_pose(pose.pose, pose_matrix(np.array([x, y, 0.0]), quaternion_from_yaw(yaw)))
            path.poses.append(pose)
        self.path_pub.publish(path)

    def finish(self) -> None:
        self.get_logger().info(
            f"pose_graph done: {len(self.graph.keyframe_stamps)} keyframes, "
            f"{self.counters['closures_received']} closures received, "
            f"{self.graph.graph.closures_used} used")


def main(args: list[str] | None = None) -> int:
    return run_node(PoseGraphNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
