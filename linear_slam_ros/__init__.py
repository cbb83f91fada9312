"""linear_slam_ros: online submap joining in closed form (Linear SLAM), with a ROS 2 node.

The core (everything but :mod:`linear_slam_ros.node` and the tools under
:mod:`linear_slam_ros.tools`) is pure numpy/scipy and never imports rclpy.
"""

__version__ = "0.1.0"
