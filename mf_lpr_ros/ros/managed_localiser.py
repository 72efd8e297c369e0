"""The localiser as a managed (lifecycle) node, for nav2's lifecycle manager.

    ros2 run mf_lpr_ros managed_localiser --ros-args -p map_path:=/data/site.mfmap
"""

from __future__ import annotations

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from mf_lpr_ros.errors import MapFileError, ParameterFault
from mf_lpr_ros.ros.lidar_node import run_node
from mf_lpr_ros.ros.localiser import LocaliserLogic


class ManagedLocaliserNode(LocaliserLogic, LifecycleNode):
    """The localiser as a managed (lifecycle) node, for nav2's lifecycle manager: parameters at
    construction, the map on configure, topics on activate, paused on deactivate, freed on
    cleanup. A failing configure (a missing or mismatched map) leaves it unconfigured."""

    def __init__(self, node_name: str = "localiser", **kwargs) -> None:
        LifecycleNode.__init__(self, node_name, **kwargs)
        self.init_lidar_state()
        self.read_settings()

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.configure(self.create_lifecycle_publisher)
        except (ParameterFault, MapFileError, OSError, ValueError) as error:
            self.get_logger().error(f"configure failed: {type(error).__name__}: {error}")
            self.localiser = None
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.activate()
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.deactivate()
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.cleanup()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.cleanup()
        return TransitionCallbackReturn.SUCCESS


def main(args: list[str] | None = None) -> int:
    return run_node(ManagedLocaliserNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
