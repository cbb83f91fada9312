"""Start the linear_slam_ros joiner, and RViz on request.

    ros2 launch linear_slam_ros joiner.launch.py                       # installed config/joiner.yaml
    ros2 launch linear_slam_ros joiner.launch.py params_file:=my.yaml use_sim_time:=true rviz:=true

Arguments:
- ``params_file``: parameters of the node (default: the installed ``config/joiner.yaml``); its
  ``/**/joiner`` block matches the node named ``joiner`` below in any namespace.
- ``use_sim_time``: take time from ``/clock`` (a bag played with ``--clock``) instead of the wall
  clock; set on the joiner and on RViz. Default ``false``.
- ``rviz``: also start ``rviz2`` with the installed ``rviz/linear_slam.rviz`` (fixed frame
  ``map``; ``path``, ``features`` and ``pose`` subscribed transient local, so they show at once
  even when RViz starts after the node has published). Default ``false``.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

PACKAGE = "linear_slam_ros"


def _use_sim_time() -> dict[str, ParameterValue]:
    """Return the ``use_sim_time`` parameter from the launch argument, as a bool (one per node)."""
    return {"use_sim_time": ParameterValue(LaunchConfiguration("use_sim_time"), value_type=bool)}


def generate_launch_description() -> LaunchDescription:
    """Return the joiner node (and, with ``rviz:=true``, rviz2) with their launch arguments."""
    share = FindPackageShare(PACKAGE)
    params_file = LaunchConfiguration("params_file")
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "params_file",
                default_value=PathJoinSubstitution([share, "config", "joiner.yaml"]),
                description="YAML parameters file of the joiner node",
            ),
            DeclareLaunchArgument(
                "use_sim_time",
                default_value="false",
                choices=["true", "false"],
                description="use /clock (e.g. a bag played with --clock) instead of the wall clock",
            ),
            DeclareLaunchArgument(
                "rviz",
                default_value="false",
                choices=["true", "false"],
                description="also start rviz2 with the installed rviz/linear_slam.rviz",
            ),
            Node(
                package=PACKAGE,
                executable="joiner",
                name="joiner",
                output="screen",
                parameters=[params_file, _use_sim_time()],
            ),
            Node(
                package="rviz2",
                executable="rviz2",
                name="rviz2",
                output="screen",
                arguments=["-d", PathJoinSubstitution([share, "rviz", "linear_slam.rviz"])],
                parameters=[_use_sim_time()],
                condition=IfCondition(LaunchConfiguration("rviz")),
            ),
        ]
    )
