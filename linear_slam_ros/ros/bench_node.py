"""Benchmark through the node: every stream replayed at full speed into the installed ``joiner``.

``bench_node [--datasets-dir ../shared/datasets] [--synthetic city2d-20000 ...] [--out out/benchmark] [--mode M]``

For each dataset archive in ``--datasets-dir`` (its bag ``bags/<name>`` is made when missing)
and each synthetic stream (``bags/<name>``, made by ``make bags`` or here), the joiner runs in
its default mode (or ``--mode``) as its own process, as ``demo`` runs it, with ``timing_file``
set. Per stream it records the node's per-submap join time, the freshness of ``pose`` and
``global_map`` (arrival of a submap to the first publication that includes it), submaps per
second end to end (first message sent to the final map received), the joiner's peak RSS against
the final information's triplet bytes (16 bytes per upper-triangle non-zero), and the final
map against the offline result of the same mode (largest difference of the estimates, χ²).

Targets (issue "Online at any scale"): join p99 <= 10 ms and max <= 100 ms; pose freshness
p99 <= 50 ms; global_map freshness p99 <= 2 s at the 20,000-pose scale; >= 500 submaps/s on
pose-only streams of 10,000 submaps or more; peak RSS <= 3 x triplet bytes + 300 MB; the final
map equal to the offline one (1e-9). Writes ``OUT/node.json``, ``OUT/node.md`` (printed too) and
``OUT/node/<stream>/`` (the demo's outputs, ``timing.csv``, ``timing.png``).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from linear_slam_ros.evaluation import city
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.io.datasets import read_dataset
from linear_slam_ros.joiner.config import JoinerConfig
from linear_slam_ros.joiner.registry import methods
from linear_slam_ros.joiner.strategy import MapType
from linear_slam_ros.ros.bag_from_dataset import make_bag
from linear_slam_ros.ros.bagio import read_messages
from linear_slam_ros.ros.demo import decode_global_map, run_demo

TARGETS = {
    "join_p99_ms": 10.0, "join_max_ms": 100.0, "pose_fresh_p99_ms": 50.0, "map_fresh_p99_s_at_20000": 2.0,
    "submaps_per_second_pose_only_10000": 500.0, "rss_factor": 3.0, "rss_extra_mb": 300.0, "map_equal": 1e-9,
}
SYNTHETIC = city.STANDARD_NAMES
POSE_GRAPH_SYNTHETIC = ("city2d", "garage3d")


def _timing(path: Path) -> dict[str, np.ndarray]:
    with open(path) as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r[k]) for r in rows]) for k in (rows[0] if rows else {})}


def _plot(timing: dict[str, np.ndarray], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    t = timing["arrival_s"]
    keys = ("join_ms", "pose_freshness_ms", "map_freshness_ms")
    labels = ("join (ms)", "pose freshness (ms)", "global_map freshness (ms)")
    for ax, key, label in zip(axes, keys, labels, strict=True):
        ax.plot(t, timing[key], ".", markersize=2)
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[-1].set_xlabel("arrival at the node (s from the first submap)")
    axes[0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _max_relative_difference(a: Any, b: Any) -> float:
    """Largest difference of two maps' estimates relative to the largest |value| (same variables, same order)."""
    if a.x.shape != b.x.shape or not np.array_equal(a.ids, b.ids):
        return float("inf")
    return float(np.abs(a.x - b.x).max() / max(1.0, float(np.abs(b.x).max())))


