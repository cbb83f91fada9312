"""Replay a rosbag2 bag into running nodes through rclpy, as ``ros2 bag play`` would.

``bag_player BAG [--rate-factor 1.0] [--wait 30] [--clock [HZ]]``: waits until every topic has
a subscriber, then publishes each message at its bag time divided by the rate factor (0: as fast
as possible), reliable and keeping all (latched topics transient local), and waits for every
message to be acknowledged before exiting. With ``--clock``, as ``ros2 bag play --clock``, it
also publishes the bag's time as ``rosgraph_msgs/Clock`` on ``/clock`` (best effort, depth 1:
``rclcpp::ClockQoS``): the record time of each message just before the message, and between
messages at ``HZ`` (default 40) the bag time reached, so that nodes with ``use_sim_time`` run on
the bag's time.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import rclpy
from rclpy._rclpy_pybind11 import RCLError  # what a refused publish raises (rclpy re-exports no name for it)
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.core.errors import ConfigError, LinearSlamError
from linear_slam_ros.ros.bagio import BagRecord, other_topics, read_messages
from linear_slam_ros.ros.qos import bag_topic_qos
from linear_slam_ros.ros.spin import node_session, wait_for_subscribers

DEFAULT_CLOCK_HZ = 40.0
"""Rate of ``/clock`` between messages with ``--clock`` (``ros2 bag play --clock``'s default)."""


def clock_qos() -> QoSProfile:
    """Return the ``/clock`` QoS of ROS 2 (``rclcpp::ClockQoS``): best effort, keep last 1, volatile."""
    return QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)


def clock_msg(time_ns: int) -> Clock:
    """Return a ``rosgraph_msgs/Clock`` at ``time_ns`` (ns since the epoch)."""
    msg = Clock()
    msg.clock.sec, msg.clock.nanosec = divmod(int(time_ns), 1_000_000_000)
    return msg


def play(
    node: Node, records: Sequence[BagRecord], rate_factor: float = 1.0, wait_s: float = 30.0,
    on_start: Callable[[], None] | None = None, clock_hz: float | None = None, subscribers: int = 1,
) -> float:
    """Publish bag records from ``node``; return the seconds spent publishing.

    Args:
        node: the node to publish from.
        records: messages in time order.
        rate_factor: bag-time speed-up (2.0 plays twice as fast; 0 or less: no pauses).
        wait_s: how long to wait for subscribers, and for acknowledgements at the end.
        on_start: called just before the first message is published (after discovery).
        clock_hz: publish the bag time on ``/clock`` (:func:`clock_msg`): at each message's
            record time, and at this rate (Hz) while waiting between messages; ``None``: no clock.
        subscribers: how many subscribers each topic waits for before the first message (a
            monitor such as ``ros2 topic echo`` counts: with one already there, 1 would start
            before the joiner has matched).

    Raises:
        ConfigError: ``clock_hz`` is not positive.
    """
    if clock_hz is not None and not clock_hz > 0:
        raise ConfigError(f"clock rate {clock_hz!r} Hz is not positive")
    clock = node.create_publisher(Clock, "/clock", clock_qos()) if clock_hz is not None else None
    publishers: dict[str, Publisher] = {}
    for r in records:
        if r.topic not in publishers:
            publishers[r.topic] = node.create_publisher(Float64MultiArray, r.topic, bag_topic_qos(r.latched))
    wait_for_subscribers(node, publishers, wait_s, subscribers)
    if on_start is not None:
        on_start()
    start_wall = time.monotonic()
    start_bag = records[0].time_ns if records else 0
    for r in records:
        if rate_factor > 0:
            due = start_wall + (r.time_ns - start_bag) / 1e9 / rate_factor
            if clock is not None and clock_hz is not None:  # the bag time advancing while waiting
                while due - time.monotonic() > 1.0 / clock_hz:
                    time.sleep(1.0 / clock_hz)
                    clock.publish(clock_msg(start_bag + int((time.monotonic() - start_wall) * rate_factor * 1e9)))
            pause = due - time.monotonic()
            if pause > 0:
                time.sleep(pause)
        if clock is not None:
            clock.publish(clock_msg(r.time_ns))
        _publish_when_room(publishers[r.topic], r.raw, wait_s, node.context.ok)
    elapsed = time.monotonic() - start_wall
    for pub in publishers.values():
        pub.wait_for_all_acked(rclpy.duration.Duration(seconds=wait_s))
    return elapsed


def _publish_when_room(publisher: Publisher, raw: bytes, wait_s: float, ok: Callable[[], bool]) -> None:
    """Publish, waiting while a reliable keep-all history is full (a subscriber behind a full-speed replay).

    The DDS writer refuses a sample when its history holds as many unacknowledged samples as its
    resource limits allow; nothing is lost by waiting for the subscriber to acknowledge some.

    Raises:
        RCLError: the history stayed full for ``wait_s`` seconds.
        ExternalShutdownException: ``ok()`` turned false (Ctrl-C, SIGTERM): the publisher is gone,
            waiting could only end in ``wait_s`` seconds of retries.
    """
    deadline = time.monotonic() + wait_s
    while True:
        try:
            publisher.publish(raw)
            return
        except RCLError:  # "cannot publish data": the history is full, or the context has been shut down
            if not ok():
                raise ExternalShutdownException() from None
            if time.monotonic() > deadline:
                raise
            time.sleep(0.002)


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    args_ros = rclpy.utilities.remove_ros_args(list(sys.argv if argv is None else argv))
    ap = argparse.ArgumentParser(prog="bag_player", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bag", type=Path)
    ap.add_argument("--rate-factor", type=float, default=1.0, help="speed-up of bag time (0: as fast as possible)")
    ap.add_argument("--wait", type=float, default=30.0, help="seconds to wait for subscribers and acknowledgements")
    ap.add_argument(
        "--subscribers", type=int, default=1, metavar="N",
        help="subscribers each topic waits for before playing (default 1; 2 with a monitor such as ros2 topic echo running)",
    )
    ap.add_argument(
        "--clock", type=float, nargs="?", const=DEFAULT_CLOCK_HZ, default=None, metavar="HZ",
        help=f"publish the bag time on /clock (rosgraph_msgs/Clock), at HZ between messages (default {DEFAULT_CLOCK_HZ:g})",
    )
    args = ap.parse_args(args_ros[1:])
    if args.subscribers < 1:
        print(f"bag_player: --subscribers {args.subscribers}: must be >= 1", file=sys.stderr)
        return 2
    if args.clock is not None and not args.clock > 0:
        print(f"bag_player: --clock {args.clock:g}: the clock rate must be positive (Hz)", file=sys.stderr)
        return 2
    try:
        records = list(read_messages(args.bag))
        skipped = other_topics(args.bag)
    except LinearSlamError as exc:
        print(f"bag_player: {exc}", file=sys.stderr)
        return 2
    with node_session("bag_player", argv) as node:
        if skipped:
            node.get_logger().warning(
                "not played (only std_msgs/msg/Float64MultiArray topics are): "
                + ", ".join(f"{t} ({m})" for t, m in sorted(skipped.items()))
            )
        try:
            seconds = play(node, records, args.rate_factor, args.wait, clock_hz=args.clock, subscribers=args.subscribers)
            node.get_logger().info(f"published {len(records)} messages in {seconds:.2f} s")
            return 0
        except TimeoutError as exc:
            node.get_logger().error(str(exc))
            return 1
        except (KeyboardInterrupt, ExternalShutdownException):  # Ctrl-C, SIGTERM
            return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
