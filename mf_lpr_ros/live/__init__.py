"""The live nodes' logic without ROS: pose buffering and pairing, map building, localisation.

The rclpy nodes in mf_lpr_ros.ros only convert messages and call these, so everything here is
tested without a ROS graph.
"""
