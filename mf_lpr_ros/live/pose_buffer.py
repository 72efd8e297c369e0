"""Pose buffering and scan-pose pairing for the live nodes, without ROS.

PoseBuffer keeps recent odometry and interpolates it at scan stamps; ScanPoseSynchroniser
holds scans until their pose is known and hands them on as PairedScans.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from mf_lpr_ros.core.pose import interpolate_poses, validate_pose
from mf_lpr_ros.errors import InvalidPoseError


class PoseBuffer:
    """A time-ordered window of recent poses, interpolated at scan stamps.

    Samples further apart than max_gap_s are not interpolated across (as offline, see
    pose.interpolate_poses). A sample implying a speed above max_speed_mps is a jump
    (relocalised odometry, a reset): the buffer restarts from it so no scan is paired with a
    pose interpolated across the jump.
    """

    def __init__(self, max_gap_s: float = 1.0, horizon_s: float = 60.0,
                 max_speed_mps: float = 30.0) -> None:
        self.max_gap_s = max_gap_s
        self.horizon_s = horizon_s
        self.max_speed_mps = max_speed_mps
        self._stamps: deque[float] = deque()
        self._poses: deque[np.ndarray] = deque()
        self.jumps = 0
        self._valid_from = -math.inf

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, stamp: float, pose: np.ndarray) -> None:
        pose = validate_pose(pose)
        if not math.isfinite(stamp):
            raise InvalidPoseError(f"pose stamp {stamp} is not finite")
        if self._stamps and stamp <= self._stamps[-1]:
            raise InvalidPoseError(f"pose stamp {stamp:.6f} is not after the previous one "
                                   f"({self._stamps[-1]:.6f}); sample ignored")
        if self._stamps:
            dt = stamp - self._stamps[-1]
            distance = float(np.linalg.norm(pose[:3, 3] - self._poses[-1][:3, 3]))
            if dt <= self.max_gap_s and distance > self.max_speed_mps * max(dt, 1e-3):
                self.jumps += 1
                self._stamps.clear()
                self._poses.clear()
                self._valid_from = stamp
        self._stamps.append(stamp)
        self._poses.append(pose)
        while self._stamps and self._stamps[0] < stamp - self.horizon_s:
            self._stamps.popleft()
            self._poses.popleft()

    def lookup(self, stamp: float, final: bool = False) -> tuple[str, np.ndarray | None]:
        """("ok", pose), ("wait", None) while a later sample may still come, or ("none", None).

        final: no later sample will come (shutdown); the end-of-stream rule applies.
        """
        if stamp < self._valid_from:
            return "none", None
        if not self._stamps:
            return ("none", None) if final else ("wait", None)
        if stamp > self._stamps[-1] and not final and stamp - self._stamps[-1] <= self.max_gap_s:
            return "wait", None
        poses, valid = interpolate_poses(np.fromiter(self._stamps, float, len(self._stamps)),
                                         np.stack(self._poses), np.array([stamp]), self.max_gap_s)
        return ("ok", poses[0]) if valid[0] else ("none", None)


@dataclass
class PairedScan:
    """A scan with its pose at its stamp (world_T_sensor, extrinsic applied)."""

    index: int
    stamp: float
    points: np.ndarray
    pose: np.ndarray
    extra: Any = None


class ScanPoseSynchroniser:
    """Pairs scans with the pose at their stamp, waiting for the pose that follows the scan.

    Scans older than the pose window, or whose pose never arrives within max_wait_s of newer
    pose samples, are dropped and counted. At most max_pending scans wait; beyond that the
    oldest is dropped.
    """

    def __init__(self, poses: PoseBuffer, extrinsic: np.ndarray | None = None,
                 max_pending: int = 50) -> None:
        self.poses = poses
        self.extrinsic = np.eye(4) if extrinsic is None else validate_pose(extrinsic, "extrinsic")
        self.max_pending = max_pending
        self._pending: deque[tuple[int, float, np.ndarray, Any]] = deque()
        self.dropped_without_pose = 0

    @property
    def pending(self) -> int:
        return len(self._pending)

    def add_scan(self, index: int, stamp: float, points: np.ndarray, extra: Any = None) -> None:
        """Queue a scan; extra travels with it (e.g. the message stamp)."""
        self._pending.append((index, stamp, points, extra))
        while len(self._pending) > self.max_pending:
            self._pending.popleft()
            self.dropped_without_pose += 1

    def ready(self, final: bool = False) -> list[PairedScan]:
        """Scans whose pose is now known, in arrival order; drops those that can have none."""
        paired = []
        while self._pending:
            index, stamp, points, extra = self._pending[0]
            status, pose = self.poses.lookup(stamp, final=final)
            if status == "wait":
                break
            self._pending.popleft()
            if status == "none":
                self.dropped_without_pose += 1
                continue
            paired.append(PairedScan(index, stamp, points, pose @ self.extrinsic, extra))
        return paired
