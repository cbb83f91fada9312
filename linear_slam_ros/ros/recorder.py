"""Record topics (``global_map`` by default) into a rosbag2 MCAP bag.

``bag_recorder --out BAG [--topics global_map] [--count N] [--duration S]``: subscribes
reliable and transient local (so a latched map published before start is received too), keeps
every message as received, and writes the bag when it stops: after N messages, S seconds,
Ctrl-C or SIGTERM. It records the node's latched ``Float64MultiArray`` outputs (``global_map``,
``global_map_refined``): a volatile publisher (``local_map``) cannot serve a transient-local
subscription, and other types are not received. Every recorded topic is written as latched, as
its publisher offered it. An ``--out`` that exists and is not a bag is refused before recording.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.core.errors import DatasetError
from linear_slam_ros.ros.bagio import check_replaceable_bag, write_messages
from linear_slam_ros.ros.qos import recorder_qos
from linear_slam_ros.ros.spin import node_session, spin_until


class Recorder:
    """Collects raw messages of some topics from a node, under their resolved names (``/global_map``:
    what ``ros2 topic list`` shows and ``ros2 bag record`` stores).

    Attributes:
        names: the resolved name of each topic, in the order given.
    """

    def __init__(self, node: Node, topics: Sequence[str]) -> None:
        self.records: list[tuple[str, int, bytes]] = []
        self.names = [node.resolve_topic_name(topic) for topic in topics]
        for name in self.names:
            node.create_subscription(Float64MultiArray, name, self._callback(name), recorder_qos(), raw=True)
        self._clock = node.get_clock()

    def _callback(self, topic: str) -> Callable[[bytes], None]:
        def on_message(raw: bytes) -> None:
            self.records.append((topic, self._clock.now().nanoseconds, bytes(raw)))

        return on_message

    def save(self, path: Path, latched: set[str]) -> int:
        """Write what was received to a bag; return the number of messages."""
        return write_messages(path, self.records, latched=latched, overwrite=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    args_ros = rclpy.utilities.remove_ros_args(list(sys.argv if argv is None else argv))
    ap = argparse.ArgumentParser(prog="bag_recorder", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--topics", nargs="+", default=["global_map"])
    ap.add_argument("--count", type=int, default=0, help="stop after this many messages (0: no limit)")
    ap.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: no limit)")
    args = ap.parse_args(args_ros[1:])
    if args.out.exists():
        try:
            check_replaceable_bag(args.out)
        except DatasetError as exc:
            print(f"bag_recorder: {exc}", file=sys.stderr)
            return 2
    with node_session("bag_recorder", argv) as node:
        recorder = Recorder(node, args.topics)
        try:
            spin_until(
                node,
                lambda: not rclpy.ok() or 0 < args.count <= len(recorder.records),
                args.duration if args.duration > 0 else math.inf,
                period_s=0.1,
            )
        except (KeyboardInterrupt, ExternalShutdownException):  # Ctrl-C, SIGTERM: the bag is written all the same
            pass
        finally:
            n = recorder.save(args.out, latched=set(recorder.names))  # subscribed transient local: latched publishers
            print(f"bag_recorder: recorded {n} messages to {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
