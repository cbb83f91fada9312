"""Benchmark of the joiner node's persistence: journal and snapshot cost against join time, and restore time.

``bench_persistence [--datasets-dir ../shared/datasets] [--out out/benchmark] [--repeat 2]``

For each dataset (default VicPark_6898_local_maps and manhattanOlson3500; one that is missing
from ``--datasets-dir`` is skipped with the reason printed), ``--repeat`` times, with the
installed ``joiner`` started as its own process (as ``demo`` does) in mode ``online-dc`` (the
default ``sequential`` mode is exact but O(n^2) per submap: it does not finish these streams):

1. **baseline**: a joiner without ``state_dir``; the dataset's bag (``bags/<dataset>``, made
   when missing) is replayed at full speed; the latched ``global_map`` that has joined every
   submap gives ``join_seconds_total``; end to end = first message published to that map
   received (the joiner is up and discovered before the clock starts).
2. **persisted**: the same with a fresh ``state_dir`` (default ``snapshot_period``); the last
   ``/diagnostics`` message of the joiner gives ``journal_seconds_total`` and
   ``snapshot_seconds_total``; then the joiner is stopped with Ctrl-C (it writes a final
   snapshot) and the stop is timed.
3. **restore**: a joiner started again on that ``state_dir``: its ``restore_seconds_total``
   (``/diagnostics``), its ``resumed from ... in X s`` log line, the time from process start to
   the restored ``global_map``; then it is stopped (timed too).

Targets: journal + snapshots <= 10 % of the join time (per dataset), restore of VicPark6898 <= 2 s.
What journal + snapshots cost the joins (``cost_ratio``, the target's figure): the journal's
wall time, which is spent on the joining thread before each join, plus the snapshots' thread CPU
time (they run on the node's output thread; while they wait for fsync or for the interpreter lock
they take nothing from the joins), over the join seconds. Reported beside it: the same in wall
time only (``ratio``: the snapshots' fsync waits counted too), in thread CPU time only
(``cpu_ratio``), and the joining thread's seconds with persistence over without (``ab_ratio``,
runs side by side; this VM's run-to-run noise is as large as the effect).
Writes ``OUT/persistence.json``, ``OUT/persistence.md`` (printed too) and the joiners' output to
``OUT/persistence_logs/``. Runs in this process's ``ROS_DOMAIN_ID`` (``--domain-id`` to choose),
DDS on loopback only.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node

from linear_slam_ros.ros.bag_from_dataset import make_bag
from linear_slam_ros.ros.bagio import BagRecord, read_messages
from linear_slam_ros.ros.demo import decode_global_summary, joiner_command
from linear_slam_ros.ros.player import play
from linear_slam_ros.ros.process import loopback_env, stop_process
from linear_slam_ros.ros.spin import LatestMessage, diagnostic_values, node_session, spin_until
from msg_adapters import MapSummary

DATASETS = ("VicPark_6898_local_maps", "manhattanOlson3500")
MODE = "online-dc"
MODE_NOTE = "mode online-dc (the node's default)"
SUMMARY_PERIOD_S = 0.5
"""The joiners' ``summary_period``: a ``/diagnostics`` message soon after the last submap."""
TARGET_RATIO = 0.10
"""Journal + snapshot seconds over join seconds, at most."""
TARGET_RESTORE_S = {"VicPark_6898_local_maps": 2.0}
"""Restore seconds, at most, per dataset."""
STOP_TIMEOUT_S = 300.0
"""Ctrl-C, then kill after this long (the final snapshot of a large map takes a while)."""
RESUMED = re.compile(r"resumed from (?P<snapshot>.+?) and (?P<records>\d+) journal record\(s\) in (?P<seconds>[0-9.]+) s")


