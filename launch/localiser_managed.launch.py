"""Launch the managed (lifecycle) localiser under nav2's lifecycle manager.

    ros2 launch mf_lpr_ros localiser_managed.launch.py map_path:=/data/site.mfmap preset:=kitti
    ros2 service call /localiser/relocalise std_srvs/srv/Trigger

The lifecycle manager configures (loads the map) and activates (subscribes) the localiser when
autostart is true. The localiser keeps no bond with the manager, so bond_timeout is 0. To manage
it from your own nav2 lifecycle manager instead, add "localiser" to its node_names with
bond_timeout 0.0 (or use a manager of its own, as here) and launch with manager:=false.
"""

from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

ARGUMENTS = {
    "preset": ("default", "parameter preset: a file config/<preset>.yaml"),
    "map_path": ("", "map file from map_builder or mf-lpr build-map"),
    "pose_source": ("none", "none, odom, pose or pose_with_covariance"),
    "points": ("points", "PointCloud2 topic"),
    "odom": ("odom", "Odometry topic (pose_source:=odom)"),
    "to_amcl": ("true", "publish relocalisation on /initialpose for nav2 AMCL"),
    "manager": ("true", "start a nav2 lifecycle manager for the localiser"),
    "autostart": ("true", "the manager configures and activates the localiser at once"),
}


def _nodes(context):
    value = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    share = FindPackageShare("mf_lpr_ros").perform(context)
    remappings = [("points", value["points"]), ("odom", value["odom"])]
    if value["to_amcl"].lower() == "true":
        remappings.append(("relocalisation", "/initialpose"))
    nodes = [LifecycleNode(
        package="mf_lpr_ros", executable="managed_localiser", name="localiser", namespace="",
        output="screen",
        parameters=[f"{share}/config/{value['preset']}.yaml",
                    {"map_path": value["map_path"], "pose_source": value["pose_source"],
                     "publish_mode": "on_request"}],
        remappings=remappings)]
    if value["manager"].lower() == "true":
        nodes.append(Node(
            package="nav2_lifecycle_manager", executable="lifecycle_manager",
            name="lifecycle_manager_relocalisation", output="screen",
            parameters=[{"autostart": value["autostart"].lower() == "true",
                         "node_names": ["localiser"], "bond_timeout": 0.0}]))
    return nodes


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text)
         for name, (default, text) in ARGUMENTS.items()] + [OpaqueFunction(function=_nodes)])
