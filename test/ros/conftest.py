"""Fixtures of the ROS tests (see ros_support for the helpers)."""

from __future__ import annotations

import uuid
from collections.abc import Callable

import pytest
import rclpy

from ros_support import JoinerProcess


def pytest_collection_modifyitems(items):
    for item in items:
        if "/ros/" in str(item.fspath):
            item.add_marker(pytest.mark.ros)
            # `make test` runs two pytest-xdist workers with --dist loadgroup: the tests that start ROS
            # nodes all run on one of them, one at a time (their joiner processes need the other core's
            # share, and their DDS domain is chosen per worker process), the others on the second.
            item.add_marker(pytest.mark.xdist_group("ros"))


@pytest.fixture(scope="session")
def rclpy_session():
    rclpy.init()
    yield
    rclpy.try_shutdown()


@pytest.fixture
def node(rclpy_session):
    n = rclpy.create_node(f"test_{uuid.uuid4().hex[:8]}")
    yield n
    n.destroy_node()


@pytest.fixture
def start_joiner() -> Callable[..., JoinerProcess]:
    started: list[JoinerProcess] = []

    def start(namespace: str | None = None, **params: object) -> JoinerProcess:
        jp = JoinerProcess(params, namespace or f"t{uuid.uuid4().hex[:8]}")
        started.append(jp)
        return jp

    yield start
    for jp in started:  # leave no process behind
        jp.stop()
