"""rclpy message classes <-> core types, through :mod:`msg_adapters.layout`."""

from __future__ import annotations

import array

import numpy as np
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from msg_adapters.layout import Encoded

COPY_CHUNK_BYTES = 1 << 20
"""Bytes of a message's data copied per call: each call holds the interpreter lock, so a large
map's copy stops the node's other threads for a few milliseconds at most (a 72 MB map copied
whole, three times, stopped them for 47-65 ms each time)."""


def to_msg(encoded: Encoded) -> Float64MultiArray:
    """Return a ``std_msgs/Float64MultiArray`` carrying ``encoded`` (its data copied once, in chunks)."""
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=k, size=s, stride=s) for k, s in zip(encoded.labels, encoded.sizes, strict=True)]
    msg.layout.data_offset = 0
    # Unless ROS_PYTHON_CHECK_FIELDS=1, the field's generated setter skips its checks and stores
    # array.array(value), a copy of whatever it is given: 47 ms under the lock at 72 MB. So the
    # message gets an empty array, and the data goes into the array the message holds.
    msg.data = array.array("d")
    data = msg.data
    raw = np.ascontiguousarray(encoded.data, dtype=np.float64).view(np.uint8)
    for start in range(0, raw.size, COPY_CHUNK_BYTES):
        data.frombytes(raw[start : start + COPY_CHUNK_BYTES].data)
    return msg


def parts(msg: Float64MultiArray) -> tuple[list[str], list[int], np.ndarray, int]:
    """Return ``(labels, sizes, data, data_offset)`` of a received message (data not copied)."""
    data = np.frombuffer(msg.data, dtype=np.float64) if len(msg.data) else np.zeros(0)
    return [d.label for d in msg.layout.dim], [int(d.size) for d in msg.layout.dim], data, int(msg.layout.data_offset)
