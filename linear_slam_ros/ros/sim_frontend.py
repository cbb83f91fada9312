"""``sim_frontend``: a simulated robot and SLAM front-end that publishes local maps live to the joiner.

It is the example to copy when you write a front-end for the ``joiner``. A robot drives a seeded
2D world of point features for ever (``park``: among trees, its route forth and back; ``loop``:
round a 10 m circle). Every ``steps_per_map`` steps the front-end turns the odometry and the
feature observations of those steps into one local map, as a real front-end would: Gauss-Newton
in the frame of the map's start pose, the intermediate poses marginalised, so the map holds its
end pose and the features it saw (:func:`linear_slam_ros.evaluation.city.feature_local_maps`).
It publishes it on ``local_map``, ``rate`` maps per second, with sequence numbers from 1 and the
node clock's stamp, and the true pose of the map's end pose on ``~/true_pose`` to compare with the
joiner's ``pose``.

Run it against the joiner (two terminals, the same ``ROS_DOMAIN_ID``)::

    ros2 run linear_slam_ros joiner --ros-args --params-file config/joiner.yaml
    ros2 run linear_slam_ros sim_frontend --ros-args -p world:=park -p rate:=10.0 -p n_maps:=200

Parameters (all read-only, declared with descriptions): ``world`` (``park`` | ``loop``),
``seed`` (the same seed gives the same maps, bit for bit), ``steps_per_map``, ``rate`` (local maps
per second), ``n_maps`` (stop after this many; 0: for ever), ``map_frame`` (``frame_id`` of
``~/true_pose``: the frame of pose 0, like the joiner's ``map_frame``). The node waits for a
subscriber on ``local_map`` before its first map; with ``n_maps`` set it exits with code 0 once
every map has been acknowledged (and the last ``~/true_pose`` by whoever subscribed to it, given
:data:`TRUTH_LINGER_S` to match), and with code 2 on an invalid parameter.

What a front-end must get right (the rest is your own business):

- **The message**: ``msg_adapters.encode_map`` + ``msg_adapters.ros.to_msg`` build the layout the
  README documents. Each map is in the frame of a robot pose the joiner already has (its
  ``frame_id``: the previous map's end pose), names its newest pose as ``end_id``, and keeps
  feature ids stable across maps: the joiner associates variables by id.
- **Sequence numbers** start at 1 and go up by one per map: the joiner joins in that order.
- **QoS**: reliable and keep all (:func:`linear_slam_ros.ros.qos.inbound_qos`), the profile the
  joiner subscribes with. Do not use ``create_publisher(..., 10)`` (reliable, *keep last 10*):
  reliability only re-sends what is still in the writer's history, and keep-last-10 holds the ten
  newest messages. Whenever the joiner falls more than ten maps behind (a large merge, a slow
  machine, a burst after a pause, DDS discovery at start-up) older unacknowledged maps are
  overwritten before they are delivered and silently lost. The joiner then waits
  ``reorder_timeout`` for the missing number and gives it up: the map loses those measurements,
  and the next map may not connect. Keep all queues them instead.
- **Start-up**: the topic is volatile, so maps published before the joiner's subscription is
  discovered (up to a few seconds) are lost: wait until ``get_subscription_count() > 0``.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from typing import Any

import numpy as np
import numpy.typing as npt
import rclpy
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.duration import Duration
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.task import Future
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.evaluation.city import feature_local_maps, measure_features, park_world
from linear_slam_ros.evaluation.synthetic import World, make_world
from linear_slam_ros.ros.qos import inbound_qos, latched_qos
from linear_slam_ros.ros.spin import print_usage_if_asked
from msg_adapters import Stamp, encode_map
from msg_adapters.ros import to_msg
from msg_adapters.views import pose_stamped_msg

FloatArray = npt.NDArray[np.float64]

NODE_NAME = "sim_frontend"
WORLDS = ("park", "loop")
"""The simulated worlds, by ``world`` parameter value."""


class Simulation:
    """A robot driving a seeded 2D world for ever, its sensors, and the local maps its front-end builds.

    Pure numpy (no ROS): the node below only publishes what it returns.

    Args:
        world: ``"park"`` (trees, a 400-step drive among them, then the same route backwards) or
            ``"loop"`` (80 features round a 10 m circle driven in 120 steps).
        seed: seed of the world and of every measurement's noise.
        steps_per_map: robot steps per local map.

    Raises:
        ValueError: unknown ``world``, or ``steps_per_map`` below 1.
    """

    def __init__(self, world: str = "park", seed: int = 0, steps_per_map: int = 4) -> None:
        if steps_per_map < 1:
            raise ValueError(f"steps_per_map must be at least 1, not {steps_per_map}")
        self.rng = np.random.default_rng(seed)
        if world == "park":
            drive = park_world(400, self.rng)
            self.route = np.concatenate([drive.poses, drive.poses[-2:0:-1]])  # forth, then back (reversing)
        elif world == "loop":
            drive = make_world(2, 120, 80, self.rng)
            self.route = drive.poses[:-1]  # its last pose is its first: drive it round and round
        else:
            raise ValueError(f"unknown world {world!r}: one of {list(WORLDS)}")
        self.features = drive.features  # ground truth {feature id: (x, y)}, frame of pose 0
        self.steps_per_map = steps_per_map
        self.n_built = 0  # local maps built so far

    def true_pose(self, step: int) -> FloatArray:
        """Return the true pose ``(x, y, phi)`` of the robot after ``step`` steps, in the frame of pose 0."""
        return self.route[step % len(self.route)]

    def next_local_map(self) -> LocalMap:
        """Drive ``steps_per_map`` steps and return the local map of their measurements.

        Map ``i`` (from 0) is in the frame of pose ``s i`` and holds pose ``s (i + 1)`` and the
        features seen (``s = steps_per_map``); pose ids are step numbers.
        """
        s, first = self.steps_per_map, self.steps_per_map * self.n_built
        # The sensors: noisy odometry of the s steps and scans (a 180-degree, 12 m laser) at each pose.
        driven = World(2, np.stack([self.true_pose(first + q) for q in range(s + 1)]), self.features)
        measurements = measure_features(driven, self.rng, s)
        # The front-end: Gauss-Newton over these measurements in the frame of the first pose,
        # intermediate poses marginalised. Here the poses are numbered 0..s ...
        (local_map,) = feature_local_maps(measurements, name=f"local_map_{self.n_built + 1}")
        self.n_built += 1
        # ... and the joiner needs them numbered by step, the same number in every map.
        pose_ids = np.where(local_map.kinds == POSE, local_map.ids + first, local_map.ids)
        return dataclasses.replace(local_map, frame_id=first, end_id=first + s, ids=pose_ids)


def _descriptor(description: str, low: float | None = None, high: float | None = None) -> ParameterDescriptor:
    """Return a read-only parameter descriptor, with an integer range when ``low``/``high`` are ints."""
    desc = ParameterDescriptor(description=description, read_only=True)
    if isinstance(low, int) and isinstance(high, int):
        desc.integer_range = [IntegerRange(from_value=low, to_value=high, step=1)]
    elif low is not None and high is not None:
        desc.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=0.0)]
    return desc


class SimFrontend(Node):
    """Publishes the local maps of a :class:`Simulation` on ``local_map``, ``rate`` per second."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)  # kwargs: Node's, e.g. parameter_overrides
        # Declared parameters: only these are taken from the command line or a params file.
        # A value out of range or of the wrong type (rate:=10, not 10.0) raises here: main exits with 2.
        world = self.declare_parameter("world", "park", _descriptor(f"simulated world, one of {list(WORLDS)}")).value
        seed = self.declare_parameter("seed", 0, _descriptor("seed of the world and the noise", 0, 2**31 - 1)).value
        steps = self.declare_parameter("steps_per_map", 4, _descriptor("robot steps per local map", 1, 1000)).value
        rate = self.declare_parameter("rate", 10.0, _descriptor("local maps published per second, Hz", 0.01, 1000.0)).value
        self.n_maps = self.declare_parameter("n_maps", 0, _descriptor("local maps to publish; 0: for ever", 0, 10**9)).value
        self.map_frame = self.declare_parameter(
            "map_frame", "map", _descriptor("frame_id of ~/true_pose (the frame of pose 0)")
        ).value
        if not self.map_frame:  # as the joiner refuses it
            raise ValueError("parameter map_frame='' is not a frame id")
        self.simulation = Simulation(world, seed, steps)  # ValueError on an unknown world

        # The joiner's inbound profile: reliable, keep all. Not a depth of 10: see the module docstring.
        self.local_map_pub = self.create_publisher(Float64MultiArray, "local_map", inbound_qos())
        # Latched (reliable, transient local, depth 1), like the joiner's own pose: a late RViz still sees it.
        self.true_pose_pub = self.create_publisher(PoseStamped, "~/true_pose", latched_qos())
        self.seq = 0  # sequence number of the last map published; the first is 1
        self.finished = Future()  # done after n_maps maps
        self.timer = self.create_timer(1.0 / rate, self.publish_next_map)
        self.get_logger().info(
            f"{world} world (seed {seed}): a local map of {steps} steps every {1.0 / rate:g} s on "
            f"{self.local_map_pub.topic_name}, {self.n_maps or 'unlimited'} maps; ground truth on {self.true_pose_pub.topic_name}"
        )

    def publish_next_map(self) -> None:
        """Timer callback: build the next local map and publish it with its true end pose."""
        if not self.context.ok():  # shutting down: nothing can be published any more
            return
        if self.seq == 0 and self.local_map_pub.get_subscription_count() == 0:
            # The topic is volatile: a map published before the joiner is discovered would be lost.
            self.get_logger().info("waiting for a subscriber on local_map", throttle_duration_sec=5.0)
            return
        local_map = self.simulation.next_local_map()
        self.seq += 1
        now = self.get_clock().now()  # the node's clock (sim time when use_sim_time is set), never wall time
        sec, nanosec = now.seconds_nanoseconds()
        self.local_map_pub.publish(to_msg(encode_map(local_map, self.seq, Stamp(sec, nanosec))))
        true_pose = self.simulation.true_pose(self.simulation.steps_per_map * self.seq)  # the map's end pose
        self.true_pose_pub.publish(pose_stamped_msg(2, true_pose, self.map_frame, now.to_msg()))
        self.get_logger().debug(f"map {self.seq}: poses {local_map.frame_id} to {local_map.end_id}, {local_map.n_vars} variables")
        if self.seq == self.n_maps:
            self.timer.cancel()
            self.finished.set_result(self.seq)


