"""The ROS layer: the joiner node and the bag tools. Only this subpackage imports rclpy or rosbags."""
