"""Child processes of the ROS tools and tests: a loopback-only environment, stopping them, and the
package's installed share directory.

Imports neither rclpy nor rosbags, so it can set the environment up before rclpy is imported.
"""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

DEFAULT_DOMAIN_ID = 42
"""The ROS domain id :func:`loopback_env` sets when none is set already (never the default 0)."""


def loopback_env(domain_id: int | None = None, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """Return an environment with DDS discovery confined to loopback and a ROS domain id set.

    Args:
        domain_id: the ``ROS_DOMAIN_ID`` to use (a test run's own domain); ``None`` keeps one
            already set, or sets :data:`DEFAULT_DOMAIN_ID`.
        base: the environment to start from (default this process's ``os.environ``), copied
            unchanged otherwise: ROS from PyPI wheels needs the parent's ``LD_LIBRARY_PATH``
            and bootstrap marker together in a child.
    """
    env = dict(os.environ if base is None else base)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    else:
        env.setdefault("ROS_DOMAIN_ID", str(DEFAULT_DOMAIN_ID))
    return env


def stop_process(process: subprocess.Popen[Any], timeout_s: float = 10.0) -> int:
    """Stop a process as Ctrl-C would (SIGINT), killing it if it has not exited after ``timeout_s``.

    A process that has already exited is left alone. Returns its exit code (negative: the
    signal that ended it, e.g. -9 when it had to be killed).
    """
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return int(process.returncode)


def share_directory() -> Path | None:
    """The package's installed share directory (``None`` when it runs from the source tree)."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    except ImportError:  # pragma: no cover - ament_index comes with rclpy
        return None
    try:
        return Path(get_package_share_directory("linear_slam_ros"))
    except PackageNotFoundError:
        return None