class Diagnostics:
    """The newest ``/diagnostics`` status of one node (status name ``"<node name>: joining"``), as numbers."""

    def __init__(self, node: Node, node_name: str) -> None:
        self.node = node
        self.status_name = f"{node_name}: joining"
        self.values: dict[str, float] = {}
        self.previous: dict[str, float] = {}
        self.count = 0
        self.received_at = 0.0
        self._sub = node.create_subscription(DiagnosticArray, "/diagnostics", self._on_message, 50)

    def _on_message(self, msg: Any) -> None:
        for status in msg.status:
            if status.name != self.status_name:
                continue
            self.previous, self.values = self.values, diagnostic_values(status)
            self.count += 1
            self.received_at = time.monotonic()

    def handled(self) -> int:
        """Submaps joined or rejected, by the newest status (0 before the first)."""
        return int(self.values.get("n_joined", 0) + self.values.get("n_rejected", 0))

    def wait(self, done: Callable[[], bool], timeout_s: float, process: subprocess.Popen[Any]) -> None:
        """Spin until ``done()``; raise if the process exits or ``timeout_s`` passes first."""

        def check() -> bool:
            if done():
                return True
            if process.poll() is not None:
                raise RuntimeError(f"joiner exited with code {process.returncode} (its output: see the log)")
            return False

        if not spin_until(self.node, check, timeout_s):
            raise TimeoutError(f"{self.status_name}: condition not met within {timeout_s:.0f} s (last status {self.values})")

    def wait_settled(self, keys: Sequence[str], timeout_s: float, process: subprocess.Popen[Any]) -> dict[str, float]:
        """Wait for two more statuses in which ``keys`` no longer change; return the last."""
        start = self.count

        def settled() -> bool:
            return self.count >= start + 2 and all(self.values.get(k) == self.previous.get(k) for k in keys)

        self.wait(settled, timeout_s, process)
        return dict(self.values)

    def close(self) -> None:
        """Destroy the subscription."""
        self.node.destroy_subscription(self._sub)

    def __enter__(self) -> Diagnostics:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class JoinerRun:
    """A joiner process of the benchmark (its output to a log file) and when it was started."""

    params: dict[str, object]
    log: Path
    namespace: str
    node_name: str
    process: subprocess.Popen[bytes] = field(init=False)
    started_at: float = field(init=False)

    def __post_init__(self) -> None:
        # demo.start_joiner's command, plus remaps that keep this run apart and the output kept in a file.
        cmd = joiner_command() + ["--ros-args", "-r", f"__ns:=/{self.namespace}", "-r", f"__node:={self.node_name}"]
        for k, v in self.params.items():
            cmd += ["-p", f"{k}:={v}"]
        self.log.parent.mkdir(parents=True, exist_ok=True)
        with self.log.open("wb") as out:
            self.started_at = time.monotonic()
            self.process = subprocess.Popen(cmd, env=dict(os.environ), stdout=out, stderr=subprocess.STDOUT)

    def topic(self, name: str) -> str:
        """Return the full name of one of this joiner's topics."""
        return f"/{self.namespace}/{name.lstrip('/')}"  # a bag's names are fully qualified

    def global_map(self, node: Node) -> LatestMessage[MapSummary]:
        """Return a subscription to this joiner's latched ``global_map`` (header and stats only)."""
        return LatestMessage(node, self.topic("global_map"), decode_global_summary)

    def stop(self) -> tuple[int, float]:
        """Stop as Ctrl-C does; return the exit code and the seconds the stop took."""
        t0 = time.monotonic()
        code = stop_process(self.process, STOP_TIMEOUT_S)
        return code, time.monotonic() - t0

    def output(self) -> str:
        """Return what the process wrote (stdout and stderr) so far."""
        return self.log.read_text(errors="replace") if self.log.exists() else ""


def dataset_bag(archive: Path, bags_dir: Path) -> Path:
    """Return ``bags_dir/<dataset>``, made from the archive (10 Hz stamps) when it is not there yet."""
    bag = bags_dir / archive.name.removesuffix(".tar.xz")
    if not (bag / "metadata.yaml").exists():
        print(f"making bag {bag} from {archive} ...", flush=True)
        make_bag(archive, bag, rate_hz=10.0)
    return bag


