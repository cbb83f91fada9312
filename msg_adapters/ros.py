"""rclpy message classes <-> core types, through :mod:`msg_adapters.layout`."""

from __future__ import annotations

import array

import numpy as np
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from msg_adapters.layout import Encoded


COPY_CHUNK_BYTES = 1 << 20
"""Bytes of a message's data copied per call: each call holds the interpreter lock, so a large
map's copy stops the node's other threads for about a millisecond at a time (a 72 MB map copied
at once, through ``tobytes``, stopped them for 56-65 ms twice)."""


def to_msg(encoded: Encoded) -> Float64MultiArray:
    """Return a ``std_msgs/Float64MultiArray`` carrying ``encoded`` (data copied once, in chunks)."""
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=k, size=s, stride=s) for k, s in zip(encoded.labels, encoded.sizes, strict=True)]
    msg.layout.data_offset = 0
    data = array.array("d")
    raw = memoryview(np.ascontiguousarray(encoded.data, dtype=np.float64)).cast("B")
    for start in range(0, len(raw), COPY_CHUNK_BYTES):
        data.frombytes(raw[start : start + COPY_CHUNK_BYTES])
    msg.data = data  # an array.array of doubles is taken as it is
    return msg


def parts(msg: Float64MultiArray) -> tuple[list[str], list[int], np.ndarray, int]:
    """Return ``(labels, sizes, data, data_offset)`` of a received message (data not copied)."""
    data = np.frombuffer(msg.data, dtype=np.float64) if len(msg.data) else np.zeros(0)
    return [d.label for d in msg.layout.dim], [int(d.size) for d in msg.layout.dim], data, int(msg.layout.data_offset)
