"""The CDR bytes of a ``std_msgs/Float64MultiArray`` written straight from an :class:`Encoded`.

What rclpy would send for :func:`msg_adapters.ros.to_msg` of the same content (little-endian
CDR, as every ROS 2 middleware of Jazzy serialises it), without the rclpy message in between:
each segment is written once, converted to float64 in place, into one buffer that can be handed
to the middleware as a serialised message (:mod:`linear_slam_ros.ros.raw_publish`). For a large
``global_map`` that is one copy of the map instead of three (the concatenated data, the
message's array and rclpy's serialised buffer).

Layout (offsets after the 4-byte encapsulation header; each primitive aligned to its size)::

    uint32 len(layout.dim), then per dimension:
        uint32 len(label) + 1, label bytes, NUL; uint32 size; uint32 stride
    uint32 layout.data_offset
    uint32 len(data); float64 data[...] (aligned to 8)

Padding bytes are zero (rclpy leaves them unset; readers ignore them).
"""

from __future__ import annotations

import struct

import numpy as np
import numpy.typing as npt

from msg_adapters.layout import Encoded

ENCAPSULATION_CDR_LE = b"\x00\x01\x00\x00"
"""RTPS encapsulation header of little-endian plain CDR."""


def _head(encoded: Encoded) -> bytes:
    """Return the encapsulation header and every field before the data's first value."""
    out = bytearray(ENCAPSULATION_CDR_LE)

    def align(size: int) -> None:
        out.extend(bytes(-(len(out) - len(ENCAPSULATION_CDR_LE)) % size))

    out += struct.pack("<I", len(encoded.labels))
    for label, size in zip(encoded.labels, encoded.sizes, strict=True):
        text = label.encode() + b"\x00"
        align(4)
        out += struct.pack("<I", len(text)) + text
        align(4)
        out += struct.pack("<II", size, size)
    align(4)
    out += struct.pack("<I", 0)  # data_offset
    out += struct.pack("<I", sum(encoded.sizes))
    align(8)
    return bytes(out)


def to_cdr(encoded: Encoded) -> npt.NDArray[np.uint8]:
    """Return the serialised ``std_msgs/Float64MultiArray`` of ``encoded``, as one byte array.

    The data's first value sits at an address that is a multiple of 8, so each segment is
    converted into it with one aligned ``numpy.copyto`` (which releases the interpreter lock).

    Args:
        encoded: the message's content.

    Returns:
        The CDR bytes, shape ``(4 + serialised size,)``: what a bag stores for the message and
        what the middleware publishes.
    """
    head = _head(encoded)
    total = len(head) + 8 * sum(encoded.sizes)
    raw = np.empty(total + 8, dtype=np.uint8)
    start = (-(raw.ctypes.data + len(head))) % 8  # so that the data's first value is 8-aligned in memory
    buffer = raw[start : start + total]
    buffer[: len(head)] = np.frombuffer(head, dtype=np.uint8)
    values = buffer[len(head) :].view(np.float64)
    pos = 0
    for part in encoded.parts:
        np.copyto(values[pos : pos + part.size], part)
        pos += part.size
    return buffer
