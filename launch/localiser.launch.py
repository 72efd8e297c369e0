"""Launch the localiser.

    ros2 launch mf_lpr_ros localiser.launch.py map_path:=/data/site.mfmap preset:=kitti
    ros2 launch mf_lpr_ros localiser.launch.py mode:=loop_closure pose_source:=odom \\
        points:=/velodyne_points
    ros2 launch mf_lpr_ros localiser.launch.py map_path:=site.mfmap to_amcl:=true
    ros2 service call /localiser/relocalise std_srvs/srv/Trigger

preset picks config/<preset>.yaml; to_amcl:=true remaps relocalisation to /initialpose;
publish_mode on_request publishes one pose per ~/relocalise call, continuous one per accepted
scan. The managed (lifecycle) variant: localiser_managed.launch.py.
"""

from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

ARGUMENTS = {
    "preset": ("default", "parameter preset: a file config/<preset>.yaml"),
    "map_path": ("", "map file from map_builder or mf-lpr build-map (relocalise mode)"),
    "mode": ("relocalise", "relocalise or loop_closure"),
    "pose_source": ("none", "none, odom, pose or pose_with_covariance"),
    "points": ("points", "PointCloud2 topic"),
    "odom": ("odom", "Odometry topic (pose_source:=odom)"),
    "to_amcl": ("false", "publish relocalisation on /initialpose for nav2 AMCL"),
    "publish_mode": ("auto", "on_request (~/relocalise service), continuous, or auto (by mode)"),
}


def _node(context):
    value = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    share = FindPackageShare("mf_lpr_ros").perform(context)
    remappings = [("points", value["points"]), ("odom", value["odom"])]
    if value["to_amcl"].lower() == "true":
        remappings.append(("relocalisation", "/initialpose"))
    return [Node(
        package="mf_lpr_ros", executable="localiser", name="localiser", output="screen",
        parameters=[f"{share}/config/{value['preset']}.yaml",
                    {"map_path": value["map_path"], "mode": value["mode"],
                     "pose_source": value["pose_source"],
                     "publish_mode": value["publish_mode"]}],
        remappings=remappings)]


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text)
         for name, (default, text) in ARGUMENTS.items()] + [OpaqueFunction(function=_node)])
