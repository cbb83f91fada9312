"""bag_player: --clock (the bag's time on /clock while replaying, as ``ros2 bag play --clock``), --subscribers, shutdown."""

from __future__ import annotations

import time

import pytest
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.ros.bagio import BagRecord
from linear_slam_ros.ros.player import clock_msg, main, play

T0 = 1_700_000_000_000_000_000  # ns


def _records(topic: str, n: int = 5, step_ns: int = 50_000_000) -> list[BagRecord]:
    raw = serialize_message(Float64MultiArray(data=[1.0]))
    return [BagRecord(topic, T0 + k * step_ns, raw, False) for k in range(n)]


def test_clock_publishes_the_bag_time_before_each_message_and_between(node):
    topic = f"/{node.get_name()}/data"
    clocks: list[int] = []
    data: list[tuple[int, int]] = []  # (clock messages received before it, ...)
    node.create_subscription(  # deep enough to hold every tick until spun
        Clock, "/clock", lambda m: clocks.append(m.clock.sec * 1_000_000_000 + m.clock.nanosec),
        QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT),
    )
    node.create_subscription(Float64MultiArray, topic, lambda m: data.append(len(clocks)), QoSProfile(depth=1000))
    records = _records(topic)
    play(node, records, rate_factor=1.0, wait_s=20.0, clock_hz=100.0)
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and (len(data) < len(records) or not clocks or clocks[-1] != records[-1].time_ns):
        rclpy.spin_once(node, timeout_sec=0.05)
    assert len(data) == len(records)
    assert clocks[-1] == records[-1].time_ns
    assert clocks == sorted(clocks) and clocks[0] >= T0  # bag time, never going back
    assert {r.time_ns for r in records} <= set(clocks)  # each message's record time
    between = [c for c in clocks if c not in {r.time_ns for r in records}]
    assert len(between) >= 5  # 0.2 s of bag time at 100 Hz: the clock advances between messages too


def test_clock_message_and_bad_rates(node, tmp_path, capsys):
    msg = clock_msg(T0 + 123)
    assert (msg.clock.sec, msg.clock.nanosec) == (T0 // 1_000_000_000, 123)
    with pytest.raises(ConfigError, match=r"clock rate 0\.0 Hz is not positive"):
        play(node, [], clock_hz=0.0)
    assert main(["bag_player", str(tmp_path), "--clock", "-1"]) == 2
    assert "--clock -1: the clock rate must be positive (Hz)" in capsys.readouterr().err


def test_a_second_subscriber_can_be_waited_for_and_a_bad_count_is_refused(node, tmp_path, capsys):
    records = [BagRecord("local_map_two", T0, serialize_message(Float64MultiArray(data=[1.0])), False)]
    listener = node.create_subscription(Float64MultiArray, "local_map_two", lambda m: None, 10)
    try:
        with pytest.raises(TimeoutError, match=r"fewer than 2 subscribers on \['local_map_two'\]"):
            play(node, records, wait_s=0.5, subscribers=2)  # a monitor alone does not start the replay
    finally:
        node.destroy_subscription(listener)
    assert main(["bag_player", str(tmp_path), "--subscribers", "0"]) == 2
    assert "--subscribers 0: must be >= 1" in capsys.readouterr().err


def test_a_publish_refused_after_shutdown_stops_at_once():
    from rclpy._rclpy_pybind11 import RCLError
    from rclpy.executors import ExternalShutdownException

    from linear_slam_ros.ros.player import _publish_when_room

    class Refusing:
        calls = 0

        def publish(self, raw):
            Refusing.calls += 1
            raise RCLError("publisher's context is invalid")

    t0 = time.monotonic()
    with pytest.raises(ExternalShutdownException):
        _publish_when_room(Refusing(), b"", wait_s=30.0, ok=lambda: False)  # type: ignore[arg-type]
    assert time.monotonic() - t0 < 1.0 and Refusing.calls == 1  # it waited 30 s, retrying every 2 ms
