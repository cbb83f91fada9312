"""ament_python set-up of linear_slam_ros: console scripts land in lib/linear_slam_ros (setup.cfg).

data_files install what ``ros2 launch`` and RViz find through the package's share directory:
share/linear_slam_ros/{package.xml, config/*.yaml, config/*.xml, launch/*.launch.py, rviz/*.rviz}, and
the demo's default bag, share/linear_slam_ros/bags/vicpark200.
Console scripts are resolved when they run, not when they are installed: a script whose module
does not exist yet still installs (and fails only when started).
"""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "linear_slam_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*", "msg_adapters", "msg_adapters.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/rviz", glob("rviz/*.rviz")),
        (f"share/{PACKAGE}/bags/vicpark200", glob("bags/vicpark200/*")),  # the demo's default bag
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="linear_slam_ros developers",
    maintainer_email="dev@linear-slam-ros.invalid",
    description="Online submap joining in closed form (Linear SLAM) for ROS 2 Jazzy",
    license="BSD-3-Clause",
    extras_require={"test": ["pytest"]},
    entry_points={
        "console_scripts": [
            "joiner = linear_slam_ros.ros.node:main",
            "bag_from_dataset = linear_slam_ros.ros.bag_from_dataset:main",
            "bag_player = linear_slam_ros.ros.player:main",
            "bag_recorder = linear_slam_ros.ros.recorder:main",
            "demo = linear_slam_ros.ros.demo:main",
            "sim_frontend = linear_slam_ros.ros.sim_frontend:main",
        ],
    },
)
