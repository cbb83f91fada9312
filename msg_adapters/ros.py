"""rclpy message classes <-> core types, through :mod:`msg_adapters.layout`."""

from __future__ import annotations

import array

import numpy as np
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from msg_adapters.layout import Encoded


def to_msg(encoded: Encoded) -> Float64MultiArray:
    """Return a ``std_msgs/Float64MultiArray`` carrying ``encoded``."""
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=k, size=s, stride=s) for k, s in zip(encoded.labels, encoded.sizes, strict=True)]
    msg.layout.data_offset = 0
    msg.data = array.array("d", encoded.data.tobytes())
    return msg


def parts(msg: Float64MultiArray) -> tuple[list[str], list[int], np.ndarray, int]:
    """Return ``(labels, sizes, data, data_offset)`` of a received message (data not copied)."""
    data = np.frombuffer(msg.data, dtype=np.float64) if len(msg.data) else np.zeros(0)
    return [d.label for d in msg.layout.dim], [int(d.size) for d in msg.layout.dim], data, int(msg.layout.data_offset)