def folder_bytes(folder: Path) -> int:
    """Total size of the files below ``folder``."""
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def replay(
    node: Node, records: Sequence[BagRecord], params: dict[str, object], log: Path, tag: str, timeout_s: float
) -> dict[str, Any]:
    """Start a joiner, replay ``records`` into it at full speed, wait until every submap is handled, stop it."""
    n_sent = len(records)
    joiner = JoinerRun(params, log, f"bench_persistence_{os.getpid()}_{tag}", f"joiner_{tag}")
    try:
        with Diagnostics(node, joiner.node_name) as diag, joiner.global_map(node) as latest:
            diag.wait(lambda: diag.count > 0, 120.0, joiner.process)  # the joiner is up and this node sees it
            ready_s = diag.received_at - joiner.started_at
            t0 = time.monotonic()
            publish_s = play(node, [r._replace(topic=joiner.topic(r.topic)) for r in records], rate_factor=0.0, wait_s=60.0)
            # Gate on the cheap diagnostics first: a global map received is only decoded once looked at.
            diag.wait(lambda: diag.handled() >= n_sent, timeout_s, joiner.process)

            def all_handled(m: MapSummary) -> bool:
                return bool(m.n_submaps >= n_sent or (m.stats and m.stats["n_joined"] + m.stats["n_rejected"] >= n_sent))

            try:
                ok = latest.wait(all_handled, timeout_s, joiner.process)
            except ChildProcessError as exc:
                raise RuntimeError(f"{exc} (its output: {log})") from None
            message = latest.value
            if not ok or message is None:
                raise TimeoutError(f"no global_map with all {n_sent} submaps within {timeout_s:.0f} s")
            end_to_end_s = latest.received_at - t0
            values = diag.wait_settled(["journal_seconds_total", "snapshot_seconds_total", "n_joined"], 60.0, joiner.process)
            # (the CPU figures settle with the wall ones: they are counted around the same calls)
        code, stop_s = joiner.stop()
    except BaseException:
        stop_process(joiner.process, STOP_TIMEOUT_S)
        raise
    stats = message.stats or {}
    return {
        "n_sent": n_sent,
        "n_joined": message.n_submaps,
        "n_rejected": int(stats.get("n_rejected", 0)),
        "join_seconds_total": stats.get("join_seconds_total"),
        "join_ms_p99": stats.get("join_ms_p99"),
        "join_ms_max": stats.get("join_ms_max"),
        "journal_seconds_total": values.get("journal_seconds_total"),
        "snapshot_seconds_total": values.get("snapshot_seconds_total"),
        "restore_seconds_total": values.get("restore_seconds_total"),
        "journal_cpu_seconds_total": values.get("journal_cpu_seconds_total"),
        "snapshot_cpu_seconds_total": values.get("snapshot_cpu_seconds_total"),
        "join_cpu_seconds_total": values.get("join_cpu_seconds_total"),
        "startup_s": ready_s,
        "publish_s": publish_s,
        "end_to_end_s": end_to_end_s,
        "stop_s": stop_s,
        "exit_code": code,
    }


def restore(node: Node, n_sent: int, params: dict[str, object], log: Path, tag: str, timeout_s: float) -> dict[str, Any]:
    """Start a joiner on a ``state_dir`` that holds a state; measure its restore; stop it."""
    joiner = JoinerRun(params, log, f"bench_persistence_{os.getpid()}_{tag}", f"joiner_{tag}")
    try:
        with Diagnostics(node, joiner.node_name) as diag, joiner.global_map(node) as latest:
            diag.wait(lambda: diag.count > 0, timeout_s, joiner.process)
            first_status_s = diag.received_at - joiner.started_at
            try:
                ok = latest.wait(lambda m: m.n_submaps >= n_sent, timeout_s, joiner.process)
            except ChildProcessError as exc:
                raise RuntimeError(f"{exc} (its output: {log})") from None
            message = latest.value
            if not ok or message is None:
                raise TimeoutError(f"restored joiner published no global_map with {n_sent} submaps within {timeout_s:.0f} s")
            map_s = latest.received_at - joiner.started_at
            values = dict(diag.values)
        code, stop_s = joiner.stop()
    except BaseException:
        stop_process(joiner.process, STOP_TIMEOUT_S)
        raise
    m = RESUMED.search(joiner.output())
    return {
        "n_joined": message.n_submaps,
        "restore_seconds_total": values.get("restore_seconds_total"),
        "resumed_log_s": float(m["seconds"]) if m else None,
        "resumed_from": Path(m["snapshot"]).name if m else None,
        "journal_records_replayed": int(m["records"]) if m else None,
        "startup_snapshot_s": values.get("snapshot_seconds_total"),
        "first_status_s": first_status_s,
        "start_to_map_s": map_s,
        "stop_s": stop_s,
        "exit_code": code,
    }


