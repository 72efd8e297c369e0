"""What both nodes share: parameters, the scan and pose inputs, and checked decoding."""

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
from rclpy.signals import SignalHandlerOptions
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from mf_lpr_ros.config import Config, config_from_flat, flat_parameters, preset
from mf_lpr_ros.errors import ConfigError
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.errors import InvalidPoseError
from mf_lpr_ros.live.pose_buffer import PoseBuffer
from mf_lpr_ros.core.pose import check_quaternion
from mf_lpr_ros.core.pose import pose_matrix
from mf_lpr_ros.ros.messages import pose_message_to_matrix, stamp_to_seconds

POSE_SOURCES = {"odom": ("odom", Odometry), "pose": ("pose", PoseStamped),
                "pose_with_covariance": ("pose", PoseWithCovarianceStamped)}
_LOG_REPEAT_S = 2.0
# Longest wait before a stop request is noticed.
_SPIN_TIMEOUT_S = 0.1


def sensor_qos(depth: int, reliable: bool = False) -> QoSProfile:
    """Best effort by default: it matches sensor drivers (best effort) and recorders (reliable)
    alike, but drops messages under load. Reliable loses nothing from reliable publishers
    (bag replays, most drivers) and cannot connect to best-effort ones."""
    return QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=QoSReliabilityPolicy.RELIABLE if reliable
                      else QoSReliabilityPolicy.BEST_EFFORT)


class ParameterFault(ConfigError):
    """A node parameter is refused at start-up; the message names it."""


class LidarNodeMixin:
    """What a node fed by PointCloud2 scans and, optionally, a pose stream needs, for plain
    (rclpy Node) and managed (LifecycleNode) nodes alike: call init_lidar_state first."""

    def init_lidar_state(self) -> None:
        self.counters: Counter[str] = Counter()
        self._last_logged: dict[str, float] = {}
        self._last_scan_stamp = -math.inf

    def finish(self) -> None:
        """Work left at shutdown (e.g. the final map save); nodes override it."""

    # --- parameters -------------------------------------------------------------------
    def declare_config(self) -> tuple[Config, dict[str, Any]]:
        """The preset named by 'preset' with every 'descriptor.*', 'search.*' and 'spacing_m'
        parameter given explicitly (params file or --ros-args -p) applied on top. Returns the
        config and the explicit values; effective values are written back for `ros2 param`."""
        preset_name = self.typed_parameter("preset", "default", "parameter preset (config/*.yaml)")
        try:
            base = preset(preset_name)
        except ConfigError as error:
            raise ParameterFault(str(error)) from None
        explicit: dict[str, Any] = {}
        for name in flat_parameters(base):
            self.declare_parameter(name, None, ParameterDescriptor(
                dynamic_typing=True, description="see mf_lpr_ros/config.py"))
            value = self.get_parameter(name).value
            if value is not None:
                explicit[name] = list(value) if isinstance(value, (list, tuple)) else value
        try:
            config = config_from_flat(explicit, base)
        except ConfigError as error:
            raise ParameterFault(str(error)) from None
        self.set_parameters([Parameter(name, value=value)
                             for name, value in flat_parameters(config).items()])
        return config, explicit

    def typed_parameter(self, name: str, default: Any, description: str,
                        check: Callable[[Any], bool] | None = None,
                        expectation: str = "") -> Any:
        try:
            value = self.declare_parameter(
                name, default, ParameterDescriptor(description=description)).value
        except ParameterException as error:
            raise ParameterFault(f"parameter {name}: {error}") from None
        if check is not None and not check(value):
            raise ParameterFault(f"parameter {name} must be {expectation}, got {value!r}")
        return value

    def declare_extrinsic(self) -> np.ndarray:
        values = self.typed_parameter(
            "extrinsic", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            "base_T_sensor as [x, y, z, qx, qy, qz, qw]: the sensor's pose on the robot",
            lambda v: len(v) == 7 and all(math.isfinite(x) for x in v),
            "7 finite numbers [x, y, z, qx, qy, qz, qw]")
        try:
            check_quaternion(np.array(values[3:]), "extrinsic")
        except InvalidPoseError as error:
            raise ParameterFault(f"parameter extrinsic: {error}") from None
        return pose_matrix(np.array(values[:3]), np.array(values[3:]))

    def freeze_parameters(self) -> None:
        """Parameters are read at start-up; refuse later changes instead of ignoring them."""
        self.add_on_set_parameters_callback(lambda _: SetParametersResult(
            successful=False, reason="mf_lpr_ros reads its parameters at start-up; restart "
                                     "the node to change them"))

    # --- inputs -------------------------------------------------------------------------
    def declare_reliable_qos(self) -> bool:
        return self.typed_parameter(
            "reliable_qos", False, "subscribe reliably (lossless from reliable publishers such "
            "as bag replays; cannot connect to best-effort publishers)")

    def subscribe_poses(self, source: str, buffer: PoseBuffer,
                        on_pose: Callable[[], None], reliable: bool = False):
        """Subscribe to the pose source; returns the subscription."""
        topic, message_type = POSE_SOURCES[source]

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

    def decode_scan(self, message: PointCloud2, max_points: int, expected_frame: str,
                    future_tolerance_s: float) -> tuple[float, np.ndarray] | None:
        """(stamp, points) of a valid scan; None after logging why it was rejected."""
        from mf_lpr_ros.io.pointcloud import decode_points

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
                points = decode_points(message, max_points)
            except (InvalidCloudError, ValueError, TypeError) as error:
                problem = str(error)
        if problem is not None:
            self.counters["scans_rejected"] += 1
            self.log_problem("scan", f"scan rejected: {problem}")
            return None
        self._last_scan_stamp = stamp
        return stamp, points

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
