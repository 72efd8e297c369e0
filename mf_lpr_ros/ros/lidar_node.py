"""What the LiDAR nodes share: the scan and pose inputs, checked decoding, and running a node."""

from __future__ import annotations

import math
import signal
import sys
import threading
import time
from collections import Counter
from typing import Any, Callable

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import PointCloud2

from mf_lpr_ros.errors import InvalidCloudError, InvalidPoseError, ParameterFault
from mf_lpr_ros.io.messages import pose_message_to_matrix, stamp_to_seconds
from mf_lpr_ros.io.pointcloud import decode_points
from mf_lpr_ros.live.pose_buffer import PoseBuffer
from mf_lpr_ros.ros.params import NodeParameters, pose_source_topic
from mf_lpr_ros.ros.qos import sensor_qos

_LOG_REPEAT_S = 2.0
# Longest wait before a stop request is noticed.
_SPIN_TIMEOUT_S = 0.1


class LidarNodeMixin(NodeParameters):
    """What a node fed by PointCloud2 scans and, optionally, a pose stream needs, for plain
    (rclpy Node) and managed (LifecycleNode) nodes alike: call init_lidar_state first. The
    node's settings (mf_lpr_ros/live/node_settings.py) hold its inputs in settings.inputs."""

    def init_lidar_state(self) -> None:
        self.counters: Counter[str] = Counter()
        self._last_logged: dict[str, float] = {}
        self._last_scan_stamp = -math.inf

    def finish(self) -> None:
        """Work left at shutdown (e.g. the final map save); nodes override it."""

    # --- inputs -------------------------------------------------------------------------
    def subscribe_poses(self, source: str, buffer: PoseBuffer,
                        on_pose: Callable[[], None], reliable: bool = False):
        """Subscribe to the pose source; returns the subscription."""
        topic, message_type = pose_source_topic(source)

        def received(message) -> None:
            self.counters["poses_received"] += 1
            try:
                buffer.add(stamp_to_seconds(message.header.stamp), pose_message_to_matrix(message))
                if not self.pose_frame_id:
                    self.pose_frame_id = message.header.frame_id
            except (InvalidPoseError, ValueError) as error:
                self.counters["poses_rejected"] += 1
                self.log_problem("pose", f"pose on '{topic}' rejected: {error}")
                return
            on_pose()

        self.pose_frame_id = ""
        return self.create_subscription(message_type, topic, received, sensor_qos(100, reliable))

    def decode_scan(self, message: PointCloud2) -> tuple[float, np.ndarray] | None:
        """(stamp, points) of a valid scan (as settings.inputs asks); None after logging why it
        was rejected."""
        inputs = self.settings.inputs
        expected_frame = inputs.sensor_frame_id
        future_tolerance_s = inputs.future_tolerance_s
        self.counters["scans_received"] += 1
        stamp = stamp_to_seconds(message.header.stamp)
        frame = message.header.frame_id
        problem = None
        if expected_frame and frame != expected_frame:
            problem = f"frame '{frame}' is not the configured sensor_frame_id '{expected_frame}'"
        elif stamp <= self._last_scan_stamp:
            problem = (f"stamp {stamp:.6f} is not after the previous scan's "
                       f"({self._last_scan_stamp:.6f}); out-of-order scans are dropped")
        elif future_tolerance_s > 0 and stamp > self.now_seconds() + future_tolerance_s:
            problem = (f"stamp {stamp:.3f} is more than {future_tolerance_s} s ahead of this "
                       f"node's clock ({self.now_seconds():.3f})")
        if problem is None:
            try:
                points = decode_points(message, inputs.max_points)
            except (InvalidCloudError, ValueError, TypeError) as error:
                problem = str(error)
        if problem is not None:
            self.reject_scan(stamp, problem)
            return None
        self._last_scan_stamp = stamp
        return stamp, points

    def reject_scan(self, stamp: float, problem: str) -> None:
        """A received scan is not used: counted and logged (a node may note it too)."""
        self.counters["scans_rejected"] += 1
        # No stamp in the text: log_problem repeats an identical problem only every few seconds.
        self.log_problem("scan", f"scan rejected: {problem}")

    def now_seconds(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def log_problem(self, kind: str, text: str) -> None:
        """Warn, repeating an identical problem at most every few seconds."""
        key = kind + text[:60]
        now = time.monotonic()
        if now - self._last_logged.get(key, -math.inf) >= _LOG_REPEAT_S:
            self._last_logged[key] = now
            self.get_logger().warning(text)


class LidarNode(LidarNodeMixin, Node):
    """A plain (unmanaged) node fed by PointCloud2 scans and, optionally, a pose stream."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        Node.__init__(self, name, **kwargs)
        self.init_lidar_state()


def run_node(factory: Callable[[], LidarNode], args: list[str] | None = None) -> int:
    """Build the node (parameter faults exit with status 2), spin until SIGINT or SIGTERM, then
    let the node finish (node.finish, e.g. the final save) while its context is still valid."""
    rclpy.init(args=args if args is not None else sys.argv,
               signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for signal_number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signal_number, lambda *_: stop.set())
    node = None
    try:
        try:
            node = factory()
        except ParameterFault as error:
            rclpy.logging.get_logger("mf_lpr_ros").fatal(str(error))
            return 2
        except Exception as error:  # a map that cannot be loaded, a path that cannot be used
            rclpy.logging.get_logger("mf_lpr_ros").fatal(f"{type(error).__name__}: {error}")
            return 2
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=_SPIN_TIMEOUT_S)
        return 0
    finally:
        if node is not None:
            node.finish()
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
