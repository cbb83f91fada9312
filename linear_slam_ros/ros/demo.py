"""The main job: replay a dataset's bag through a running ``joiner`` and write what it produced.

``demo [--dataset ARCHIVE] [--bag bags/vicpark200] [--out out] [--mode MODE]``
``demo --sim [--n-maps 200] [--sim-rate 20.0] [--out out/sim]`` (``make run-sim``)

Starts the joiner as its own process (the colcon-installed ``lib/linear_slam_ros/joiner`` when
ament can find it), plays the bag into it over DDS on loopback, waits for the latched
``global_map`` that has joined every submap, and writes ``OUT/poses.txt``, ``features.txt``
(first pose's frame), ``report.json``, ``map.png`` and ``global_map_bag``. Without ``--mode`` the
joiner runs its default mode. The report's freshness figures and the joiner's peak memory come
from the joiner's ``/diagnostics`` after the final map.

With ``--sim`` the bag is replaced by the live front-end example: ``sim_frontend`` (the installed
executable, as ``ros2 run`` starts it) publishes ``--n-maps`` local maps of its seeded park world
at ``--sim-rate`` maps a second into the joiner, and the same files are written; χ² is computed
against the same maps, rebuilt from the seed (:class:`~linear_slam_ros.ros.sim_frontend.Simulation`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from std_msgs.msg import Float64MultiArray

from linear_slam_ros.core.errors import ConfigError, LinearSlamError
from linear_slam_ros.core.limits import OUTPUT_LIMITS
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.plots import plot_map
from linear_slam_ros.io.results import write_result
from linear_slam_ros.joiner.config import JoinerConfig
from linear_slam_ros.joiner.registry import methods
from linear_slam_ros.joiner.strategy import MapType
from linear_slam_ros.joining.islands import maps_within
from linear_slam_ros.ros.bag_from_dataset import load_source, make_bag
from linear_slam_ros.ros.bagio import read_messages, write_messages
from linear_slam_ros.ros.player import play
from linear_slam_ros.ros.process import loopback_env, share_directory, stop_process
from linear_slam_ros.ros.qos import latched_qos
from linear_slam_ros.ros.sim_frontend import Simulation
from linear_slam_ros.ros.spin import LatestMessage, node_session, spin_until, wait_for_diagnostics
from msg_adapters import MapMessage, MapSummary, decode_map, decode_map_summary
from msg_adapters.bags import bag_parts, deserialize

DEFAULT_DATASET = Path("bags/vicpark200")
"""The committed bag of VicPark_200 (``bags/README.md``): a dataset source like its archive, with the same maps."""


def default_bag() -> Path:
    """Return the bag ``demo`` replays by default: :data:`DEFAULT_DATASET` in the current folder (a
    checkout), else the copy installed in the package's share folder (``ros2 run linear_slam_ros demo``
    from anywhere), else :data:`DEFAULT_DATASET` (which then fails naming it)."""
    share = share_directory()
    if DEFAULT_DATASET.exists() or share is None or not (share / DEFAULT_DATASET / "metadata.yaml").is_file():
        return DEFAULT_DATASET
    return share / DEFAULT_DATASET


def joiner_command(executable: str = "joiner", module: str = "linear_slam_ros.ros.node") -> list[str]:
    """Return the command that starts an executable of the package (the joiner), installed, as ``ros2 run`` would."""
    try:
        from ament_index_python.packages import get_package_prefix

        exe = Path(get_package_prefix("linear_slam_ros")) / "lib" / "linear_slam_ros" / executable
        if exe.exists():
            return [str(exe)]
    except Exception:  # not installed with colcon: run the module with this interpreter
        pass
    return [sys.executable, "-m", module]


def start_joiner(params: dict[str, object], env: dict[str, str]) -> subprocess.Popen[bytes]:
    """Start the joiner process with ``-p name:=value`` parameters."""
    cmd = joiner_command() + ["--ros-args"]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={v}"]
    return subprocess.Popen(cmd, env=env)


def decode_global_map(raw: bytes) -> MapMessage:
    """Return the decoded ``global_map`` message of its CDR bytes (the node's output: :data:`OUTPUT_LIMITS`)."""
    return decode_map(*bag_parts(deserialize(raw)), limits=OUTPUT_LIMITS)


def decode_global_summary(raw: bytes) -> MapSummary:
    """Return the header and ``stats`` of a ``global_map`` message's CDR bytes, without its map.

    What a waiting reader looks at in every message: decoding each of a city-sized stream's
    global maps would take a core from the joiner on the same machine.
    """
    return decode_map_summary(*bag_parts(deserialize(raw)))


def decode_refined_map(raw: bytes) -> tuple[MapMessage, dict[str, float]]:
    """Return a decoded ``global_map_refined`` message and its ``refine`` segment by field (empty when absent)."""
    from linear_slam_ros.ros.refine_sink import REFINE_FIELDS

    labels, sizes, data, offset = bag_parts(deserialize(raw))
    segment: dict[str, float] = {}
    if "refine" in labels:
        start = sum(int(s) for s in sizes[: labels.index("refine")])
        segment = dict(zip(REFINE_FIELDS, (float(v) for v in data[start : start + int(sizes[labels.index("refine")])]),
                           strict=False))
    return decode_map(labels, sizes, data, offset, limits=OUTPUT_LIMITS), segment


REFINED_WITHIN = 1e-3
"""``refined_within_lag_s``: the first refined map covering every submap with χ² within this fraction of the final one."""

FRESHNESS_KEYS = tuple(f"freshness_{what}_ms_{q}" for what in ("pose", "map") for q in ("p50", "p99", "max"))


def run_demo(
    dataset: Path, bag: Path, out: Path, mode: str | None = None, rate_factor: float = 0.0, timeout_s: float = 300.0,
    params: dict[str, object] | None = None, refine: bool = False,
) -> dict[str, object]:
    """Replay ``bag`` through a joiner process; write and return the report.

    Args:
        mode: the joiner's ``mode`` (``None``: its default).
        params: more joiner parameters (``timing_file``...).
        refine: run the joiner with ``refine`` on, wait for the converged ``global_map_refined`` that
            covers every submap, and add ``chi2_refined`` and ``refined_lag_s`` to the report (and
            ``refined_within_lag_s``: to the first one within 0.1% of its χ²). The stream starts
            once the refiner process is up (its latched empty ``global_map_refined``), as it would be
            on a robot: the process's start-up is not counted in the lag.
    """
    if not (bag / "metadata.yaml").exists():
        make_bag(dataset, bag)
    records = list(read_messages(bag))
    n_sent = len(records)
    os.environ.update(loopback_env())  # this process's DDS too
    joiner_params: dict[str, object] = {"output_frame": "end_pose", "publish_rate": 20.0, "summary_period": 0.5}
    if mode is not None:
        joiner_params["mode"] = mode
    if refine:
        joiner_params["refine"] = "true"
    refined: tuple[MapMessage, dict[str, float]] | None = None
    refined_raw: list[bytes] = []  # every global_map_refined, in order
    refined_log: list[tuple[MapMessage, dict[str, float]]] = []
    joiner = start_joiner({**joiner_params, **(params or {})}, dict(os.environ))
    mode = mode or JoinerConfig().mode.value

    # with the χ² gate on, a submap the gate split something off counts as joined and under n_rejected
    # ("gated"), as does a held closure gated later: only every submap joined ends the wait then
    gate = float((params or {}).get("gate_probability", 0.0) or 0.0) > 0.0  # type: ignore[arg-type]

    def all_handled(m: MapSummary) -> bool:
        counted = bool(m.stats and m.stats["n_joined"] + m.stats["n_rejected"] >= n_sent)
        return m.n_submaps >= n_sent or (counted and not gate)

    try:
        with node_session("demo") as node, LatestMessage(node, "global_map", decode_global_summary) as latest:
            if refine:  # every refined map (decoded at the end); as on a robot, the refiner process is up
                # before the stream starts: its latched empty map says so
                def keep(raw: bytes) -> None:
                    refined_raw.append(bytes(raw))

                node.create_subscription(Float64MultiArray, "global_map_refined", keep, latched_qos(), raw=True)
                if not spin_until(node, lambda: bool(refined_raw) or joiner.poll() is not None, 60.0) or not refined_raw:
                    raise RuntimeError("the joiner's refiner published no global_map_refined within 60 s")
            started: list[float] = []
            cpu_before_play = time.process_time()
            play(node, records, rate_factor=rate_factor, wait_s=60.0, on_start=lambda: started.append(time.monotonic()))
            replay_cpu_s = time.process_time() - cpu_before_play  # this process's load on the joiner's machine
            t0 = started[0]
            try:
                latest.wait(all_handled, timeout_s, joiner)
            except ChildProcessError:
                raise RuntimeError(f"joiner exited with code {joiner.returncode}") from None
            raw = latest.raw
            if raw is None:
                raise RuntimeError(f"no global_map received within {timeout_s:.0f} s")
            message = decode_global_map(raw)
            seconds = latest.received_at - t0
            n_joined = message.n_submaps
            diagnostics = wait_for_diagnostics(node, lambda v: v.get("n_fresh_map", -1) >= n_joined, 10.0) or {}
            if refine:
                seen = [0]

                def refined_done() -> bool:
                    if len(refined_raw) == seen[0]:
                        return joiner.poll() is not None
                    seen[0] = len(refined_raw)
                    m, segment = decode_refined_map(refined_raw[-1])
                    return m.n_submaps >= n_joined and segment.get("converged") == 1.0

                spin_until(node, refined_done, timeout_s)
                refined_log = [decode_refined_map(r) for r in refined_raw]
                final = [r for r in refined_log if r[0].n_submaps >= n_joined and r[1].get("converged") == 1.0]
                refined = final[-1] if final else None
    finally:
        code = stop_process(joiner)
    # the maps for χ²: the dataset's, or the bag's own when the dataset is not there (the same maps)
    source = load_source(dataset if dataset.exists() or str(dataset).startswith("synthetic:") else bag)
    report = write_outputs(
        out, message, raw, source.maps, source.name, mode, n_sent, seconds, diagnostics, code, {"replay_cpu_s": replay_cpu_s},
    )
    if refine:
        if refined is None or refined[0].n_submaps < message.n_submaps:
            raise RuntimeError(f"no converged global_map_refined covering {message.n_submaps} submaps within {timeout_s:.0f} s")
        best = refined[1]["chi2"] * (1 + REFINED_WITHIN)
        within = next(
            r[1] for r in refined_log if r[0].n_submaps >= message.n_submaps and r[1].get("chi2", math.inf) <= best
        )
        report.update({
            "chi2_refined": chi2(refined[0].local_map, source.maps), "refined_lag_s": refined[1].get("lag_s"),
            "refined_within_lag_s": within.get("lag_s"),
            "refined_iterations": refined[1].get("iterations"), "refiner_cpu_s": refined[1].get("cpu_s"),
        })
        (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


def write_outputs(
    out: Path, message: MapMessage, raw: bytes, maps: Sequence[LocalMap], name: str, mode: str, n_sent: int,
    seconds: float, diagnostics: dict[str, float], exit_code: int, extra: dict[str, object] | None = None,
) -> dict[str, object]:
    """Write ``poses.txt``, ``features.txt``, ``report.json``, ``map.png`` and ``global_map_bag`` of a final global map.

    Args:
        message: the decoded final ``global_map``; ``raw``: its CDR bytes.
        maps: the submaps sent (for χ²); ``name``: what they are (the report's ``dataset``).
        seconds: from the first message sent to the final map received.
        diagnostics: the joiner's ``/diagnostics`` values after it.
        exit_code: the joiner's.
        extra: more keys of ``report.json`` (``replay_cpu_s``: the replaying process's CPU while it sent).
    """
    in_first = write_result(out, message.local_map, maps[0].frame_id)
    stats = message.stats or {}
    report: dict[str, object] = {
        "dataset": name,
        "mode": mode,
        "n_submaps_sent": n_sent,
        "n_submaps_joined": message.n_submaps,
        "n_submaps_rejected": int(stats.get("n_rejected", 0)),
        "chi2": chi2(message.local_map, maps if not message.islands or len(message.islands) == 1
                     else maps_within(message.local_map, maps)),  # the main island's own submaps
        "seconds": seconds,
        "per_submap_ms_p50": stats.get("join_ms_p50"),
        "per_submap_ms_p99": stats.get("join_ms_p99"),
        "per_submap_ms_max": stats.get("join_ms_max"),
        "join_seconds_total": stats.get("join_seconds_total"),
        **{key: diagnostics.get(key) for key in FRESHNESS_KEYS},
        "submaps_per_second": message.n_submaps / seconds if seconds > 0 else None,
        "joiner_peak_rss_mb": diagnostics.get("peak_rss_mb"),
        "joiner_cpu_s": diagnostics.get("cpu_seconds"),
        "state_dim": message.local_map.state_dim,
        "n_islands": len(message.islands) if message.islands else 1,
        "island_sizes": sorted(message.islands or (message.n_submaps,), reverse=True),
        "joiner_exit_code": exit_code,
        **(extra or {}),
    }
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    title = f"{report['dataset']}: {message.n_submaps} submaps joined ({mode}), χ² {report['chi2']:.1f}"
    plot_map(in_first, out / "map.png", title)
    write_messages(out / "global_map_bag", [("global_map", 0, raw)], latched={"global_map"}, overwrite=True)
    return report


def run_sim_demo(
    out: Path, n_maps: int = 200, rate: float = 20.0, world: str = "park", seed: int = 0, mode: str | None = None,
    timeout_s: float = 300.0,
) -> dict[str, object]:
    """Run the live front-end example (``sim_frontend``) into a joiner process; write and return the report.

    Args:
        n_maps: local maps the front-end publishes; ``rate``: maps a second (Hz).
        world, seed: the simulated world (``sim_frontend``'s parameters).
        mode: the joiner's ``mode`` (``None``: its default).

    Raises:
        ConfigError: ``n_maps`` below 1 or ``rate`` not positive.
        RuntimeError: a process failed, or no final map came within ``timeout_s``.
    """
    if n_maps < 1 or not rate > 0:
        raise ConfigError(f"--n-maps {n_maps} must be at least 1 and --sim-rate {rate} positive")
    os.environ.update(loopback_env())
    joiner_params: dict[str, object] = {"output_frame": "end_pose", "publish_rate": 20.0, "summary_period": 0.5}
    if mode is not None:
        joiner_params["mode"] = mode
    joiner = start_joiner(joiner_params, dict(os.environ))
    mode = mode or JoinerConfig().mode.value
    sim_cmd = joiner_command("sim_frontend", "linear_slam_ros.ros.sim_frontend") + [
        "--ros-args", "-p", f"world:={world}", "-p", f"seed:={seed}", "-p", f"n_maps:={n_maps}", "-p", f"rate:={float(rate)}",
    ]
    frontend: subprocess.Popen[bytes] | None = None
    try:
        with node_session("demo") as node, LatestMessage(node, "global_map", decode_global_summary) as latest:
            t0 = time.monotonic()
            frontend = subprocess.Popen(sim_cmd, env=dict(os.environ))
            try:
                latest.wait(lambda m: m.n_submaps >= n_maps, timeout_s, joiner)
            except ChildProcessError:
                raise RuntimeError(f"joiner exited with code {joiner.returncode}") from None
            summary, raw = latest.value, latest.raw
            if summary is None or raw is None or summary.n_submaps < n_maps:
                raise RuntimeError(f"no global_map of {n_maps} submaps within {timeout_s:.0f} s")
            message = decode_global_map(raw)
            seconds = latest.received_at - t0
            diagnostics = wait_for_diagnostics(node, lambda v: v.get("n_fresh_map", -1) >= message.n_submaps, 10.0) or {}
    finally:
        if frontend is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):  # it exits by itself once every map is acknowledged
                frontend.wait(30.0)
        sim_code = stop_process(frontend) if frontend is not None else None
        code = stop_process(joiner)
    if sim_code not in (0, None):
        raise RuntimeError(f"sim_frontend exited with code {sim_code}")
    simulation = Simulation(world, seed)
    maps = [simulation.next_local_map() for _ in range(n_maps)]
    return write_outputs(out, message, raw, maps, f"sim_frontend:{world}@{seed}", mode, n_maps, seconds, diagnostics, code)


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(prog="demo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", type=Path, default=None,
                    help="the bag to replay (default: bags/vicpark200 here, else the copy installed with the package)")
    ap.add_argument(
        "--dataset", type=Path, default=None,
        help="the dataset the bag was made from: made into --bag when the bag is missing, and the maps the χ² is "
             "scored against (default: the bag's own)",
    )
    ap.add_argument("--out", type=Path, default=Path("out"))
    ap.add_argument(
        "--mode", choices=[m.value for m in methods(MapType.AS_IS, online_only=True)], default=None,
        help=f"joining mode (default: the joiner's, {JoinerConfig().mode.value})",
    )
    ap.add_argument("--rate-factor", type=float, default=0.0, help="bag-time speed-up; 0 plays as fast as possible")
    ap.add_argument("--refine", action="store_true",
                    help="joiner with refine on; report.json gains chi2_refined and refined_lag_s")
    ap.add_argument("--sim", action="store_true", help="run the live front-end example sim_frontend instead of the bag")
    ap.add_argument("--n-maps", type=int, default=200, help="--sim: local maps sim_frontend publishes")
    ap.add_argument("--sim-rate", type=float, default=20.0, help="--sim: local maps a second, Hz")
    args = ap.parse_args(argv)
    try:
        if args.sim:
            report = run_sim_demo(args.out, args.n_maps, args.sim_rate, mode=args.mode)
        else:
            bag = args.bag if args.bag is not None else default_bag()
            dataset = args.dataset if args.dataset is not None else bag  # --bag OTHER was scored against VicPark200
            report = run_demo(dataset, bag, args.out, args.mode, args.rate_factor, refine=args.refine)
    except LinearSlamError as exc:  # a missing or unreadable bag or dataset, a bad option
        print(f"demo: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(report, indent=2))
    ok = report["n_submaps_joined"] == report["n_submaps_sent"] and report["joiner_exit_code"] == 0
    return 0 if ok else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
