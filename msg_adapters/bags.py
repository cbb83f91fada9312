"""rosbags message classes (ROS 2 Jazzy typestore) <-> core types, through :mod:`msg_adapters.layout`."""

from __future__ import annotations

import numpy as np
from rosbags.typesys import Stores, get_typestore

from msg_adapters.layout import Encoded

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
MSGTYPE = "std_msgs/msg/Float64MultiArray"
_Float64MultiArray = TYPESTORE.types[MSGTYPE]
_Layout = TYPESTORE.types["std_msgs/msg/MultiArrayLayout"]
_Dim = TYPESTORE.types["std_msgs/msg/MultiArrayDimension"]


def to_bag_msg(encoded: Encoded) -> object:
    """Return a rosbags ``std_msgs/msg/Float64MultiArray`` carrying ``encoded``."""
    dims = [_Dim(label=k, size=s, stride=s) for k, s in zip(encoded.labels, encoded.sizes, strict=True)]
    return _Float64MultiArray(layout=_Layout(dim=dims, data_offset=0), data=np.asarray(encoded.data, dtype=np.float64))


def bag_parts(msg: object) -> tuple[list[str], list[int], np.ndarray, int]:
    """Return ``(labels, sizes, data, data_offset)`` of a rosbags message."""
    layout = msg.layout  # type: ignore[attr-defined]
    return (
        [d.label for d in layout.dim],
        [int(d.size) for d in layout.dim],
        np.asarray(msg.data, dtype=np.float64),  # type: ignore[attr-defined]
        int(layout.data_offset),
    )


def serialize(encoded: Encoded) -> bytes:
    """Return the CDR bytes of the message (what a bag stores and rclpy can publish raw)."""
    return bytes(TYPESTORE.serialize_cdr(to_bag_msg(encoded), MSGTYPE))


def deserialize(raw: bytes) -> object:
    """Return the rosbags message of CDR bytes."""
    return TYPESTORE.deserialize_cdr(raw, MSGTYPE)
