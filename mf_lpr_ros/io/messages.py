"""Stamps and poses read from ROS messages, for bags (rosbags' classes) and nodes (rclpy's) alike.

Both kinds of message expose the same fields (stamp.sec / stamp.nanosec, pose.position /
pose.orientation), so one implementation reads either without importing ROS.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mf_lpr_ros.core.pose import check_quaternion, pose_matrix


def stamp_to_seconds(stamp: Any) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def seconds_to_stamp_parts(seconds: float) -> tuple[int, int]:
    """(sec, nanosec) of a time in seconds, nanoseconds rounded and carried into seconds."""
    whole = math.floor(seconds)
    nanoseconds = int(round((seconds - whole) * 1e9))
    if nanoseconds >= 1_000_000_000:
        whole, nanoseconds = whole + 1, nanoseconds - 1_000_000_000
    return int(whole), nanoseconds


def pose_message_to_matrix(message: Any) -> np.ndarray:
    """world_T_child of an Odometry, PoseStamped or PoseWithCovarianceStamped; refuses NaN and
    non-unit quaternions (InvalidPoseError)."""
    pose = message.pose.pose if hasattr(message.pose, "pose") else message.pose
    q = pose.orientation
    quaternion = np.array([q.x, q.y, q.z, q.w])
    check_quaternion(quaternion)
    p = pose.position
    return pose_matrix(np.array([p.x, p.y, p.z]), quaternion)
