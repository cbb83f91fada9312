"""Conversions between linear_slam_ros core types and ROS messages.

:mod:`msg_adapters.layout` defines the documented array layouts without any ROS library;
:mod:`msg_adapters.ros` converts to and from rclpy message classes, :mod:`msg_adapters.bags`
to and from rosbags message classes (for reading and writing bags without ROS).
"""

from msg_adapters.layout import (
    FORMAT_VERSION,
    MAP_KIND_GLOBAL,
    MAP_KIND_LOCAL,
    MAP_KIND_POSE_GRAPH,
    ChunkMessage,
    Encoded,
    FeatureMapMessage,
    MapMessage,
    MapSummary,
    Stamp,
    decode_chunk,
    decode_feature_map,
    decode_map,
    decode_map_summary,
    encode_chunk,
    encode_feature_map,
    encode_map,
    submap_of,
)

__all__ = [
    "FORMAT_VERSION",
    "MAP_KIND_GLOBAL",
    "MAP_KIND_LOCAL",
    "MAP_KIND_POSE_GRAPH",
    "ChunkMessage",
    "Encoded",
    "FeatureMapMessage",
    "MapMessage",
    "MapSummary",
    "Stamp",
    "decode_chunk",
    "decode_feature_map",
    "decode_map",
    "decode_map_summary",
    "encode_chunk",
    "encode_feature_map",
    "encode_map",
    "submap_of",
]
