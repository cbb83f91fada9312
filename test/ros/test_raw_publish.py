"""Publishing a serialised message through rcl (``linear_slam_ros.ros.raw_publish``)."""

from __future__ import annotations

import time
import uuid

import numpy as np
import pytest
import rclpy
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.ros import raw_publish
from linear_slam_ros.ros.qos import latched_qos
from linear_slam_ros.ros.raw_publish import PublishError, publish_serialized
from linear_slam_ros.ros.spin import wait_for_subscribers
from msg_adapters.cdr import to_cdr
from msg_adapters.layout import Encoded
from msg_adapters.ros import parts


def _received(node, topic: str, send) -> list[Float64MultiArray]:
    got: list[Float64MultiArray] = []
    sub = node.create_subscription(Float64MultiArray, topic, got.append, latched_qos())
    pub = node.create_publisher(Float64MultiArray, topic, latched_qos())
    wait_for_subscribers(node, {topic: pub}, timeout_s=10.0)
    send(pub)
    deadline = time.monotonic() + 10.0
    while not got and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    node.destroy_subscription(sub)
    node.destroy_publisher(pub)
    return got


def _content(rng) -> Encoded:
    segments = (np.arange(9.0), np.arange(5, dtype=np.int32), rng.standard_normal(1000))
    return Encoded(("header", "info_rows", "info_vals"), segments)


def test_a_serialised_message_arrives_as_the_message_through_rcl(node, rng):
    assert raw_publish._rcl() is not None  # this Jazzy: the ctypes path, not the fallback
    enc = _content(rng)
    got = _received(node, f"raw_{uuid.uuid4().hex[:8]}", lambda pub: publish_serialized(pub, to_cdr(enc)))
    assert len(got) == 1
    labels, sizes, data, offset = parts(got[0])
    assert (labels, sizes, offset) == (list(enc.labels), list(enc.sizes), 0)
    assert data.tobytes() == enc.data.tobytes()


def test_without_librcl_it_publishes_the_same_bytes_through_rclpy(node, rng, monkeypatch):
    monkeypatch.setattr(raw_publish, "_rcl", lambda: None)
    enc = _content(rng)
    got = _received(node, f"raw_{uuid.uuid4().hex[:8]}", lambda pub: publish_serialized(pub, to_cdr(enc)))
    assert len(got) == 1 and np.frombuffer(got[0].data, dtype=np.float64).tobytes() == enc.data.tobytes()


def test_an_rcl_error_is_raised_with_its_code_and_topic(node, monkeypatch):
    real = raw_publish._rcl()
    assert real is not None
    monkeypatch.setattr(raw_publish, "_rcl", lambda: (lambda *_args: 1, real[1]))  # RCL_RET_ERROR
    pub = node.create_publisher(Float64MultiArray, "raw_error", latched_qos())
    with pytest.raises(PublishError, match=r"rcl_publish_serialized_message on /raw_error returned 1"):
        publish_serialized(pub, to_cdr(Encoded.of(("a",), (1,), [1.0])))
    node.destroy_publisher(pub)


def test_the_loaded_rcl_is_found_by_its_mapping():
    path = raw_publish._loaded_library("librcl.so")
    assert path is not None and path.endswith("/librcl.so")
    assert raw_publish._loaded_library("libno_such_library_here.so") is None
