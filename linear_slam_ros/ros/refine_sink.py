"""The refiner process's publisher of ``global_map_refined`` (built in the child by :class:`SinkSpec`).

The joiner node starts :class:`~linear_slam_ros.refinement.worker.RefineWorker` with
``SinkSpec("linear_slam_ros.ros.refine_sink:make_sink", {...})``; in the child this module
starts its own rclpy context and node (``<joiner>_refiner``) and publishes each refined map on
the joiner's resolved ``global_map_refined`` topic (latched), so encoding and sending a large map
never takes the joiner's interpreter lock. The message has the ``global_map`` layout in the
joiner's ``output_frame`` and one more segment, ``refine``: ``chi2, iterations, converged,
lag_s, cpu_s, initial_chi2`` (lag: from the arrival of the newest submap it covers to this
publication; cpu: the refiner process's CPU time so far).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import rclpy
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.refinement.online import RefinedMap
from linear_slam_ros.ros.qos import latched_qos
from linear_slam_ros.ros.raw_publish import publish_serialized
from msg_adapters import Encoded, Stamp
from msg_adapters.cdr import to_cdr
from msg_adapters.global_map import encode_empty_global, encode_global

REFINE_FIELDS = ("chi2", "iterations", "converged", "lag_s", "cpu_s", "initial_chi2")
"""The ``refine`` segment of ``global_map_refined``, in order."""


class RosSink:
    """Publishes refined maps on ``topic`` from a node of its own (the child's rclpy context)."""

    def __init__(self, topic: str, node_name: str, output_frame: str) -> None:
        rclpy.init(args=None)
        self.node = rclpy.create_node(node_name)
        self.pub = self.node.create_publisher(Float64MultiArray, topic, latched_qos())
        self.output_frame = output_frame
        self._last: tuple[RefinedMap, float, float] | None = None  # the newest map published, its CPU and lag (s)
        publish_serialized(self.pub, to_cdr(encode_empty_global(LocalMap, 0, Stamp(), {})))  # no older refined map stays latched

    def publish(self, refined: RefinedMap, cpu_seconds: float) -> None:
        """Encode and publish one refined map (module docstring)."""
        self._last = (refined, cpu_seconds, time.monotonic() - refined.last_arrival)
        self._send(*self._last)

    def configure(self, settings: dict[str, Any]) -> None:
        """Take the joiner's new ``output_frame`` and republish the newest refined map in it (the topic is latched:
        an idle refiner publishes nothing more).

        Raises:
            ConfigError: a setting other than ``output_frame``.
        """
        unknown = sorted(set(settings) - {"output_frame"})
        if unknown:
            raise ConfigError(f"the refined map's publisher has no setting {unknown[0]!r}")
        if settings.get("output_frame", self.output_frame) == self.output_frame:
            return
        self.output_frame = str(settings["output_frame"])
        if self._last is not None:
            self._send(*self._last)

    def _send(self, refined: RefinedMap, cpu_seconds: float, lag: float) -> None:
        m = refined.map
        if self.output_frame == "end_pose" and m.end_id is not None and m.end_id != m.frame_id:
            m = change_frame(m, m.end_id)
        encoded = encode_global(m, refined.last_seq, Stamp(*refined.stamp), refined.n_submaps, {"n_joined": refined.n_submaps})
        values = [refined.chi2, refined.iterations, float(refined.converged), lag, cpu_seconds, refined.initial_chi2]
        publish_serialized(self.pub, to_cdr(with_refine_segment(encoded, values)))

    def close(self, cpu_seconds: float) -> None:
        """Destroy the node and end the child's rclpy context."""
        self.node.destroy_node()
        rclpy.try_shutdown()


def with_refine_segment(encoded: Encoded, values: list[float]) -> Encoded:
    """Append the ``refine`` segment (:data:`REFINE_FIELDS`) to an encoded map."""
    return Encoded(encoded.labels + ("refine",), encoded.parts + (np.asarray(values, dtype=np.float64),))


def make_sink(topic: str, node_name: str, output_frame: str) -> RosSink:
    """The sink factory named in the joiner's :class:`SinkSpec`."""
    return RosSink(topic, node_name, output_frame)
