"""Replay a rosbag2 bag into running nodes through rclpy, as ``ros2 bag play`` would.

``bag_player BAG [--rate-factor 1.0] [--wait 30]``: waits until every topic has a subscriber,
then publishes each message at its bag time divided by the rate factor (0: as fast as
possible), reliable and keeping all (latched topics transient local), and waits for every
message to be acknowledged before exiting.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import rclpy
from rclpy._rclpy_pybind11 import RCLError  # what a refused publish raises (rclpy re-exports no name for it)
from rclpy.node import Node
from rclpy.publisher import Publisher
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.core.errors import LinearSlamError
from linear_slam_ros.ros.bagio import BagRecord, read_messages
from linear_slam_ros.ros.qos import bag_topic_qos
from linear_slam_ros.ros.spin import node_session, wait_for_subscribers


def play(
    node: Node, records: Sequence[BagRecord], rate_factor: float = 1.0, wait_s: float = 30.0,
    on_start: Callable[[], None] | None = None,
) -> float:
    """Publish bag records from ``node``; return the seconds spent publishing.

    Args:
        node: the node to publish from.
        records: messages in time order.
        rate_factor: bag-time speed-up (2.0 plays twice as fast; 0 or less: no pauses).
        wait_s: how long to wait for subscribers, and for acknowledgements at the end.
        on_start: called just before the first message is published (after discovery).
    """
    publishers: dict[str, Publisher] = {}
    for r in records:
        if r.topic not in publishers:
            publishers[r.topic] = node.create_publisher(Float64MultiArray, r.topic, bag_topic_qos(r.latched))
    wait_for_subscribers(node, publishers, wait_s)
    if on_start is not None:
        on_start()
    start_wall = time.monotonic()
    start_bag = records[0].time_ns if records else 0
    for r in records:
        if rate_factor > 0:
            due = start_wall + (r.time_ns - start_bag) / 1e9 / rate_factor
            pause = due - time.monotonic()
            if pause > 0:
                time.sleep(pause)
        _publish_when_room(publishers[r.topic], r.raw, wait_s)
    elapsed = time.monotonic() - start_wall
    for pub in publishers.values():
        pub.wait_for_all_acked(rclpy.duration.Duration(seconds=wait_s))
    return elapsed


def _publish_when_room(publisher: Publisher, raw: bytes, wait_s: float) -> None:
    """Publish, waiting while a reliable keep-all history is full (a subscriber behind a full-speed replay).

    The DDS writer refuses a sample when its history holds as many unacknowledged samples as its
    resource limits allow; nothing is lost by waiting for the subscriber to acknowledge some.

    Raises:
        RCLError: the history stayed full for ``wait_s`` seconds.
    """
    deadline = time.monotonic() + wait_s
    while True:
        try:
            publisher.publish(raw)
            return
        except RCLError:  # "cannot publish data": the history is full
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
    args = ap.parse_args(args_ros[1:])
    try:
        records = list(read_messages(args.bag))
    except LinearSlamError as exc:
        print(f"bag_player: {exc}", file=sys.stderr)
        return 2
    with node_session("bag_player", argv) as node:
        try:
            seconds = play(node, records, args.rate_factor, args.wait)
            node.get_logger().info(f"published {len(records)} messages in {seconds:.2f} s")
            return 0
        except TimeoutError as exc:
            node.get_logger().error(str(exc))
            return 1
        except KeyboardInterrupt:
            return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