def run_figures(rep: int, baseline: dict[str, Any], persisted: dict[str, Any], restored: dict[str, Any]) -> dict[str, Any]:
    """Return one repetition's figures from its three phases (see the module docstring for each ratio)."""
    persist_s = persisted["journal_seconds_total"] + persisted["snapshot_seconds_total"]
    cost_s = persisted["journal_seconds_total"] + persisted["snapshot_cpu_seconds_total"]
    return {
        "repetition": rep,
        "baseline": baseline,
        "persisted": persisted,
        "restore": restored,
        "persistence_seconds": persist_s,
        "ratio": persist_s / persisted["join_seconds_total"],
        "cost_seconds": cost_s,
        "cost_ratio": cost_s / persisted["join_seconds_total"],
        # What the joining thread spent per stream, with persistence over without (runs side by side):
        # the journal writes in full, and whatever the snapshots (another thread) took from the joins.
        "ab_ratio": (persisted["join_seconds_total"] + persisted["journal_seconds_total"]) / baseline["join_seconds_total"],
        "cpu_ratio": (persisted["journal_cpu_seconds_total"] + persisted["snapshot_cpu_seconds_total"])
        / persisted["join_cpu_seconds_total"],
        # The final snapshot at Ctrl-C, estimated as the extra time the stop took.
        "final_snapshot_s_est": persisted["stop_s"] - baseline["stop_s"],
    }


