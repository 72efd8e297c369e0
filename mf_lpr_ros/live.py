"""The logic of the live nodes, without ROS: pose buffering, scan-pose pairing, map building
and localisation with acceptance. The rclpy nodes in mf_lpr_ros.ros only convert messages and
call these, so everything here is tested without a ROS graph.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .auto_params import SAMPLE_SCANS, auto_config, map_metadata
from .config import Config, SearchParams
from .descriptor import InvalidCloudError, describe_points, stamp_seed_key
from .map_store import ReferenceMap
from .pose import interpolate_poses, level_points, planar
from .refine import refine_match
from .search import MatchedFilterIndex, MatchResult
from .verification import MatchVerifier


class InvalidPoseError(ValueError):
    """A pose sample cannot be used; the message says why."""


def validate_pose(pose: np.ndarray, what: str = "pose") -> np.ndarray:
    """A finite 4x4 rigid transform, or InvalidPoseError naming the problem."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        raise InvalidPoseError(f"{what} must be 4x4, got shape {pose.shape}")
    if not np.isfinite(pose).all():
        raise InvalidPoseError(f"{what} holds NaN or infinite values")
    rotation = pose[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3):
        raise InvalidPoseError(f"{what} has a rotation that is not orthonormal")
    return pose


def check_quaternion(quaternion: np.ndarray, what: str = "orientation") -> None:
    """Refuse quaternions that are not finite or far from unit length (sloppy publishers within
    1 % are normalised downstream)."""
    norm = float(np.linalg.norm(quaternion))
    if not math.isfinite(norm):
        raise InvalidPoseError(f"{what} quaternion holds NaN or infinite values")
    if abs(norm - 1.0) > 0.01:
        raise InvalidPoseError(f"{what} quaternion has norm {norm:.4g}, not 1")


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
        self.out_of_order = 0
        self._valid_from = -math.inf

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_stamp(self) -> float | None:
        return self._stamps[-1] if self._stamps else None

    def add(self, stamp: float, pose: np.ndarray) -> None:
        pose = validate_pose(pose)
        if not math.isfinite(stamp):
            raise InvalidPoseError(f"pose stamp {stamp} is not finite")
        if self._stamps and stamp <= self._stamps[-1]:
            self.out_of_order += 1
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


def descriptor_points(points: np.ndarray, pose: np.ndarray | None, level: bool) -> np.ndarray:
    """Points in the descriptor's frame: levelled by the pose's roll and pitch when asked."""
    if not level:
        return points
    if pose is None:
        raise InvalidPoseError("descriptor.level needs each scan's orientation; no pose is known "
                               "at this scan's stamp (set a pose source)")
    return level_points(points, pose[:3, :3])


