"""The node's process tuning: one BLAS thread in every mode (``core.runtime.SHARED_MACHINE_BLAS_THREADS``)."""

from __future__ import annotations

import uuid

import pytest
from rclpy.parameter import Parameter

from linear_slam_ros.core.runtime import SHARED_MACHINE_BLAS_THREADS
from linear_slam_ros.ros import node as node_module


@pytest.mark.parametrize(("mode", "map_type"), [("online-dc", "as-is"), ("sequential", "as-is"), ("online-dc", "feature-only")])
def test_the_node_runs_blas_on_one_thread_whatever_its_mode(rclpy_session, monkeypatch, mode, map_type):
    threads: list[int | None] = []
    monkeypatch.setattr(node_module, "set_blas_threads", threads.append)
    monkeypatch.setattr(node_module, "tune_allocator", lambda threshold: True)  # this process's allocator stays as it is
    overrides = [Parameter("mode", value=mode), Parameter("map_type", value=map_type)]
    joiner = node_module.JoinerNode(namespace=f"t{uuid.uuid4().hex[:8]}", parameter_overrides=overrides)
    try:
        assert joiner.config.mode.value == mode
    finally:
        joiner.destroy_node()
    assert SHARED_MACHINE_BLAS_THREADS == 1 and threads == [1]
