"""The installed layout is what `ros2 run linear_slam_ros joiner` resolves, and it starts the node."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from std_srvs.srv import Trigger

from linear_slam_ros.ros.spin import spin_until
from ros_support import sourced
from support import install_prefix


def test_ament_index_finds_the_package_and_its_executable(node, start_joiner):
    out = subprocess.run(
        sourced(f"{sys.executable} -c \"from ament_index_python.packages import get_package_prefix as p, "
                "get_package_share_directory as s; print(p('linear_slam_ros')); print(s('linear_slam_ros'))\""),
        capture_output=True, text=True, env=dict(os.environ), check=True,
    ).stdout.split()
    prefix, share = Path(out[0]), Path(out[1])
    exe = prefix / "lib" / "linear_slam_ros" / "joiner"
    assert exe.is_file() and os.access(exe, os.X_OK)
    assert (share / "package.xml").is_file() and (share / "config" / "joiner.yaml").is_file()
    for tool in ("bag_from_dataset", "bag_player", "bag_recorder", "demo"):
        assert os.access(prefix / "lib" / "linear_slam_ros" / tool, os.X_OK)
    assert prefix.resolve() == install_prefix().resolve()  # the tree this test run sourced

    joiner = start_joiner()
    appeared = spin_until(node, lambda: ("joiner", f"/{joiner.namespace}") in node.get_node_names_and_namespaces(), 30.0, 0.1)
    assert appeared, f"node joiner did not appear: {node.get_node_names_and_namespaces()}"
    # the node is discoverable from the start of its constructor: stop it once the constructor is done
    # (its services are made near the end, the "ready" line right after)
    client = node.create_client(Trigger, f"/{joiner.namespace}/joiner/save_map")
    assert client.wait_for_service(timeout_sec=30.0)
    time.sleep(0.5)
    code, output = joiner.stop()
    assert code == 0, output  # Ctrl-C is a clean exit
    assert "joiner ready: mode=online-dc" in output  # the default mode
