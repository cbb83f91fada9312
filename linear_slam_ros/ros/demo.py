"""The main job: replay a dataset's bag through a running ``joiner`` and write what it produced.

``demo [--dataset ARCHIVE] [--bag bags/vicpark200] [--out out] [--mode MODE]``

Starts the joiner as its own process (the colcon-installed ``lib/linear_slam_ros/joiner`` when
ament can find it), plays the bag into it over DDS on loopback, waits for the latched
``global_map`` that has joined every submap, and writes ``OUT/poses.txt``, ``features.txt``
(first pose's frame), ``report.json``, ``map.png`` and ``global_map_bag``. Without ``--mode`` the
joiner runs its default mode. The report's freshness figures and the joiner's peak memory come
from the joiner's ``/diagnostics`` after the final map.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.plots import plot_map
from linear_slam_ros.io.results import write_result
from linear_slam_ros.joiner.config import JoinerConfig
from linear_slam_ros.joiner.registry import methods
from linear_slam_ros.joiner.strategy import MapType
from linear_slam_ros.ros.bag_from_dataset import load_source, make_bag
from linear_slam_ros.ros.bagio import read_messages, write_messages
from linear_slam_ros.ros.player import play
from linear_slam_ros.ros.process import loopback_env, stop_process
from linear_slam_ros.ros.spin import LatestMessage, node_session, wait_for_diagnostics
from msg_adapters import MapMessage, decode_map
from msg_adapters.bags import bag_parts, deserialize

DEFAULT_DATASET = Path("bags/vicpark200")
"""The committed bag of VicPark_200 (``bags/README.md``): a dataset source like its archive, with the same maps."""


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


def decode_global_map(raw: bytes) -> MapMessage:
    """Return the decoded ``global_map`` message of its CDR bytes."""
    return decode_map(*bag_parts(deserialize(raw)))


FRESHNESS_KEYS = tuple(f"freshness_{what}_ms_{q}" for what in ("pose", "map") for q in ("p50", "p99", "max"))


def run_demo(
    dataset: Path, bag: Path, out: Path, mode: str | None = None, rate_factor: float = 0.0, timeout_s: float = 300.0,
    params: dict[str, object] | None = None,
) -> dict[str, object]:
    """Replay ``bag`` through a joiner process; write and return the report.

    Args:
        mode: the joiner's ``mode`` (``None``: its default).
        params: more joiner parameters (``timing_file``...).
    """
    if not (bag / "metadata.yaml").exists():
        make_bag(dataset, bag)
    records = list(read_messages(bag))
    n_sent = len(records)
    os.environ.update(loopback_env())  # this process's DDS too
    joiner_params: dict[str, object] = {"output_frame": "end_pose", "publish_rate": 20.0, "summary_period": 0.5}
    if mode is not None:
        joiner_params["mode"] = mode
    joiner = start_joiner({**joiner_params, **(params or {})}, dict(os.environ))
    mode = mode or JoinerConfig().mode.value

    def all_handled(m: MapMessage) -> bool:
        return m.n_submaps >= n_sent or bool(m.stats and m.stats["n_joined"] + m.stats["n_rejected"] >= n_sent)

    try:
        with node_session("demo") as node, LatestMessage(node, "global_map", decode_global_map) as latest:
            started: list[float] = []
            play(node, records, rate_factor=rate_factor, wait_s=60.0, on_start=lambda: started.append(time.monotonic()))
            t0 = started[0]
            try:
                latest.wait(all_handled, timeout_s, joiner)
            except ChildProcessError:
                raise RuntimeError(f"joiner exited with code {joiner.returncode}") from None
            message, raw = latest.value, latest.raw
            if message is None or raw is None:
                raise RuntimeError(f"no global_map received within {timeout_s:.0f} s")
            seconds = latest.received_at - t0
            n_joined = message.n_submaps
            diagnostics = wait_for_diagnostics(node, lambda v: v.get("n_fresh_map", -1) >= n_joined, 10.0) or {}
    finally:
        code = stop_process(joiner)
    # the maps for χ²: the dataset's, or the bag's own when the dataset is not there (the same maps)
    source = load_source(dataset if dataset.exists() or str(dataset).startswith("synthetic:") else bag)
    maps = source.maps
    origin = maps[0].frame_id
    in_first = write_result(out, message.local_map, origin)
    stats = message.stats or {}
    report: dict[str, object] = {
        "dataset": source.name,
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
        **{key: diagnostics.get(key) for key in FRESHNESS_KEYS},
        "submaps_per_second": message.n_submaps / seconds if seconds > 0 else None,
        "joiner_peak_rss_mb": diagnostics.get("peak_rss_mb"),
        "state_dim": message.local_map.state_dim,
        "joiner_exit_code": code,
    }
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    title = f"{report['dataset']}: {message.n_submaps} submaps joined ({mode}), χ² {report['chi2']:.1f}"
    plot_map(in_first, out / "map.png", title)
    write_messages(out / "global_map_bag", [("global_map", 0, raw)], latched={"global_map"}, overwrite=True)
    return report


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(prog="demo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--bag", type=Path, default=Path("bags/vicpark200"))
    ap.add_argument("--out", type=Path, default=Path("out"))
    ap.add_argument(
        "--mode", choices=[m.value for m in methods(MapType.AS_IS, online_only=True)], default=None,
        help=f"joining mode (default: the joiner's, {JoinerConfig().mode.value})",
    )
    ap.add_argument("--rate-factor", type=float, default=0.0, help="bag-time speed-up; 0 plays as fast as possible")
    args = ap.parse_args(argv)
    report = run_demo(args.dataset, args.bag, args.out, args.mode, args.rate_factor)
    print(json.dumps(report, indent=2))
    ok = report["n_submaps_joined"] == report["n_submaps_sent"] and report["joiner_exit_code"] == 0
    return 0 if ok else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