class MapBuilder:
    """Keeps a reference every spacing_m metres of travel and saves the map atomically.

    With preset auto (config.auto) and a new map, the first auto_params.SAMPLE_SCANS scans are
    held back until the descriptor is derived from them (auto_choice then says what was
    chosen), and then described like every later scan; an existing map keeps its parameters.
    """

    def __init__(self, config: Config, map_path: str | Path | None, *, frame_id: str = "map",
                 sensor_frame_id: str = "", keep_clouds: bool = False,
                 reference_map: ReferenceMap | None = None) -> None:
        self.map_path = None if map_path is None else Path(map_path)
        self.keep_clouds = keep_clouds
        self.auto_choice: str | None = None
        self.rejected_while_held = 0
        self._held: list[PairedScan] | None = None
        if reference_map is None:
            reference_map = ReferenceMap(config.descriptor, frame_id=frame_id,
                                         sensor_frame_id=sensor_frame_id,
                                         metadata={"source": "map_builder",
                                                   "spacing_m": config.spacing_m})
            if config.auto:
                self._held = []
        elif config.auto:
            config = replace(config, descriptor=reference_map.params, auto=False)
        else:
            reference_map.check_params(config.descriptor)
        self.config = config
        self.map = reference_map
        self.saved_references = len(reference_map)
        positions = reference_map.poses[:, :3, 3]
        self._last_position = positions[-1] if len(positions) else None

    @property
    def waiting_for_auto(self) -> bool:
        """Scans are still held back for preset auto."""
        return self._held is not None

    def offer(self, scan: PairedScan) -> int | None:
        """Adds the scan as a reference when it is spacing_m from the last one; its index or None
        (or, for preset auto, the last reference the held-back scans gave once derived)."""
        if self._held is not None:
            self._held.append(scan)
            return self.derive_auto() if len(self._held) >= SAMPLE_SCANS else None
        return self._offer(scan)

    def derive_auto(self) -> int | None:
        """Derive the descriptor from the held-back scans (preset auto) and add them; the last
        reference added or None. Nothing to do when nothing is held."""
        held = self._held
        if not held:
            return None
        try:
            resolved, profile = auto_config([scan.points for scan in held], self.config,
                                            [scan.pose[:3, :3] for scan in held])
        except InvalidCloudError:
            self._held = []
            raise
        self._held = None
        self.config = resolved
        metadata = dict(self.map.metadata, auto=map_metadata(profile, resolved.descriptor))
        self.map = ReferenceMap(resolved.descriptor, frame_id=self.map.frame_id,
                                sensor_frame_id=self.map.sensor_frame_id, metadata=metadata)
        self.auto_choice = metadata["auto"]["choice"]
        last = None
        for scan in held:
            try:
                index = self._offer(scan)
            except (InvalidCloudError, InvalidPoseError, ValueError):
                self.rejected_while_held += 1
                continue
            last = index if index is not None else last
        return last

    def _offer(self, scan: PairedScan) -> int | None:
        position = scan.pose[:3, 3]
        if self._last_position is not None and \
                np.linalg.norm(position - self._last_position) < self.config.spacing_m:
            return None
        params = self.config.descriptor
        points = descriptor_points(scan.points, scan.pose, params.level)
        occupancy = describe_points(points, params, reference=True,
                                    seed_key=stamp_seed_key(scan.stamp))
        index = self.map.append(occupancy, scan.pose, scan.stamp, scan.index,
                                points if self.keep_clouds else None)
        self._last_position = position
        return index

    @property
    def unsaved(self) -> int:
        return len(self.map) - self.saved_references

    def save(self) -> int:
        """Writes the map (temporary file, fsync, rename); returns the references now on disk.
        On failure the previous file is untouched, the in-memory map is kept, and the error
        propagates for the caller to report."""
        if self.map_path is None:
            raise RuntimeError("this map builder has no map_path to save to")
        count = len(self.map)
        self.map.save(self.map_path)
        self.saved_references = count
        return count


@dataclass
class LiveMatch:
    """One localisation attempt on a live scan."""

    stamp: float
    match: MatchResult | None
    accepted: bool
    reason: str
    descriptor_ms: float
    references_searched: int
    reference_stamp: float = math.nan
    fitness: float = math.nan
    support: int = -1
    timings_ms: dict[str, float] = field(default_factory=dict)


