"""The in-process ROS 2 graph the demo and the node tests run on."""

from rclpy.exceptions import InvalidHandle
from std_msgs.msg import String


def test_the_graph_spins_on_after_a_node_is_destroyed_mid_wait(ros_graph, monkeypatch):
    """RosGraph.stop destroys a node that the executor thread may be waiting on, and rclpy
    then raises InvalidHandle from that wait. The thread must spin on: if it stopped, every
    later message of the graph would be lost."""
    spin_once = ros_graph.executor.spin_once
    raised = []

    def spin_once_destroyed_mid_wait(timeout_sec=None):
        if not raised:
            raised.append(True)
            raise InvalidHandle("cannot use Destroyable because destruction was requested")
        spin_once(timeout_sec=timeout_sec)

    monkeypatch.setattr(ros_graph.executor, "spin_once", spin_once_destroyed_mid_wait)
    assert ros_graph.wait_for(lambda: bool(raised), 10.0)
    received = ros_graph.collect(String, "/graph_check")
    publisher = ros_graph.publisher(String, "/graph_check")
    ros_graph.wait_for_subscribers(publisher)
    assert ros_graph.wait_for(
        lambda: publisher.publish(String(data="still spinning")) or bool(received), 10.0)
    assert received[0].data == "still spinning"
