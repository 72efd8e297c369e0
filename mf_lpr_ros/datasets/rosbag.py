"""ROS 1 (.bag) and ROS 2 (.db3 / .mcap folder or file) bags, read with rosbags (no ROS needed).

Scans are the PointCloud2 messages of one topic; poses come from a nav_msgs/Odometry,
geometry_msgs/PoseStamped or PoseWithCovarianceStamped topic, interpolated at each cloud's
header stamp and composed with the sensor extrinsic (base_T_sensor).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from mf_lpr_ros.core.pose import interpolate_poses
from mf_lpr_ros.datasets.base import Scan, Sequence, register_loader
from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.io.messages import pose_message_to_matrix, stamp_to_seconds
from mf_lpr_ros.io.pointcloud import pointcloud2_to_xyz

BAG_SUFFIXES = (".bag", ".db3", ".mcap")
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
              "geometry_msgs/msg/PoseWithCovarianceStamped")
DEFAULT_MAX_POSE_GAP_S = 1.0


def open_bag(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY))


def _pick_topic(connections, types: tuple[str, ...], wanted: str | None, what: str,
                path: Path, required: bool) -> str | None:
    available = sorted({c.topic for c in connections if c.msgtype in types})
    if wanted is not None:
        if wanted not in {c.topic for c in connections}:
            raise DatasetError(f"{path}: no topic {wanted!r}; {what} topics: {available}")
        return wanted
    if len(available) == 1:
        return available[0]
    if not available and not required:
        return None
    raise DatasetError(f"{path}: {len(available)} {what} topics {available}; choose one")


@register_loader
class RosbagSequence(Sequence):
    layout = "a ROS bag (.bag, .db3, .mcap or a ROS 2 bag folder)"
    notes = ("read with `rosbags`; `--cloud-topic` / `--pose-topic` default to the only "
             "PointCloud2 / Odometry-or-Pose topic")
    priority = 10

    @classmethod
    def recognises(cls, path: Path) -> bool:
        if path.is_file():
            return path.suffix in BAG_SUFFIXES
        return (path / "metadata.yaml").exists() or any(path.glob("*.mcap")) or \
            any(path.glob("*.db3"))

    @classmethod
    def from_source(cls, path: Path, cloud_topic: str | None = None,
                    pose_topic: str | None = None) -> "RosbagSequence":
        return cls(path, cloud_topic, pose_topic)

    def __init__(self, path: str | Path, cloud_topic: str | None = None,
                 pose_topic: str | None = None, extrinsic: np.ndarray | None = None,
                 max_pose_gap_s: float = DEFAULT_MAX_POSE_GAP_S) -> None:
        self.path = Path(path)
        self.name = self.path.stem
        extrinsic = np.eye(4) if extrinsic is None else np.asarray(extrinsic, dtype=np.float64)
        try:
            with open_bag(self.path) as reader:
                self.cloud_topic = _pick_topic(reader.connections, (CLOUD_TYPE,), cloud_topic,
                                               "PointCloud2", self.path, required=True)
                self.pose_topic = _pick_topic(reader.connections, POSE_TYPES, pose_topic,
                                              "pose", self.path, required=False)
                self.pose_type = next((c.msgtype for c in reader.connections
                                       if c.topic == self.pose_topic), None)
                cloud_stamps, self.frame_id = self._index_clouds(reader)
                pose_stamps, poses = self._read_poses(reader)
        except DatasetError:
            raise
        except Exception as error:  # rosbags raises many types for unreadable bags
            raise DatasetError(f"cannot read bag {self.path}: {error}") from error
        if not cloud_stamps:
            raise DatasetError(f"{self.path}: no messages on {self.cloud_topic}")
        self._order = np.argsort(cloud_stamps, kind="stable")
        self.stamps = np.asarray(cloud_stamps)[self._order]
        self.poses = None
        if poses is not None:
            at_scans, valid = interpolate_poses(pose_stamps, poses, self.stamps, max_pose_gap_s)
            at_scans = at_scans @ extrinsic
            at_scans[~valid] = np.nan
            self.poses = at_scans

    def _index_clouds(self, reader) -> tuple[list[float], str]:
        stamps, frame_id = [], ""
        connections = [c for c in reader.connections if c.topic == self.cloud_topic]
        for connection, _, raw in reader.messages(connections=connections):
            message = reader.deserialize(raw, connection.msgtype)
            stamps.append(stamp_to_seconds(message.header.stamp))
            frame_id = message.header.frame_id
        return stamps, frame_id

    def _read_poses(self, reader) -> tuple[np.ndarray, np.ndarray | None]:
        if self.pose_topic is None:
            return np.zeros(0), None
        stamps, poses = [], []
        connections = [c for c in reader.connections if c.topic == self.pose_topic]
        for connection, _, raw in reader.messages(connections=connections):
            message = reader.deserialize(raw, connection.msgtype)
            try:
                poses.append(pose_message_to_matrix(message))
            except ValueError:
                continue  # an invalid quaternion: that sample is skipped, neighbours interpolate
            stamps.append(stamp_to_seconds(message.header.stamp))
        order = np.argsort(stamps, kind="stable")
        return np.asarray(stamps)[order], np.asarray(poses).reshape(-1, 4, 4)[order]

    def has_pose(self, index: int) -> bool:
        return self.poses is not None and bool(np.isfinite(self.poses[index]).all())

    def pose(self, index: int) -> np.ndarray | None:
        return self.poses[index] if self.has_pose(index) else None

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        # Bag order -> time order position, so a single pass serves any requested subset.
        position_of = np.empty_like(self._order)
        position_of[self._order] = np.arange(len(self._order))
        wanted = set(int(i) for i in indices)
        pending: dict[int, Scan] = {}
        next_index = iter(sorted(wanted))
        expected = next(next_index, None)
        with open_bag(self.path) as reader:
            connections = [c for c in reader.connections if c.topic == self.cloud_topic]
            for bag_position, (connection, _, raw) in enumerate(
                    reader.messages(connections=connections)):
                index = int(position_of[bag_position])
                if index not in wanted:
                    continue
                message = reader.deserialize(raw, connection.msgtype)
                # An empty cloud at a driver's start, a malformed one: a scan naming it.
                pending[index] = self._scan(index, lambda: {"points": pointcloud2_to_xyz(message)},
                                            f"{self.cloud_topic} message {index}")
                while expected is not None and expected in pending:
                    yield pending.pop(expected)
                    expected = next(next_index, None)