def bench_stream(source: str, bag: Path, out: Path, mode: str | None, as_pose_graph: bool) -> dict[str, Any]:
    """Replay one stream through the joiner and compare with the offline result of the same mode."""
    if not (bag / "metadata.yaml").exists():
        make_bag(source, bag, as_pose_graph=as_pose_graph)
    out.mkdir(parents=True, exist_ok=True)
    timing_file = (out / "timing.csv").resolve()
    report = run_demo(Path(source), bag, out, mode, params={"timing_file": str(timing_file)}, timeout_s=1800.0)
    mode_used = str(report["mode"])
    maps = read_dataset(source).maps
    offline = run_join(maps, mode_used)
    node_map = decode_global_map(next(iter(read_messages(out / "global_map_bag"))).raw).local_map
    info = node_map.info
    upper_nnz = int((info.nnz + node_map.state_dim) // 2) if hasattr(info, "nnz") else int(np.count_nonzero(np.triu(info)))
    triplet_mb = 16 * upper_nnz / 2**20
    for _ in range(50):  # the joiner writes timing_file as it exits
        if timing_file.exists():
            break
        time.sleep(0.1)
    timing = _timing(timing_file)
    _plot(timing, f"{report['dataset']} through the joiner ({mode_used})", out / "timing.png")
    pose_only = not read_dataset(source).kind.has_features
    entry = {
        **report,
        "pose_only": pose_only,
        "offline_seconds": offline.seconds,
        "offline_chi2": chi2(offline.result, maps),
        "map_difference": _max_relative_difference(node_map, offline.result),
        "triplet_mb": triplet_mb,
        "rss_bound_mb": TARGETS["rss_factor"] * triplet_mb + TARGETS["rss_extra_mb"],
    }
    entry["checks"] = _checks(entry)
    return entry


def _checks(e: dict[str, Any]) -> dict[str, bool | None]:
    n = int(e["n_submaps_sent"])
    checks: dict[str, bool | None] = {
        "join_p99": (e["per_submap_ms_p99"] or 0) <= TARGETS["join_p99_ms"],
        "join_max": (e["per_submap_ms_max"] or 0) <= TARGETS["join_max_ms"],
        "pose_fresh_p99": (e["freshness_pose_ms_p99"] or 0) <= TARGETS["pose_fresh_p99_ms"],
        "map_fresh_p99": (e["freshness_map_ms_p99"] or 0) <= TARGETS["map_fresh_p99_s_at_20000"] * 1e3 if n >= 20000 else None,
        "throughput": (e["submaps_per_second"] or 0) >= TARGETS["submaps_per_second_pose_only_10000"]
        if e["pose_only"] and n >= 10000 else None,
        "rss": (e["joiner_peak_rss_mb"] or 0) <= e["rss_bound_mb"],
        "map_equal": e["map_difference"] <= TARGETS["map_equal"],
        "all_joined": e["n_submaps_joined"] == n,
    }
    return checks


def _fmt(v: Any, digits: int = 1) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "**NO**"
    if isinstance(v, float):
        return f"{v:.{digits}e}" if (abs(v) < 1e-3 and v != 0) else f"{v:,.{digits}f}"
    return str(v)


def to_markdown(entries: list[dict[str, Any]]) -> str:
    """Return the benchmark table (one row per stream) and the list of missed targets."""
    head = (
        "| stream | mode | submaps | join p50 / p99 / max ms | pose fresh p50 / p99 / max ms | map fresh p50 / p99 / max s "
        "| submaps/s | peak RSS MB (bound) | χ² node / offline | Δx vs offline |\n|---|---|---|---|---|---|---|---|---|---|"
    )
    rows = []
    missed = []
    for e in entries:
        rows.append(
            f"| {e['dataset']} | {e['mode']} | {e['n_submaps_joined']}/{e['n_submaps_sent']} "
            f"| {_fmt(e['per_submap_ms_p50'], 2)} / {_fmt(e['per_submap_ms_p99'], 1)} / {_fmt(e['per_submap_ms_max'], 0)} "
            f"| {_fmt(e['freshness_pose_ms_p50'], 1)} / {_fmt(e['freshness_pose_ms_p99'], 1)} "
            f"/ {_fmt(e['freshness_pose_ms_max'], 0)} "
            f"| {_fmt((e['freshness_map_ms_p50'] or 0) / 1e3, 2)} / {_fmt((e['freshness_map_ms_p99'] or 0) / 1e3, 2)} "
            f"/ {_fmt((e['freshness_map_ms_max'] or 0) / 1e3, 2)} | {_fmt(e['submaps_per_second'], 0)} "
            f"| {_fmt(e['joiner_peak_rss_mb'], 0)} ({_fmt(e['rss_bound_mb'], 0)}) | {e['chi2']:.2f} / {e['offline_chi2']:.2f} "
            f"| {_fmt(e['map_difference'], 1)} |"
        )
        missed += [f"{e['dataset']}: {k}" for k, ok in e["checks"].items() if ok is False]
    summary = "\n\nTargets missed: " + (", ".join(missed) if missed else "none") + "\n"
    return head + "\n" + "\n".join(rows) + summary


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(prog="bench_node", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets-dir", type=Path, default=Path("../shared/datasets"))
    ap.add_argument(
        "--synthetic", nargs="*", default=list(SYNTHETIC), help="synthetic streams (city2d-N, garage3d-N, features2d-N)"
    )
    ap.add_argument("--only", nargs="*", default=None, help="only these streams (dataset or synthetic names)")
    ap.add_argument("--bags", type=Path, default=Path("bags"))
    ap.add_argument("--out", type=Path, default=Path("out/benchmark"))
    ap.add_argument(
        "--mode", choices=[m.value for m in methods(MapType.AS_IS, online_only=True)], default=None,
        help=f"joiner mode (default: the joiner's, {JoinerConfig().mode.value})",
    )
    args = ap.parse_args(argv)
    streams: list[tuple[str, str, bool]] = []  # (name, source, as_pose_graph)
    archives = sorted(args.datasets_dir.glob("*.tar.xz")) if args.datasets_dir.is_dir() else []
    if not archives:
        print(f"no datasets in {args.datasets_dir}: only the synthetic streams are measured", file=sys.stderr)
    streams += [(a.name.removesuffix(".tar.xz"), str(a), False) for a in archives]
    streams += [(s, f"synthetic:{s}", s.split("-")[0] in POSE_GRAPH_SYNTHETIC) for s in args.synthetic]
    if args.only:
        unknown = sorted(set(args.only) - {name for name, _, _ in streams})
        if unknown:  # a typo measured nothing and overwrote node.md with an empty table
            ap.error(f"--only {' '.join(unknown)}: no such stream (have: {', '.join(name for name, _, _ in streams)})")
        streams = [s for s in streams if s[0] in args.only]
    entries = []
    for name, source, as_graph in streams:
        print(f"== {name}", file=sys.stderr, flush=True)
        entries.append(bench_stream(source, args.bags / name, args.out / "node" / name, args.mode, as_graph))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "node.json").write_text(json.dumps({"targets": TARGETS, "streams": entries}, indent=2, default=str) + "\n")
    table = to_markdown(entries)
    header = f"# Through the node ({os.cpu_count()} cores), full-speed replay\n\n"
    (args.out / "node.md").write_text(header + table)
    print(header + table)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
