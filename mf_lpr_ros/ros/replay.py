"""Replays a ROS 1 or ROS 2 bag onto live topics with rclpy, paced by the bag's timestamps.

ROS 2 messages are published as they are stored (CDR bytes); ROS 1 messages are converted to
their ROS 2 Jazzy form first. Header stamps are kept, as `ros2 bag play` does.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import rclpy
from rclpy.node import Node

from mf_lpr_ros.datasets.rosbag import CLOUD_TYPE, POSE_TYPES, open_bag
from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.progress import progress_bar
from mf_lpr_ros.ros.qos import sensor_qos, wait_for_subscribers

DEFAULT_TYPES = (CLOUD_TYPE, *POSE_TYPES, "tf2_msgs/msg/TFMessage")


@dataclass
class ReplayReport:
    published: dict[str, int] = field(default_factory=dict)
    skipped_topics: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0


def message_class(msgtype: str):
    """The rclpy message class of 'pkg/msg/Name', or None when that package is not installed."""
    package, _, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        return None


def replay_bag(path: str | Path, *, topics: list[str] | None = None, rate: float = 1.0,
               wait_for_subscribers: int = 0, wait_timeout_s: float = 30.0,
               node: Node | None = None, progress: bool = True) -> ReplayReport:
    """Publish the bag's messages (the given topics, or its clouds and poses) on their topics.

    rate: speed-up over real time. wait_for_subscribers: before starting, wait (at most
    wait_timeout_s) until every replayed topic has this many subscribers. rclpy must be
    initialised; a node is created when none is given.
    """
    if rate <= 0:
        raise ValueError(f"rate must be > 0, got {rate}")
    from rosbags.typesys import Stores, get_typestore

    jazzy = get_typestore(Stores.ROS2_JAZZY)
    own_node = node is None
    node = node or rclpy.create_node("mf_lpr_replay")
    report = ReplayReport()
    qos = sensor_qos(100, reliable=True)
    try:
        with open_bag(Path(path)) as reader:
            by_topic = {c.topic: c for c in reader.connections}
            if topics:
                missing = [t for t in topics if t not in by_topic]
                if missing:
                    raise DatasetError(f"{path}: no topic(s) {missing}; the bag has "
                                       f"{sorted(by_topic)}")
                chosen = [by_topic[t] for t in topics]
            else:
                chosen = [c for c in reader.connections if c.msgtype in DEFAULT_TYPES]
            publishers = {}
            for connection in chosen:
                cls = message_class(connection.msgtype)
                if cls is None:
                    report.skipped_topics[connection.topic] = (
                        f"{connection.msgtype} is not installed in this ROS environment")
                    continue
                if connection.topic not in publishers:
                    publishers[connection.topic] = node.create_publisher(cls, connection.topic, qos)
            if not publishers:
                raise DatasetError(f"{path}: nothing to replay (topics: {sorted(by_topic)}; "
                                   f"skipped: {report.skipped_topics})")
            for topic, reason in report.skipped_topics.items():
                node.get_logger().warning(f"not replaying {topic}: {reason}")
            _wait_for_subscribers(publishers, wait_for_subscribers, wait_timeout_s, node)
            ros1 = reader.is2 is False
            connections = [c for c in chosen if c.topic in publishers]
            total = sum(c.msgcount for c in connections)
            started, first = time.monotonic(), None
            for connection, timestamp, raw in progress_bar(reader.messages(connections=connections),
                                                           total=total, desc="replay", unit="msg",
                                                           enabled=progress):
                first = timestamp if first is None else first
                delay = (timestamp - first) * 1e-9 / rate - (time.monotonic() - started)
                if delay > 0:
                    time.sleep(delay)
                data = raw
                if ros1:
                    message = reader.deserialize(raw, connection.msgtype)
                    data = jazzy.serialize_cdr(message, connection.msgtype)
                publishers[connection.topic].publish(bytes(data))
                report.published[connection.topic] = report.published.get(connection.topic, 0) + 1
            report.seconds = time.monotonic() - started
    finally:
        if own_node:
            node.destroy_node()
    return report


def replay_with_own_context(path: str | Path, ros_args: list[str], **options
                            ) -> ReplayReport | None:
    """replay_bag with rclpy initialised (with ros_args: remappings...) and shut down around it;
    None when interrupted (Ctrl-C)."""
    rclpy.init(args=["mf_lpr_replay", *(["--ros-args", *ros_args] if ros_args else [])])
    try:
        return replay_bag(path, **options)
    except KeyboardInterrupt:
        return None
    finally:
        if rclpy.ok():
            rclpy.shutdown()


def _wait_for_subscribers(publishers: dict, count: int, timeout_s: float, node: Node) -> None:
    if count > 0 and not wait_for_subscribers(publishers.values(), count, timeout_s):
        waiting = {t: p.get_subscription_count() for t, p in publishers.items()}
        node.get_logger().warning(f"replaying without every subscriber after {timeout_s} s: "
                                  f"{waiting}")
