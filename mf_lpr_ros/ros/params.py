"""Node parameters: declared typed and checked at start-up, frozen afterwards.

declare_config gives every node the descriptor, search and spacing parameters of mf_lpr_ros.config
(a preset with explicit overrides); declare_inputs the parameters of the scan and pose inputs
that the map builder and the localiser share. A refused value raises ParameterFault, which
run_node reports and turns into exit status 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterException
from rclpy.parameter import Parameter

from mf_lpr_ros.config import Config, config_from_flat, flat_parameters, preset
from mf_lpr_ros.core.pose import check_quaternion, pose_matrix
from mf_lpr_ros.errors import ConfigError, InvalidPoseError

POSE_SOURCES = {"odom": ("odom", Odometry), "pose": ("pose", PoseStamped),
                "pose_with_covariance": ("pose", PoseWithCovarianceStamped)}
NO_POSES = "none"


class ParameterFault(ConfigError):
    """A node parameter is refused at start-up; the message names it."""


@dataclass(frozen=True)
class InputSettings:
    """The scan and pose input parameters both LiDAR nodes declare."""

    pose_source: str
    extrinsic: np.ndarray
    max_pose_gap_s: float
    max_points: int
    sensor_frame_id: str
    map_frame_id: str
    future_tolerance_s: float
    reliable: bool


class NodeParameters:
    """Parameter declaration for rclpy Node and LifecycleNode classes alike."""

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

    def declare_reliable_qos(self) -> bool:
        return self.typed_parameter(
            "reliable_qos", False, "subscribe reliably (lossless from reliable publishers such "
            "as bag replays; cannot connect to best-effort publishers)")

    def declare_inputs(self, *, pose_default: str, pose_use: str,
                       map_frame_use: str) -> InputSettings:
        """The shared input parameters. pose_default: "odom", or NO_POSES when poses are
        optional; pose_use and map_frame_use: what this node uses them for (the descriptions)."""
        sources = ([NO_POSES] if pose_default == NO_POSES else []) + sorted(POSE_SOURCES)
        positive = (lambda v: v > 0, "> 0")
        return InputSettings(
            pose_source=self.typed_parameter(
                "pose_source", pose_default, f"odom (nav_msgs/Odometry on 'odom'), pose "
                f"(PoseStamped on 'pose') or pose_with_covariance: {pose_use}",
                lambda v: v in sources, f"one of {sources}"),
            extrinsic=self.declare_extrinsic(),
            max_pose_gap_s=self.typed_parameter(
                "max_pose_gap_s", 1.0, "largest gap between pose samples interpolated across",
                *positive),
            max_points=self.typed_parameter("max_points", 2_000_000,
                                            "scans with more points are rejected", *positive),
            sensor_frame_id=self.typed_parameter(
                "sensor_frame_id", "", "accept only scans in this frame ('' = any)"),
            map_frame_id=self.typed_parameter("map_frame_id", "", map_frame_use),
            future_tolerance_s=self.typed_parameter(
                "future_tolerance_s", 60.0, "reject scans stamped further ahead of the clock "
                "(0 = no check)", lambda v: v >= 0, ">= 0"),
            reliable=self.declare_reliable_qos())
