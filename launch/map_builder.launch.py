"""Launch the map builder.

    ros2 launch mf_lpr_ros map_builder.launch.py map_path:=/data/site.mfmap preset:=kitti \\
        points:=/velodyne_points odom:=/odometry/filtered

preset picks config/<preset>.yaml; the map is saved every save_period_s and at shutdown.
"""

from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

ARGUMENTS = {
    "preset": ("default", "parameter preset: a file config/<preset>.yaml"),
    "map_path": ("mf_lpr_map.mfmap", "map file to write"),
    "if_exists": ("error", "when map_path exists: error, append or overwrite"),
    "pose_source": ("odom", "odom, pose or pose_with_covariance"),
    "points": ("points", "PointCloud2 topic"),
    "odom": ("odom", "Odometry topic (pose_source:=odom)"),
    "pose": ("pose", "PoseStamped topic (pose_source:=pose)"),
}


def _node(context):
    value = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    share = FindPackageShare("mf_lpr_ros").perform(context)
    return [Node(
        package="mf_lpr_ros", executable="map_builder", name="map_builder", output="screen",
        parameters=[f"{share}/config/{value['preset']}.yaml",
                    {"map_path": value["map_path"], "if_exists": value["if_exists"],
                     "pose_source": value["pose_source"]}],
        remappings=[("points", value["points"]), ("odom", value["odom"]),
                    ("pose", value["pose"])])]


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text)
         for name, (default, text) in ARGUMENTS.items()] + [OpaqueFunction(function=_node)])