TRUTH_LINGER_S = 1.0
"""s: with ``n_maps`` set, how long the node waits, after its last map, for a ``~/true_pose`` subscriber to match."""


def main(args: list[str] | None = None) -> None:
    """Run the node until ``n_maps`` maps are acknowledged (or for ever); Ctrl-C stops it cleanly; ``--help`` prints the docs."""
    if print_usage_if_asked(args, "sim_frontend", __doc__ or ""):
        return
    rclpy.init(args=args)
    try:
        node = SimFrontend()
    except (ValueError, InvalidParameterTypeException, InvalidParameterValueException) as exc:
        rclpy.logging.get_logger(NODE_NAME).fatal(f"cannot start: {exc}")
        rclpy.try_shutdown()
        sys.exit(2)
    try:
        rclpy.spin_until_future_complete(node, node.finished)
        # Reliable delivery ends with the subscriber's acknowledgement: exiting earlier can lose the last maps.
        node.local_map_pub.wait_for_all_acked(Duration(seconds=30))
        # The latched truth ends with the process: a subscriber still being discovered gets TRUTH_LINGER_S to
        # match, and whoever matched has acknowledged it before the exit.
        deadline = time.monotonic() + TRUTH_LINGER_S
        while node.true_pose_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        node.true_pose_pub.wait_for_all_acked(Duration(seconds=5))
        node.get_logger().info(f"published {node.seq} local maps")
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # SIGTERM (ros2 launch, docker, systemd) shut the context down under a publication or the wait for
        # acknowledgements: rclpy's RCLError then, a normal stop all the same (as the joiner's main)
        if node.context.ok():
            raise
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":  # pragma: no cover
    main()
