"""The joiner stops cleanly when signalled mid-stream: SIGTERM (``ros2 launch``'s stop, ``kill``) and SIGINT
(Ctrl-C) end it with code 0 and no traceback while a callback is still draining its queue.

rclpy's signal handler shuts the context down under that callback: the next publication raised
``RCLError: publisher's context is invalid``, which ended the node with code 1 (SIGTERM: 6 of 7 runs
mid-stream; SIGINT: 2 of 9) and an ERROR line on the output thread.
"""

from __future__ import annotations

import signal
import subprocess
from types import SimpleNamespace

import pytest

from linear_slam_ros.ros import node as node_module
from linear_slam_ros.ros.bagio import read_messages
from ros_support import global_map_subscription
from support import committed_bag


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_mid_stream_stops_the_joiner_with_code_0_and_no_traceback(node, start_joiner, signum) -> None:
    records = list(read_messages(committed_bag("manhattanOlson3500")))  # 3499 chunks: seconds of joining
    joiner = start_joiner(publish_rate=20.0)
    with global_map_subscription(node, joiner.topic("global_map")) as latest:
        joiner.play(node, records)  # every chunk delivered to the joiner's queue; far from all joined yet
        assert latest.wait(lambda m: m.n_submaps >= 100, 60.0, joiner.process), "no global_map of 100 submaps"
        assert latest.value.n_submaps < len(records), "the joiner finished before the signal: nothing tested"
    joiner.process.send_signal(signum)
    try:
        code = joiner.process.wait(20.0)
    except subprocess.TimeoutExpired:
        code, out = joiner.stop()
        pytest.fail(f"the joiner did not stop within 20 s of {signum.name} (then: {code}):\n{out[-3000:]}")
    out = joiner.process.stdout.read().decode(errors="replace") if joiner.process.stdout else ""
    assert code == 0, f"{signum.name}: exit code {code}\n{out[-3000:]}"
    assert "Traceback" not in out and "[ERROR]" not in out, out[-3000:]


class _Stopped(Exception):
    """Stands in for rclpy's ``RCLError`` raised by a publication after the context was shut down."""


def _main_with(monkeypatch, context_ok: bool) -> None:
    """Run ``node.main`` with a node whose spin raises :class:`_Stopped` and whose context is (not) ok."""
    destroyed: list[bool] = []
    fake = SimpleNamespace(context=SimpleNamespace(ok=lambda: context_ok), destroy_node=lambda: destroyed.append(True))

    class Executor:
        def add_node(self, node: object) -> None:
            pass

        def spin(self) -> None:
            raise _Stopped("Failed to publish: publisher's context is invalid")

    monkeypatch.setattr(node_module, "JoinerNode", lambda: fake)
    monkeypatch.setattr(node_module, "SingleThreadedExecutor", Executor)
    monkeypatch.setattr(node_module, "inbound_dds_profile", lambda env, share: None)
    monkeypatch.setattr(node_module.rclpy, "init", lambda args=None: None)
    monkeypatch.setattr(node_module.rclpy, "try_shutdown", lambda: None)
    monkeypatch.setattr(node_module.gc, "freeze", lambda: None)
    try:
        node_module.main([])
    finally:
        assert destroyed == [True]  # the node is destroyed either way (snapshots, refiner, threads)


def test_an_error_raised_once_the_context_is_shut_down_is_a_normal_stop(monkeypatch) -> None:
    _main_with(monkeypatch, context_ok=False)  # returns: exit code 0


def test_an_error_while_the_context_runs_is_not_hidden(monkeypatch) -> None:
    with pytest.raises(_Stopped, match="publisher's context is invalid"):
        _main_with(monkeypatch, context_ok=True)


def test_a_shut_down_callback_takes_nothing_more_from_its_queue() -> None:
    received: list[bytes] = []
    flushed: list[bool] = []
    receiver = node_module._Receiver(
        lambda topic, raw, robot: received.append(raw), lambda: flushed.append(True), "local_map", "", ok=lambda: False,
    )
    receiver.subscription = SimpleNamespace()  # take_queued would fail on it: nothing may be taken
    receiver(b"first")
    assert received == [b"first"] and flushed == [True]