def dataset_figures(name: str, n_submaps: int, runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Return a dataset's figures from its repetitions (:func:`run_figures`), with the targets' verdicts."""
    restore_target = TARGET_RESTORE_S.get(name)
    return {
        "dataset": name,
        "n_submaps": n_submaps,
        "runs": runs,
        "target_ratio": TARGET_RATIO,
        "ratio_met": all(r["cost_ratio"] <= TARGET_RATIO for r in runs),
        "wall_ratio_met": all(r["ratio"] <= TARGET_RATIO for r in runs),
        "ab_ratio_median": statistics.median(r["ab_ratio"] for r in runs),
        "cpu_ratio_median": statistics.median(r["cpu_ratio"] for r in runs),
        "target_restore_s": restore_target,
        "restore_met": None if restore_target is None else all(
            r["restore"]["restore_seconds_total"] <= restore_target for r in runs
        ),
    }


def bench_dataset(node: Node, archive: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Run the three phases ``args.repeat`` times on one dataset; return its figures."""
    name = archive.name.removesuffix(".tar.xz")
    records = list(read_messages(dataset_bag(archive, args.bags_dir)))
    base: dict[str, object] = {"mode": MODE, "summary_period": SUMMARY_PERIOD_S, **args.params}
    logs = args.out / "persistence_logs"
    runs = []
    for rep in range(1, args.repeat + 1):
        tag = f"{name}_{rep}"
        print(f"{name} run {rep}/{args.repeat}: {len(records)} submaps, baseline (no state_dir) ...", flush=True)
        baseline = replay(node, records, base, logs / f"{tag}_baseline.log", f"b{rep}", args.timeout)
        state_dir = (args.out / "persistence_state" / tag).resolve()
        shutil.rmtree(state_dir, ignore_errors=True)
        print(f"{name} run {rep}/{args.repeat}: with state_dir {state_dir} ...", flush=True)
        persisted = replay(
            node, records, {**base, "state_dir": state_dir}, logs / f"{tag}_persisted.log", f"p{rep}", args.timeout
        )
        persisted["state_dir_bytes"] = folder_bytes(state_dir)
        print(f"{name} run {rep}/{args.repeat}: restore ...", flush=True)
        restored = restore(node, len(records), {**base, "state_dir": state_dir}, logs / f"{tag}_restore.log", f"r{rep}",
                           args.timeout)
        restored["state_dir_bytes_after"] = folder_bytes(state_dir)
        if not args.keep_state:
            shutil.rmtree(state_dir, ignore_errors=True)
            with contextlib.suppress(OSError):
                state_dir.parent.rmdir()  # when empty
        runs.append(run_figures(rep, baseline, persisted, restored))
        print(f"  -> {table_row(name, runs[-1])}", flush=True)
    return dataset_figures(name, len(records), runs)


HEADER = (
    "| dataset | run | join s (no state / state) | journal s | snapshot s | **cost**: (journal s + snapshot CPU s) / join "
    "| (journal+snapshot)/join, wall | same in CPU s "
    "| (join+journal with state) / (join without) "
    "| Ctrl-C stop s (state / no state) | end-to-end s (no state / state) | restore s (diag / log) | restart to map s "
    "| state_dir MB |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def table_row(name: str, r: dict[str, Any]) -> str:
    """Return the markdown table row of one repetition."""
    b, p, s = r["baseline"], r["persisted"], r["restore"]
    log_s = "–" if s["resumed_log_s"] is None else f"{s['resumed_log_s']:.2f}"
    return (
        f"| {name} | {r['repetition']} | {b['join_seconds_total']:.2f} / {p['join_seconds_total']:.2f} "
        f"| {p['journal_seconds_total']:.3f} | {p['snapshot_seconds_total']:.3f} "
        f"| ({p['journal_seconds_total']:.3f} + {p['snapshot_cpu_seconds_total']:.3f}) / {p['join_seconds_total']:.2f} "
        f"= **{r['cost_ratio']:.3f}** | {r['ratio']:.3f} "
        f"| {p['journal_cpu_seconds_total']:.3f} + {p['snapshot_cpu_seconds_total']:.3f} / {p['join_cpu_seconds_total']:.2f}"
        f" = {r['cpu_ratio']:.3f} | {r['ab_ratio']:.3f} "
        f"| {p['stop_s']:.2f} / {b['stop_s']:.2f} | {b['end_to_end_s']:.1f} / {p['end_to_end_s']:.1f} "
        f"| {s['restore_seconds_total']:.2f} / {log_s} | {s['start_to_map_s']:.1f} | {p['state_dir_bytes'] / 1e6:.1f} |"
    )


def _spread(runs: list[dict[str, Any]]) -> str:
    """``lo-hi s (±p%)`` of the baseline join seconds of a dataset's runs."""
    seconds = [r["baseline"]["join_seconds_total"] for r in runs]
    lo, hi = min(seconds), max(seconds)
    return f"{lo:.2f}-{hi:.2f} s ({100 * (hi - lo) / (hi + lo):+.0f}% about their middle)".replace("+", "±")


def markdown(results: list[dict[str, Any]], command: str) -> str:
    """Return ``persistence.md``: the table of every repetition, then the targets per dataset."""
    lines = [
        "# Persistence cost of the joiner node",
        "",
        f"`{command}`; {MODE_NOTE}. Default `snapshot_period`; bags replayed at full speed; "
        f"summary_period {SUMMARY_PERIOD_S} s. Seconds: join, journal, snapshot and restore as the node counts them; "
        "journal and snapshot s: the joiner's `/diagnostics` after the last submap (start-up and periodic snapshots; the "
        "final snapshot is in the Ctrl-C stop time, which the stop without state_dir bounds from below); end-to-end: "
        "first submap published to the global map with every submap received; restore s: `restore_seconds_total` and "
        "the `resumed from ... in X s` log line; restart to map: process start to the restored global map received. "
        "Cost (the target's figure): the journal's wall time (spent on the joining thread before each join) plus the "
        "snapshots' thread CPU time (they run on the output thread beside the joins; their fsync waits and interpreter-"
        "lock waits take nothing from the joins), over the join seconds; beside it the same in wall time only and in "
        "CPU time only. "
        "CPU s: thread CPU time of the journal writes + snapshots / of the joins (wall time around a journal write also "
        "counts the waits for the interpreter lock while the node's other threads run, and the snapshots run on the "
        "output thread beside the joins, their disk waits included). Last column: the joining thread's seconds per "
        "stream with persistence (joins + journal writes, so also whatever the snapshots took from the joins) over "
        "the joins' seconds without, in the run beside it.",
        "",
        HEADER,
    ]
    notes = []
    for res in results:
        if "skipped" in res or "failed" in res:
            what = "skipped" if "skipped" in res else "failed"
            notes.append(f"- {res['dataset']}: {what} ({res[what]})")
            continue
        for r in res["runs"]:
            lines.append(table_row(res["dataset"], r))
        costs = ", ".join(f"{r['cost_ratio']:.3f}" for r in res["runs"])
        ratios = ", ".join(f"{r['ratio']:.3f}" for r in res["runs"])
        cpu_ratios = ", ".join(f"{r['cpu_ratio']:.3f}" for r in res["runs"])
        ab_ratios = ", ".join(f"{r['ab_ratio']:.3f}" for r in res["runs"])
        notes.append(
            f"- {res['dataset']} ({res['n_submaps']} submaps): cost (journal s + snapshot CPU s) / join {costs} "
            f"(target <= {TARGET_RATIO:.2f}): {'met' if res['ratio_met'] else 'NOT met'}; in wall time only {ratios} "
            f"({'within' if res.get('wall_ratio_met') else 'NOT within'} {TARGET_RATIO:.2f}); in CPU time of the threads "
            f"doing them {cpu_ratios} (median {res['cpu_ratio_median']:.3f}); (join+journal with state) / (join "
            f"without) {ab_ratios} (median {res['ab_ratio_median']:.3f}; a cross-check, not the target's figure: the join "
            f"seconds without state alone range {_spread(res['runs'])} between identical runs)"
        )
        if res["target_restore_s"] is not None:
            restores = ", ".join(f"{r['restore']['restore_seconds_total']:.2f}" for r in res["runs"])
            notes.append(
                f"- {res['dataset']}: restore {restores} s (target <= {res['target_restore_s']:.1f} s): "
                f"{'met' if res['restore_met'] else 'NOT met'}"
            )
    return "\n".join(lines + [""] + notes) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(
        prog="bench_persistence", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--datasets-dir", type=Path, default=Path("../shared/datasets"))
    ap.add_argument("--out", type=Path, default=Path("out/benchmark"))
    ap.add_argument("--bags-dir", type=Path, default=Path("bags"), help="where bags/<dataset> are found or made")
    ap.add_argument("--datasets", nargs="+", default=list(DATASETS), help="dataset names (archives without .tar.xz)")
    ap.add_argument("--repeat", type=int, default=2, help="runs per dataset (this VM is noisy)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds to wait for a run's global map")
    ap.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: the environment's)")
    ap.add_argument("--keep-state", action="store_true", help="keep OUT/persistence_state/<dataset>_<run>")
    ap.add_argument("--set", dest="params", action="append", default=[], metavar="NAME=VALUE",
                    help="another joiner parameter for every run (e.g. publish_rate=0.05); repeatable")
    args = ap.parse_args(argv)
    try:
        args.params = dict(p.split("=", 1) for p in args.params)
    except ValueError:
        ap.error(f"--set takes NAME=VALUE, got {args.params}")
    command = "python -m linear_slam_ros.ros.bench_persistence " + " ".join(sys.argv[1:] if argv is None else argv)
    os.environ.update(loopback_env(args.domain_id))  # this process's DDS, and the joiners' (they inherit it)
    args.out.mkdir(parents=True, exist_ok=True)
    print(MODE_NOTE, flush=True)

    results: list[dict[str, Any]] = []
    failed = False
    with node_session(f"bench_persistence_{os.getpid()}", []) as node:
        for name in args.datasets:
            archive = args.datasets_dir / f"{name}.tar.xz"
            if not archive.exists():
                reason = f"{archive} not found"
                print(f"skipping {name}: {reason}", flush=True)
                results.append({"dataset": name, "skipped": reason})
                continue
            try:
                results.append(bench_dataset(node, archive, args))
            except (RuntimeError, TimeoutError) as exc:
                print(f"{name} failed: {exc}", file=sys.stderr, flush=True)
                results.append({"dataset": name, "failed": str(exc)})
                failed = True

    report = {
        "command": command,
        "mode": MODE,
        "note": MODE_NOTE,
        "ros_domain_id": os.environ.get("ROS_DOMAIN_ID"),
        "summary_period": SUMMARY_PERIOD_S,
        "joiner_parameters": {"mode": MODE, "summary_period": SUMMARY_PERIOD_S, **args.params},
        "datasets": results,
    }
    (args.out / "persistence.json").write_text(json.dumps(report, indent=2) + "\n")
    text = markdown(results, command)
    (args.out / "persistence.md").write_text(text)
    print(text)
    return 1 if failed else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