class Localiser:
    """Matches live scans against a map; in loop-closure mode the map grows from the scans.

    relocalise: the map is fixed (built earlier). loop_closure: each paired scan that moved
    spacing_m becomes a reference, and a query only searches references older than
    exclude_recent_s (so it cannot match the scans it was just taken with).
    A match is accepted when it passes verification.MatchVerifier: confidence, min_score,
    distinctiveness, ICP fitness (search.verify_fitness > 0) and, when odometry_known (the
    scans come with odometry poses), odometry consistency.
    """

    MODES = ("relocalise", "loop_closure")

    def __init__(self, reference_map: ReferenceMap, config: Config, *, mode: str = "relocalise",
                 exclude_recent_s: float = 30.0, min_score: float = 0.0,
                 odometry_known: bool | None = None) -> None:
        if mode not in self.MODES:
            raise ValueError(f"mode must be one of {self.MODES}, got {mode!r}")
        reference_map.check_params(config.descriptor)
        self.config = config
        self.mode = mode
        self.exclude_recent_s = exclude_recent_s
        self.min_score = min_score
        self.map = reference_map
        self.index = MatchedFilterIndex(reference_map, config.search)
        self.reference_count = len(reference_map)
        self._incoming: deque[PairedScan] = deque()
        self.rejected_references = 0
        self.last_reference_error = ""
        odometry_known = mode == "loop_closure" if odometry_known is None else odometry_known
        self.verifier = MatchVerifier(config.search, min_score=min_score,
                                      odometry_known=odometry_known)
        self.verify = config.search.verify_fitness > 0
        if self.verify:
            _require_open3d()
        if self.verify and mode == "relocalise" and not reference_map.has_clouds:
            raise ValueError("search.verify_fitness needs a map that keeps reference clouds "
                             "(build it with keep_clouds / --keep-clouds), or set it to 0")
        self._builder = MapBuilder(config, None, reference_map=reference_map,
                                   keep_clouds=self.verify) if mode == "loop_closure" else None

    @property
    def search(self) -> SearchParams:
        return self.config.search

    def add_reference(self, scan: PairedScan) -> None:
        """Loop-closure mode: queue the robot's own scan for the map (safe from any thread; the
        searching thread adds queued scans, spacing permitting, before its next search)."""
        if self._builder is None:
            raise RuntimeError("references are only added in loop_closure mode")
        self._incoming.append(scan)

    def _integrate_references(self) -> None:
        added = False
        while self._incoming:
            scan = self._incoming.popleft()
            try:
                added |= self._builder.offer(scan) is not None
            except (InvalidCloudError, InvalidPoseError, ValueError) as error:
                self.rejected_references += 1
                self.last_reference_error = f"scan at {scan.stamp:.3f} not added: {error}"
        if added:
            self.index.sync()
            self.reference_count = len(self.map)

    def localise(self, stamp: float, points: np.ndarray, pose: np.ndarray | None = None
                 ) -> LiveMatch:
        """Search the map for one scan and verify the match (pose: world_T_sensor from odometry,
        used for levelling and odometry consistency). Call it from one thread: it also adds the
        references queued by add_reference."""
        if self._builder is not None:
            self._integrate_references()
        params = self.config.descriptor
        started = time.perf_counter()
        points = descriptor_points(points, pose, params.level)
        occupancy = describe_points(points, params)
        descriptor_ms = (time.perf_counter() - started) * 1e3
        n_active = len(self.map)
        if self.mode == "loop_closure":
            n_active = int(np.searchsorted(self.map.stamps, stamp - self.exclude_recent_s,
                                           side="right"))
        match = self.index.query(occupancy, n_active) if n_active else None
        odometry = planar(pose) if pose is not None and self.verifier.consistency_active \
            else None
        verdict = self.verifier.verify(
            match, odometry, lambda found: refine_match(found, points, self.map).fitness)
        if match is None:
            return LiveMatch(stamp, None, False, verdict.reason, descriptor_ms, n_active)
        timings = {"descriptor": descriptor_ms, **match.timings_ms}
        return LiveMatch(stamp, match, verdict.accepted, verdict.reason, descriptor_ms, n_active,
                         float(self.map.stamps[match.reference_index]), verdict.fitness,
                         verdict.support, timings)

    def reference_pose(self, index: int) -> np.ndarray:
        return np.array(self.map.poses[index])


def _require_open3d() -> None:
    """Import open3d now (about a second) rather than at the first match, and fail at start-up
    when it is missing."""
    try:
        import open3d  # noqa: F401
    except ImportError as error:
        raise ValueError(f"search.verify_fitness needs open3d, which failed to import ({error}); "
                         "install open3d-cpu or set search.verify_fitness to 0") from error


def relocalised_pose(match: MatchResult, reference_pose: np.ndarray,
                     extrinsic: np.ndarray | None = None) -> np.ndarray:
    """world_T_base (4x4) from a match: planar x, y, yaw of the estimate, z of the reference,
    no roll or pitch; the sensor-to-base extrinsic (base_T_sensor) removed."""
    x, y, yaw = match.pose
    sensor = np.eye(4)
    sensor[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    sensor[:3, 3] = [x, y, reference_pose[2, 3]]
    if extrinsic is None:
        return sensor
    return sensor @ np.linalg.inv(extrinsic)


def relative_transform(match: MatchResult) -> np.ndarray:
    """reference_T_query (4x4, planar) of a match: the loop-closure constraint."""
    transform = np.eye(4)
    c, s = math.cos(match.rotation_rad), math.sin(match.rotation_rad)
    transform[:2, :2] = [[c, -s], [s, c]]
    transform[:2, 3] = match.shift_m
    return transform


def decode_points(cloud: Any, max_points: int) -> np.ndarray:
    """A PointCloud2's finite points, refusing clouds with none left."""
    from .pointcloud import pointcloud2_to_xyz

    points = pointcloud2_to_xyz(cloud, max_points=max_points)
    if len(points) == 0:
        raise InvalidCloudError("PointCloud2 holds no finite point (all NaN or infinite)")
    return points
