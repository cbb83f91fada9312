"""ROS test support: loopback-only DDS in a domain of this run, the installed joiner as a process."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from linear_slam_ros.ros.process import loopback_env, stop_process  # imports no rclpy
from support import committed_bag, dataset_source, install_prefix

REPO = Path(__file__).resolve().parents[2]
INSTALL_SETUP = install_prefix().parent / "setup.bash"  # install/setup.bash of the repository or of a colcon workspace

# DDS stays on loopback, in a domain of this test run (20-59: never the default 0, nor `make`'s
# 61): the tests never meet another run's nodes.
os.environ.update(loopback_env(20 + os.getpid() % 40))

from rclpy.serialization import deserialize_message  # noqa: E402  (after the environment is set)
from std_msgs.msg import Float64MultiArray  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from linear_slam_ros.ros.bagio import BagRecord  # noqa: E402
from linear_slam_ros.ros.player import play  # noqa: E402
from linear_slam_ros.ros.spin import LatestMessage, spin_until  # noqa: E402
from msg_adapters import decode_map  # noqa: E402
from msg_adapters.ros import parts  # noqa: E402


def call_trigger(node, name: str, timeout_s: float = 30.0, attempts: int = 3):  # type: ignore[no-untyped-def]
    """Call the ``std_srvs/Trigger`` service ``name`` from ``node``; return its response.

    Asserts that the service appears within ``timeout_s`` and answers one of ``attempts`` requests,
    each given ``timeout_s``; the client is destroyed. A request is sent again when its answer does
    not come: rmw_fastrtps drops a service's response when the client's response reader has not
    matched after a short wait ("client will not receive response"; the server's rclpy only warns
    "failed to send response (timeout)"), which a loaded machine can meet right after
    ``wait_for_service`` (seen once in a full test run; not reproduced in 25 calls under load).
    The joiner's services (``save_map``, ``load_map``, ``reset``) are idempotent, so a second
    request changes nothing the first did not.
    """
    client = node.create_client(Trigger, name)
    try:
        assert client.wait_for_service(timeout_sec=timeout_s), f"service {name} did not appear"
        for _ in range(attempts):
            future = client.call_async(Trigger.Request())
            if spin_until(node, future.done, timeout_s, 0.05):
                return future.result()
            client.remove_pending_request(future)
        raise AssertionError(f"{name} did not answer {attempts} requests of {timeout_s} s each")
    finally:
        node.destroy_client(client)


def set_parameter(node, target: str, name: str, value: str, timeout_s: float = 30.0):  # type: ignore[no-untyped-def]
    """Set the string parameter ``name`` of the node ``target`` (its full name) as ``ros2 param set`` does; return the result."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    client = node.create_client(SetParameters, f"{target}/set_parameters")
    try:
        assert client.wait_for_service(timeout_sec=timeout_s), f"{target}/set_parameters did not appear"
        request = SetParameters.Request(parameters=[
            Parameter(name=name, value=ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)),
        ])
        future = client.call_async(request)
        assert spin_until(node, future.done, timeout_s, 0.05), f"{target}/set_parameters did not answer"
        return future.result().results[0]
    finally:
        node.destroy_client(client)


def dataset_bag(name: str) -> Path:
    """Return the bag of benchmark dataset ``name`` (10 Hz stamps): the committed one (bags/README.md), else
    ``bags/<name>``, made from the dataset when it is not there yet."""
    from linear_slam_ros.ros.bag_from_dataset import make_bag

    committed = committed_bag(name)
    if committed is not None:
        return committed
    bag = REPO / "bags" / name
    if not (bag / "metadata.yaml").exists():
        make_bag(dataset_source(name), bag, rate_hz=10.0)
    return bag


def sourced(command: str) -> list[str]:
    """Return a bash command line that runs ``command`` after ``source install/setup.bash``."""
    if not INSTALL_SETUP.exists():
        pytest.fail("install/setup.bash is missing: run `make setup` (colcon build) first")
    return ["bash", "-c", f"set +u; source {INSTALL_SETUP}; set -u; {command}"]


