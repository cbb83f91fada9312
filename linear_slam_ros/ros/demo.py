"""The main job: replay a dataset's bag through a running ``joiner`` and write what it produced.

``demo [--dataset ARCHIVE] [--bag bags/vicpark200] [--out out] [--mode sequential]``

Starts the joiner as its own process (the colcon-installed ``lib/linear_slam_ros/joiner`` when
ament can find it), plays the bag into it over DDS on loopback, waits for the latched
``global_map`` that has joined every submap, and writes ``OUT/poses.txt``, ``features.txt``
(first pose's frame), ``report.json``, ``map.png`` and ``global_map_bag``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Sequence

import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.cli.main import write_result
from linear_slam_ros.io.datasets import read_dataset
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.plots import plot_map
from linear_slam_ros.ros.bag_from_dataset import make_bag
from linear_slam_ros.ros.bagio import read_messages, write_messages
from linear_slam_ros.ros.player import play
from msg_adapters import decode_map
from msg_adapters.bags import bag_parts, deserialize

DEFAULT_DATASET = Path("../shared/datasets/VicPark_200_local_maps.tar.xz")


def loopback_env(domain_id: int | None = None) -> dict[str, str]:
    """Return this process's environment with DDS confined to loopback and a domain id set."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("ROS_DOMAIN_ID", str(domain_id if domain_id is not None else 42))
    return env


def joiner_command() -> list[str]:
    """Return the command that starts the joiner: the installed executable, as ``ros2 run`` would."""
    try:
        from ament_index_python.packages import get_package_prefix

        exe = Path(get_package_prefix("linear_slam_ros")) / "lib" / "linear_slam_ros" / "joiner"
        if exe.exists():
            return [str(exe)]
    except Exception:  # not installed with colcon: run the module with this interpreter
        pass
    return [sys.executable, "-m", "linear_slam_ros.ros.node"]


def start_joiner(params: dict[str, object], env: dict[str, str]) -> subprocess.Popen[bytes]:
    """Start the joiner process with ``-p name:=value`` parameters."""
    cmd = joiner_command() + ["--ros-args"]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={v}"]
    return subprocess.Popen(cmd, env=env)


def stop(process: subprocess.Popen[bytes], timeout_s: float = 10.0) -> int:
    """Stop a process with Ctrl-C (SIGINT), killing it if it does not exit; return its code."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return int(process.returncode)


def run_demo(dataset: Path, bag: Path, out: Path, mode: str = "sequential", rate_factor: float = 0.0, timeout_s: float = 300.0) -> dict[str, object]:
    """Replay ``bag`` through a joiner process; write and return the report."""
    if not (bag / "metadata.yaml").exists():
        make_bag(dataset, bag)
    records = list(read_messages(bag))
    n_sent = len(records)
    os.environ.update(loopback_env())
    joiner = start_joiner({"mode": mode, "output_frame": "end_pose", "publish_rate": 20.0}, dict(os.environ))
    rclpy.init()
    node = rclpy.create_node("demo")
    latest: dict[str, object] = {}
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(Float64MultiArray, "global_map", lambda raw: latest.update(raw=bytes(raw), t=time.monotonic()), qos, raw=True)
    try:
        t0 = time.monotonic()
        play(node, records, rate_factor=rate_factor, wait_s=60.0)
        deadline = time.monotonic() + timeout_s
        message = None
        while time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
            if "raw" in latest:
                message = decode_map(*bag_parts(deserialize(latest["raw"])))  # type: ignore[arg-type]
                if message.n_submaps >= n_sent or (message.stats and message.stats["n_joined"] + message.stats["n_rejected"] >= n_sent):
                    break
            if joiner.poll() is not None:
                raise RuntimeError(f"joiner exited with code {joiner.returncode}")
        if message is None:
            raise RuntimeError(f"no global_map received within {timeout_s:.0f} s")
        seconds = float(latest["t"]) - t0  # type: ignore[arg-type]
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        code = stop(joiner)
    maps = read_dataset(dataset).maps
    origin = maps[0].frame_id
    in_first = write_result(out, message.local_map, origin)
    stats = message.stats or {}
    report = {
        "dataset": dataset.name.removesuffix(".tar.xz"),
        "mode": mode,
        "n_submaps_sent": n_sent,
        "n_submaps_joined": message.n_submaps,
        "n_submaps_rejected": int(stats.get("n_rejected", 0)),
        "chi2": chi2(message.local_map, maps),
        "seconds": seconds,
        "per_submap_ms_p50": stats.get("join_ms_p50"),
        "per_submap_ms_p99": stats.get("join_ms_p99"),
        "per_submap_ms_max": stats.get("join_ms_max"),
        "join_seconds_total": stats.get("join_seconds_total"),
        "state_dim": message.local_map.state_dim,
        "joiner_exit_code": code,
    }
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    plot_map(in_first, out / "map.png", f"{report['dataset']}: {message.n_submaps} submaps joined ({mode}), χ² {report['chi2']:.1f}")
    write_messages(out / "global_map_bag", [("global_map", 0, latest["raw"])], latched={"global_map"}, overwrite=True)  # type: ignore[list-item]
    return report


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(prog="demo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--bag", type=Path, default=Path("bags/vicpark200"))
    ap.add_argument("--out", type=Path, default=Path("out"))
    ap.add_argument("--mode", choices=["sequential", "online-dc"], default="sequential")
    ap.add_argument("--rate-factor", type=float, default=0.0, help="bag-time speed-up; 0 plays as fast as possible")
    args = ap.parse_args(argv)
    report = run_demo(args.dataset, args.bag, args.out, args.mode, args.rate_factor)
    print(json.dumps(report, indent=2))
    ok = report["n_submaps_joined"] == report["n_submaps_sent"] and report["joiner_exit_code"] == 0
    return 0 if ok else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
