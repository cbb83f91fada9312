"""The node's inbound path: a subscription callback drains its own queue (``take_queued``, ``DRAIN_MAX``)
and publishes the newest pose once for what it took (``POSE_COALESCE_S``)."""

from __future__ import annotations

import time
import uuid
from types import SimpleNamespace

from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.ros.node import DRAIN_MAX, POSE_COALESCE_S, JoinerNode, take_queued
from linear_slam_ros.ros.spin import wait_for_subscribers


def test_take_queued_takes_what_waits_in_order_then_none(node):
    topic = f"inbound_{uuid.uuid4().hex[:8]}"
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    sub = node.create_subscription(Float64MultiArray, topic, lambda _raw: None, qos, raw=True)
    pub = node.create_publisher(Float64MultiArray, topic, qos)
    wait_for_subscribers(node, {topic: pub}, timeout_s=10.0)
    for i in range(5):
        pub.publish(Float64MultiArray(data=[float(i)]))
    taken: list[float] = []
    deadline = time.monotonic() + 10.0
    while len(taken) < 5 and time.monotonic() < deadline:  # DDS delivers them within milliseconds
        raw = take_queued(sub)
        if raw is None:
            time.sleep(0.01)
            continue
        assert isinstance(raw, bytes)  # a raw subscription's serialised message
        taken.append(deserialize_message(raw, Float64MultiArray).data[0])
    assert taken == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert take_queued(sub) is None  # nothing left
    assert take_queued(None) is None  # not created yet
    node.destroy_subscription(sub)
    assert take_queued(sub) is None  # destroyed: nothing to take, no exception


class _FakeHandle:
    """What ``take_queued`` uses of an rclpy subscription handle: a context and ``take_message``."""

    def __init__(self, queue: list[bytes]) -> None:
        self.queue = queue

    def __enter__(self) -> _FakeHandle:
        return self

    def __exit__(self, *_exc: object) -> None:
        return None

    def take_message(self, _msg_type: type, raw: bool) -> tuple[bytes, object] | None:
        assert raw
        return (self.queue.pop(0), None) if self.queue else None


def test_the_callback_takes_its_message_then_at_most_drain_max_queued_ones_in_order():
    received: list[tuple[str, bytes, str]] = []
    flushed: list[int] = []  # messages received when each flush came
    fake_node = SimpleNamespace(_receive=lambda topic, raw, robot: received.append((topic, raw, robot)),
                                _flush_poses=lambda: flushed.append(len(received)), context=SimpleNamespace(ok=lambda: True))
    receive = JoinerNode._receiver(fake_node, "r1/pose_graph", "r1")  # type: ignore[arg-type]
    assert receive.subscription is None
    receive(b"first")  # before the subscription is set: only the message given
    assert received == [("r1/pose_graph", b"first", "r1")]
    assert flushed == [1]
    queue = [f"m{i}".encode() for i in range(DRAIN_MAX + 3)]
    receive.subscription = SimpleNamespace(handle=_FakeHandle(queue), msg_type=Float64MultiArray, raw=True)  # type: ignore[assignment]
    received.clear()
    receive(b"given")
    assert [raw for _, raw, _ in received] == [b"given"] + [f"m{i}".encode() for i in range(DRAIN_MAX)]
    assert len(queue) == 3  # left for the executor's next round
    assert flushed == [1, DRAIN_MAX + 1]  # once, after the drain
    received.clear()
    receive(b"again")
    assert [raw for _, raw, _ in received] == [b"again"] + [f"m{i}".encode() for i in range(DRAIN_MAX, DRAIN_MAX + 3)]  # ran dry


def test_a_drain_holds_the_pose_back_at_most_pose_coalesce_s_and_the_flush_publishes_it(monkeypatch):
    published: list[tuple[str, list[int], str]] = []
    fake_node = SimpleNamespace(_pending_pose={}, context=SimpleNamespace(ok=lambda: True))
    fake_node._publish_pose = lambda state, joined, robot: published.append((state, list(joined), robot))
    now = [100.0]
    monkeypatch.setattr(time, "monotonic", lambda: now[0])
    coalesce = JoinerNode._coalesce_pose

    coalesce(fake_node, "s1", [1], "", 100.0)  # just arrived: held back for what is queued behind it
    now[0] += POSE_COALESCE_S / 2
    coalesce(fake_node, "s2", [2, 3], "", now[0])  # one pose for both, the newest state's
    assert published == []
    coalesce(fake_node, "x1", [7], "robot_b", now[0])  # another robot's pose is held apart
    JoinerNode._flush_poses(fake_node)
    assert sorted(published) == [("s2", [1, 2, 3], ""), ("x1", [7], "robot_b")]
    assert fake_node._pending_pose == {}

    published.clear()
    coalesce(fake_node, "s4", [4], "", now[0])
    now[0] += POSE_COALESCE_S  # the oldest submap held arrived POSE_COALESCE_S ago: published at once
    coalesce(fake_node, "s5", [5], "", now[0])
    assert published == [("s5", [4, 5], "")]
    assert fake_node._pending_pose == {}
    coalesce(fake_node, "s6", [6], "", now[0] - 2 * POSE_COALESCE_S)  # a submap that waited already
    assert published[-1] == ("s6", [6], "")
    JoinerNode._flush_poses(fake_node)  # nothing held: nothing more
    assert len(published) == 2
