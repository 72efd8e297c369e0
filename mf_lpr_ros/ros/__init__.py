"""ROS 2 (rclpy) layer: the map_builder and localiser nodes and the bag replayer.

The only modules of the package that import rclpy or ROS message types.
"""
