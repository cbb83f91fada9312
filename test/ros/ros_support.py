"""ROS test support: loopback-only DDS in a domain of this run, the installed joiner as a process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import pytest

REPO = Path(__file__).resolve().parents[2]
INSTALL_SETUP = REPO / "install" / "setup.bash"

# DDS stays on loopback, in a domain of this test run (never the default 0).
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ["ROS_DOMAIN_ID"] = str(20 + os.getpid() % 70)

import rclpy  # noqa: E402  (after the environment is set)
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from msg_adapters import decode_map  # noqa: E402
from msg_adapters.ros import parts  # noqa: E402

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


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
        self.process = subprocess.Popen(sourced(cmd), cwd=REPO, env=dict(os.environ), stdout=subprocess.PIPE, stderr=subprocess.STDOUT)

    def topic(self, name: str) -> str:
        return f"/{self.namespace}/{name}"

    def stop(self, timeout_s: float = 15.0) -> tuple[int, str]:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        out = self.process.stdout.read().decode(errors="replace") if self.process.stdout else ""
        return int(self.process.returncode), out


def wait_for_global_map(node, topic: str, done: Callable[[object], bool], timeout_s: float, joiner: JoinerProcess | None = None,
                        decode: Callable[..., object] = decode_map):
    """Spin until a received global map (decoded by ``decode``) satisfies ``done``; return (message, receive time)."""
    latest: dict[str, object] = {}
    sub = node.create_subscription(Float64MultiArray, topic, lambda m: latest.update(msg=m, t=time.monotonic()), LATCHED)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
            if "msg" in latest:
                decoded = decode(*parts(latest["msg"]))
                if done(decoded):
                    return decoded, latest["t"]
            if joiner is not None and joiner.process.poll() is not None:
                code, out = joiner.stop()
                pytest.fail(f"joiner exited with {code}:\n{out[-3000:]}")
        pytest.fail(f"no satisfying global_map on {topic} within {timeout_s} s (last: {latest.get('msg') is not None})")
    finally:
        node.destroy_subscription(sub)
