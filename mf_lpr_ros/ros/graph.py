"""An in-process ROS 2 graph: its own rclpy context, an executor thread, our nodes and a driver
node that publishes and collects over Fast DDS. The demo and the tests drive the nodes with it
exactly as separate processes would (no intra-process shortcuts)."""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

import rclpy
from rclpy.context import Context
from rclpy.exceptions import InvalidHandle
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from mf_lpr_ros.ros.qos import sensor_qos, wait_for_subscribers


class RosGraph:
    def __init__(self, ros_args: list[str] | None = None) -> None:
        """ros_args: rclpy arguments for every node here (e.g. --ros-args -r points:=/lidar)."""
        self.context = Context()
        rclpy.init(args=["mf_lpr", *(ros_args or [])], context=self.context)
        self.node = rclpy.create_node("mf_lpr_driver", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.nodes: list[Any] = []
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except InvalidHandle:
                # stop() destroyed a node this wait held: the next wait leaves it out.
                continue
            except Exception:  # the context shut down mid-wait
                if self.context.ok():
                    raise

    def start(self, node_class, **parameters: Any):
        """A node of ours with parameter overrides, spinning on this graph."""
        node = node_class(context=self.context, parameter_overrides=[
            Parameter(name, value=value) for name, value in parameters.items()])
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def publisher(self, message_type, topic: str, reliable: bool = True):
        return self.node.create_publisher(message_type, topic, sensor_qos(100, reliable))

    def collect(self, message_type, topic: str) -> list:
        received: list = []
        self.node.create_subscription(message_type, topic, received.append,
                                      sensor_qos(100, reliable=True))
        return received

    @staticmethod
    def wait_for(predicate: Callable[[], bool], timeout_s: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.02)
        return predicate()

    def wait_for_subscribers(self, publisher, count: int = 1, timeout_s: float = 15.0) -> None:
        assert wait_for_subscribers([publisher], count, timeout_s), \
            f"no subscriber on {publisher.topic_name} after {timeout_s} s"

    def stop(self, node) -> None:
        """Finish a node (its shutdown work) and remove it from the graph."""
        self.executor.remove_node(node)
        node.finish()
        node.destroy_node()
        self.nodes.remove(node)

    def close(self) -> None:
        for node in list(self.nodes):
            self.stop(node)
        self.node.destroy_node()
        self.context.shutdown()
        self._thread.join(timeout=5)
        self.executor.shutdown()
