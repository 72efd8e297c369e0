"""The managed (lifecycle) localiser driven through the lifecycle_msgs services, as nav2's
lifecycle manager drives it."""

from __future__ import annotations

from geometry_msgs.msg import PoseWithCovarianceStamped
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from sensor_msgs.msg import PointCloud2
from test_ros_nodes import errors, planar_of_message

from mf_lpr_ros.core.pose import planar
from mf_lpr_ros.ros.managed_localiser import ManagedLocaliserNode
from mf_lpr_ros.ros.messages import points_to_pointcloud2, seconds_to_stamp


class Lifecycle:
    """Calls a node's lifecycle services from the test's driver node."""

    def __init__(self, ros_graph, node_name: str) -> None:
        self.graph = ros_graph
        self.change = ros_graph.node.create_client(ChangeState, f"/{node_name}/change_state")
        self.get = ros_graph.node.create_client(GetState, f"/{node_name}/get_state")
        assert self.change.wait_for_service(timeout_sec=10) and \
            self.get.wait_for_service(timeout_sec=10)

    def _call(self, client, request):
        future = client.call_async(request)
        assert self.graph.wait_for(future.done, 30)
        return future.result()

    def transition(self, transition_id: int) -> bool:
        return self._call(self.change, ChangeState.Request(
            transition=Transition(id=transition_id))).success

    @property
    def state(self) -> str:
        return self._call(self.get, GetState.Request()).current_state.label


def test_lifecycle_transitions_load_listen_pause_and_free(ros_graph, synthetic_map):
    path, queries = synthetic_map
    node = ros_graph.start(ManagedLocaliserNode, preset="kitti", map_path=str(path),
                           publish_mode="continuous")
    lifecycle = Lifecycle(ros_graph, "localiser")
    poses = ros_graph.collect(PoseWithCovarianceStamped, "relocalisation")
    scans = ros_graph.publisher(PointCloud2, "points")
    stamp = iter(range(100, 1000))

    def send(index: int) -> None:
        scans.publish(points_to_pointcloud2(queries[index][0], seconds_to_stamp(next(stamp)),
                                            "velodyne"))

    assert lifecycle.state == "unconfigured" and node.localiser is None
    assert lifecycle.transition(Transition.TRANSITION_CONFIGURE)
    assert lifecycle.state == "inactive" and node.localiser.reference_count == 45
    assert scans.get_subscription_count() == 0          # configured, not yet listening

    for cycle in range(2):
        assert lifecycle.transition(Transition.TRANSITION_ACTIVATE)
        assert lifecycle.state == "active"
        ros_graph.wait_for_subscribers(scans)
        send(cycle)
        assert ros_graph.wait_for(lambda: len(poses) == cycle + 1)
        translation, yaw = errors(planar_of_message(poses[-1]), planar(queries[cycle][1]))
        assert translation < 0.5 and yaw < 2.0

        assert lifecycle.transition(Transition.TRANSITION_DEACTIVATE)
        assert lifecycle.state == "inactive"
        assert ros_graph.wait_for(lambda: scans.get_subscription_count() == 0)
        received = node.counters["scans_received"]
        send(5)
        ros_graph.wait_for(lambda: False, 0.5)
        assert node.counters["scans_received"] == received and len(poses) == cycle + 1

    assert lifecycle.transition(Transition.TRANSITION_CLEANUP)
    assert lifecycle.state == "unconfigured" and node.localiser is None
    # A diagnostics tick already due when cleanup ran: it finds nothing to report (it used to
    # raise in the executor's thread, which then stopped spinning).
    node._publish_diagnostics()
    assert lifecycle.transition(Transition.TRANSITION_CONFIGURE)   # and again from scratch
    assert node.localiser.reference_count == 45


def test_a_failing_configure_leaves_the_node_unconfigured(ros_graph, tmp_path):
    node = ros_graph.start(ManagedLocaliserNode, preset="kitti",
                           map_path=str(tmp_path / "missing.mfmap"))
    lifecycle = Lifecycle(ros_graph, "localiser")
    assert not lifecycle.transition(Transition.TRANSITION_CONFIGURE)
    assert lifecycle.state == "unconfigured" and node.localiser is None
