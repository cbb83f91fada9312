"""The joiner's optional TF output: ``map_frame`` -> ``base_frame`` at the newest pose (``publish_tf``).

With ``publish_tf`` true the node broadcasts the newest pose as a transform, where it publishes
``pose``. How it is sent depends on what is installed:

- ``tf2_ros`` (every ROS 2 Jazzy install): its ``TransformBroadcaster`` (topic ``/tf``).
- ``tf2_msgs`` without ``tf2_ros``: a ``tf2_msgs/TFMessage`` publisher on ``/tf`` with the
  broadcaster's QoS (reliable, volatile, depth 100), which is what the broadcaster does.
- neither (the PyPI Jazzy wheels: they ship no tf2 package at all): one warning at start-up,
  and no TF.

These parameters belong to the node's ROS outputs, not to the joining configuration
(:class:`~linear_slam_ros.joiner.config.JoinerConfig`), so they are declared here.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile

from linear_slam_ros.joiner.config import ParameterDeclaration, ParamSpec

TF_QOS_DEPTH = 100
"""History depth of the ``/tf`` publisher (``tf2_ros.TransformBroadcaster``'s default)."""

TF_PARAMETERS = (
    ParameterDeclaration(
        "publish_tf",
        False,
        ParamSpec(
            "broadcast the transform map_frame -> base_frame of the newest pose on /tf (needs tf2_ros or tf2_msgs)",
            read_only=True,
        ),
        (),
    ),
    ParameterDeclaration(
        "base_frame",
        "base_link",
        ParamSpec("child frame of the publish_tf transform: the robot's frame at the newest pose", read_only=True),
        (),
    ),
)
"""The node's TF parameters, declared beside :func:`~linear_slam_ros.joiner.config.parameter_declarations`."""

TfSender = Callable[[TransformStamped], None]


def tf_sender(node: Node) -> tuple[TfSender | None, str]:
    """Return a function that broadcasts a transform from ``node``, and what it uses.

    Returns:
        ``(send, "tf2_ros")``, ``(send, "tf2_msgs")`` or ``(None, reason)`` when neither
        package can be imported (``reason`` names both).
    """
    try:  # imported by name: optional packages (neither is on PyPI), so no static import for mypy to miss
        tf2_ros = importlib.import_module("tf2_ros")
    except ImportError:
        pass
    else:
        broadcaster = tf2_ros.TransformBroadcaster(node)
        return broadcaster.sendTransform, "tf2_ros"
    message_class = tf_message_class()
    if message_class is None:
        return None, "neither tf2_ros nor tf2_msgs can be imported (the PyPI Jazzy wheels have no tf2 package)"
    publisher = node.create_publisher(message_class, "/tf", QoSProfile(depth=TF_QOS_DEPTH))

    def send(transform: TransformStamped) -> None:
        publisher.publish(message_class(transforms=[transform]))

    return send, "tf2_msgs"


def tf_message_class() -> Any | None:
    """Return ``tf2_msgs.msg.TFMessage``, or ``None`` when it is not installed (for a subscriber on ``/tf``)."""
    try:
        return importlib.import_module("tf2_msgs.msg").TFMessage
    except ImportError:
        return None
