"""linear_slam_ros: online submap joining in closed form (Linear SLAM), with a ROS 2 node.

Everything but :mod:`linear_slam_ros.ros` (the node and the bag tools) is pure numpy/scipy and
never imports rclpy; the sub-packages and their layers are listed in the README's Architecture
section and enforced by ``test/test_architecture.py``.
"""

__version__ = "0.1.0"
