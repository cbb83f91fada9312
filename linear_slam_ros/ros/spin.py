"""Spinning a node until something happens: the waits the ROS tools and tests share.

- :func:`node_session`: ``rclpy.init``, one node, and their teardown.
- :func:`spin_until`: spin until a condition holds or time runs out.
- :func:`wait_for_subscribers`: spin until every publisher sees a subscriber (DDS discovery
  takes up to a few seconds, and volatile messages published before it are lost).
- :class:`LatestMessage`: keep the newest message of a latched topic and wait for one that
  satisfies a condition, while watching the process that should publish it.
- :func:`wait_for_diagnostics`, :func:`diagnostic_values`: spin until a ``/diagnostics`` status
  carries the wanted values; a status's numeric values.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from types import TracebackType
from typing import Any, Generic, TypeVar

import rclpy
from rclpy.node import Node
from rclpy.publisher import Publisher
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.ros.qos import latched_qos

T = TypeVar("T")


def print_usage_if_asked(args: Sequence[str] | None, name: str, text: str) -> bool:
    """Print ``text`` as ``name``'s usage and return True when ``args`` (default ``sys.argv``), ROS
    arguments aside, ask for ``-h``/``--help``: a node's executable otherwise starts the node."""
    asked = rclpy.utilities.remove_ros_args(list(sys.argv if args is None else args))[1:]
    if not {"-h", "--help"} & set(asked):
        return False
    print(f"usage: ros2 run linear_slam_ros {name} [--ros-args -p NAME:=VALUE | --params-file FILE ...]\n\n{text}")
    return True


@contextmanager
def node_session(name: str, args: Sequence[str] | None = None) -> Iterator[Node]:
    """Initialise rclpy (with ``args``, default ``sys.argv``), yield a node called ``name``,
    then destroy the node and shut rclpy down, however the block ends."""
    rclpy.init(args=None if args is None else list(args))
    try:
        node = rclpy.create_node(name)
        try:
            yield node
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()


def spin_until(node: Node, done: Callable[[], bool], timeout_s: float, period_s: float = 0.05) -> bool:
    """Spin ``node`` until ``done()`` is true; return False if ``timeout_s`` passed first.

    ``done`` is checked before each spin of at most ``period_s`` seconds; an exception it
    raises ends the wait.
    """
    deadline = time.monotonic() + timeout_s
    while not done():
        if time.monotonic() >= deadline:
            return False
        rclpy.spin_once(node, timeout_sec=period_s)
    return True


def wait_for_subscribers(node: Node, publishers: Mapping[str, Publisher], timeout_s: float, count: int = 1) -> None:
    """Spin until each publisher (by topic) sees at least ``count`` subscribers.

    Raises:
        TimeoutError: some topic had fewer within ``timeout_s``.
    """
    if not spin_until(node, lambda: all(p.get_subscription_count() >= count for p in publishers.values()), timeout_s):
        missing = [t for t, p in publishers.items() if p.get_subscription_count() < count]
        what = "no subscriber" if count == 1 else f"fewer than {count} subscribers"
        raise TimeoutError(f"{what} on {missing} after {timeout_s:.0f} s")


class LatestMessage(Generic[T]):
    """The newest message of a latched ``Float64MultiArray`` topic, as CDR bytes and decoded.

    Subscribes with :func:`~linear_slam_ros.ros.qos.latched_qos` (so a message published before
    the subscription is received too) until :meth:`close` (or the end of a ``with`` block).
    A message is decoded once, when it is first looked at.
    """

    def __init__(self, node: Node, topic: str, decode: Callable[[bytes], T]) -> None:
        self.node = node
        self.topic = topic
        self._decode = decode
        self.raw: bytes | None = None
        """CDR bytes of the newest message (None before the first)."""
        self.received_at = 0.0
        """``time.monotonic()`` when the newest message arrived."""
        self._value: T | None = None
        self._stale = False
        self._sub = node.create_subscription(Float64MultiArray, topic, self._on_message, latched_qos(), raw=True)

    def _on_message(self, raw: bytes) -> None:
        self.raw = bytes(raw)
        self.received_at = time.monotonic()
        self._stale = True

    @property
    def value(self) -> T | None:
        """The newest message decoded (None before the first)."""
        if self._stale and self.raw is not None:
            self._value = self._decode(self.raw)
            self._stale = False
        return self._value

    def wait(self, done: Callable[[T], bool], timeout_s: float, process: subprocess.Popen[Any] | None = None) -> bool:
        """Spin until the newest message satisfies ``done``; return False if none did within ``timeout_s``.

        Raises:
            ChildProcessError: ``process`` (the publisher, when given) exited first.
        """

        def satisfied() -> bool:
            value = self.value
            if value is not None and done(value):
                return True
            if process is not None and process.poll() is not None:
                code = process.returncode
                raise ChildProcessError(f"process {process.pid} exited with code {code} while waiting on {self.topic}")
            return False

        return spin_until(self.node, satisfied, timeout_s)

    def close(self) -> None:
        """Destroy the subscription."""
        self.node.destroy_subscription(self._sub)

    def __enter__(self) -> LatestMessage[T]:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


def wait_for_diagnostics(
    node: Node, done: Callable[[dict[str, float]], bool], timeout_s: float, name_prefix: str = "joiner"
) -> dict[str, float] | None:
    """Spin until a ``/diagnostics`` status named ``name_prefix...`` has values satisfying ``done``.

    Returns:
        The status's numeric values (``{key: value}``), or ``None`` if none came within ``timeout_s``.
    """
    from diagnostic_msgs.msg import DiagnosticArray

    found: list[dict[str, float]] = []

    def on_status(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.lstrip("/").startswith(name_prefix):
                values = diagnostic_values(status)
                if done(values):
                    found.append(values)

    sub = node.create_subscription(DiagnosticArray, "/diagnostics", on_status, 10)
    try:
        spin_until(node, lambda: bool(found), timeout_s)
    finally:
        node.destroy_subscription(sub)
    return found[0] if found else None


def diagnostic_values(status: Any) -> dict[str, float]:
    """Return the numeric values of a ``diagnostic_msgs/DiagnosticStatus`` (non-numeric ones left out)."""
    values = {}
    for kv in status.values:
        try:
            values[kv.key] = float(kv.value)
        except ValueError:
            continue
    return values