class JoinerProcess:
    """The installed ``lib/linear_slam_ros/joiner`` started as ``ros2 run`` would, in its own process."""

    def __init__(self, params: dict[str, object], namespace: str) -> None:
        args = " ".join(f"-p {k}:={v}" for k, v in params.items())
        cmd = (
            f"prefix=$({sys.executable} -c \"from ament_index_python.packages import get_package_prefix as p; "
            f"print(p('linear_slam_ros'))\"); exec \"$prefix/lib/linear_slam_ros/joiner\" --ros-args "
            f"--params-file {REPO}/config/joiner.yaml -r __ns:=/{namespace} {args}"
        )
        self.namespace = namespace
        self.process = subprocess.Popen(
            sourced(cmd), cwd=REPO, env=dict(os.environ), stdout=subprocess.PIPE, stderr=subprocess.STDOUT
        )

    def topic(self, name: str) -> str:
        return f"/{self.namespace}/{name.lstrip('/')}"  # a bag's names are fully qualified

    def play(self, node, records: list[BagRecord], wait_s: float = 60.0) -> float:
        """Play bag records into this joiner's namespace as fast as possible; return the seconds spent publishing."""
        return play(node, [r._replace(topic=self.topic(r.topic)) for r in records], rate_factor=0.0, wait_s=wait_s)

    def stop(self, timeout_s: float = 15.0) -> tuple[int, str]:
        """Stop the joiner (Ctrl-C, then kill); return its exit code and output."""
        code = stop_process(self.process, timeout_s)
        out = self.process.stdout.read().decode(errors="replace") if self.process.stdout else ""
        return code, out


def global_map_subscription(node, topic: str, decode: Callable[..., object] = decode_map) -> LatestMessage:
    """Subscribe to a joiner's latched ``global_map`` now (use it as a context manager); pass it to
    :func:`wait_for_global_map` as ``latest``.

    Subscribing before the joiner is fed makes its last map a live delivery: a subscription made
    after the joiner's last publication depends on the latched (transient-local) copy alone.
    """
    return LatestMessage(node, topic, lambda raw: decode(*parts(deserialize_message(raw, Float64MultiArray))))


def wait_for_global_map(node, topic: str, done: Callable[[object], bool], timeout_s: float, joiner: JoinerProcess | None = None,
                        decode: Callable[..., object] = decode_map, latest: LatestMessage | None = None):
    """Spin until a received global map (decoded by ``decode``) satisfies ``done``; return (message, receive time).

    ``latest``: an open :func:`global_map_subscription` of ``topic`` to wait on (default: subscribe now).
    """
    own = latest is None
    if latest is None:
        latest = global_map_subscription(node, topic, decode)
    try:
        try:
            satisfied = latest.wait(done, timeout_s, joiner.process if joiner is not None else None)
            exited = False
        except ChildProcessError:
            satisfied, exited = False, True
        if exited:  # fail outside the except block: the report shows the joiner's output, not a chain
            code, out = joiner.stop()
            pytest.fail(f"joiner exited with {code}:\n{out[-3000:]}")
        if not satisfied:
            last = latest.value
            seen = "none" if last is None else (
                f"n_submaps={getattr(last, 'n_submaps', '?')}, stats={getattr(last, 'stats', '?')}, "
                f"{time.monotonic() - latest.received_at:.1f} s before the timeout"
            )
            out = ""
            if joiner is not None:  # what the joiner said (resume line, warnings, summaries)
                code, out = joiner.stop()
                out = f"\njoiner output (exit {code}):\n{out[-3000:]}"
            pytest.fail(f"no satisfying global_map on {topic} within {timeout_s} s (last received: {seen}){out}")
        return latest.value, latest.received_at
    finally:
        if own:
            latest.close()
