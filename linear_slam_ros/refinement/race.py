"""The race: linear joining plus background refinement against GTSAM's iSAM2, on the same streams, in one run.

``python -m linear_slam_ros.refinement.race [--datasets-dir ../shared/datasets] [--out out/benchmark] [--only NAME ...]``
(the third line of ``make benchmark``; gtsam comes from ``requirements-bench.txt``, never a
dependency of the node).

Per stream, one submap at a time, in one process each:

- **ours**: online divide and conquer (:class:`~linear_slam_ros.joiner.joiner.Joiner`, merges
  inline) times each submap's join; every joined submap goes to a
  :class:`~linear_slam_ros.refinement.worker.RefineWorker` process; as the node's output
  thread does, a thread of its own computes the linear global map (``end_pose`` frame, the
  node's default) at most every 0.5 s and at most half of the time while the joins go on (its
  estimate goes to the refiner), and once after the last submap. CPU, each thread's own
  (``time.thread_time``): the joins (the joining thread inside ``offer``), the linear outputs
  (that thread, and the final output), the rest of this process (the queue's feeder thread,
  which pickles the submaps sent to the refiner, and the BLAS libraries' own threads, which
  take part in the joins' and outputs' products) and the refiner process's.
- **iSAM2** (gtsam, default ``ISAM2Params``): one ``update`` per submap with that submap's
  factors. Conversion: each local map's pose block ``i`` (its estimate of pose ``i`` in the frame
  of its frame pose ``f``, and the diagonal block of its information) becomes
  ``BetweenFactor(f, i)``; the pose-only datasets' information is block diagonal per edge, so
  nothing is dropped. The information is carried to gtsam's error exactly to first order at the
  measurement (translation error in the measured pose's frame; in 3D the rotation vector, twice
  the quaternion's vector part, first: :func:`linear_slam_ros.pose_graph.g2o.graph_to_g2o` then a
  reordering). A new pose starts at its frame pose's current estimate composed with the
  measurement. Pose 0 of the first submap gets a prior of sigma 1e-6 (the gauge). Pose-feature
  streams (VicPark6898) are not converted: their local maps' information couples poses and
  features, which gtsam's stock factors cannot carry.

Scored with the project's own χ² (:func:`linear_slam_ros.evaluation.objective.chi2`); the optimum
is the converged refined map's χ². Targets (issue 13): the refined map within 0.1% of the optimum
≤ 2 s after the last submap; the CPU of joining plus refinement ≤ 1/3 of iSAM2's (``cpu_join_refine_s``:
the joins, the rest of this process and the refiner process). iSAM2's figure is its updates plus the
estimate of each new pose's frame pose that its start needs (``calculateEstimate(key)``: it makes
iSAM2 back-substitute its delta at every update, which ``update`` alone does only when it
relinearises; reported apart as ``cpu_estimate_queries_s``, 20–50% of the total on the larger
streams), with no full estimate computed after them. The ratio ``cpu_third_of_isam2`` is on that
total; ``cpu_third_of_isam2_updates`` on the updates alone (a user who starts new poses without a
query). The linear outputs, which a node publishes whether it refines or not, are reported apart and
in ``cpu_total_s``, which is checked against the same third as well.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import queue
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from linear_slam_ros.core.geometry import angles3
from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.core.runtime import SHARED_MACHINE_BLAS_THREADS, blas_threads
from linear_slam_ros.core.timing import latency
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.joiner.config import OutputFrame
from linear_slam_ros.joiner.joiner import Joiner, JoinerState, global_result
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.refinement.online import LinearEstimate, RefinerConfig, Submission
from linear_slam_ros.refinement.worker import Published, RefineWorker, SinkSpec

STREAMS = ("Intel", "manhattanOlson3500", "sphere2500", "VicPark_6898_local_maps", "synthetic:city2d-20000")
TARGETS = {"refined_within": 1e-3, "refined_lag_s": 2.0, "cpu_ratio": 1.0 / 3.0}
OUTPUT_PERIOD_S = 0.5
OUTPUT_DUTY = 0.5


def run_ours(maps: Sequence[LocalMap], config: RefinerConfig | None = None, timeout_s: float = 600.0) -> dict[str, Any]:
    """Join ``maps`` one by one with the refiner in its own process (module docstring)."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    results = ctx.Queue()
    worker = RefineWorker(SinkSpec("linear_slam_ros.refinement.worker:queue_sink", {"out": results}), config)
    # as the node's refiner, started with the node, is: the child is up before the stream (its start-up CPU
    # still counts in cpu_refiner_s)
    if not worker.wait_ready(120.0):
        raise RuntimeError("the refiner process did not start within 120 s")
    with blas_threads(SHARED_MACHINE_BLAS_THREADS):  # as the node; the caller's setting back afterwards
        joiner = Joiner(JoinMethod.ONLINE_DC)
        steps: list[float] = []
        outputs = _Outputs(joiner, worker)
        c0 = time.process_time()
        cpu_join = 0.0
        last_arrival = 0.0
        outputs.start()
        try:
            for seq, m in enumerate(maps, start=1):
                arrived = time.monotonic()
                t0, u0 = time.perf_counter(), time.thread_time()
                joined = joiner.offer(m, seq)
                cpu_join += time.thread_time() - u0
                steps.append(time.perf_counter() - t0)
                if joined:
                    worker.submit(Submission(seq, m, arrived))
                last_arrival = arrived
        finally:
            outputs.stop()
        t_join_end, u_join_end = time.perf_counter(), time.thread_time()
        linear_map = _linear_map(joiner.state)
        worker.linear(LinearEstimate.of_map(linear_map, joiner.state.n_joined))
        final_linear_seconds = time.perf_counter() - t_join_end
        cpu_outputs = outputs.cpu_seconds + time.thread_time() - u_join_end
        output_seconds = outputs.seconds
        cpu_parent = time.process_time() - c0
    publications: list[Published] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            pub = results.get(timeout=1.0)
        except queue.Empty:
            continue
        publications.append(pub)
        if pub.refined is not None and pub.refined.n_submaps == len(maps) and pub.refined.converged:
            break
    time.sleep(0.2)  # nothing more comes: the child is idle
    worker.stop()
    child_cpu = 0.0
    while True:
        try:
            pub = results.get(timeout=5.0)
        except queue.Empty:
            break
        if pub.final:
            child_cpu = pub.cpu_seconds
            break
        publications.append(pub)
    final = [p for p in publications if p.refined is not None and p.refined.n_submaps == len(maps)]
    return {
        "n_submaps": len(maps),
        "join_seconds": float(sum(steps)),
        **_latency("join", steps),
        "linear_output_seconds": output_seconds + final_linear_seconds,
        "cpu_parent_s": cpu_parent,
        "cpu_join_s": cpu_join,
        "cpu_outputs_s": cpu_outputs,
        "cpu_rest_s": cpu_parent - cpu_join - cpu_outputs,
        "cpu_refiner_s": child_cpu,
        "cpu_join_refine_s": cpu_parent - cpu_outputs + child_cpu,
        "cpu_total_s": cpu_parent + child_cpu,
        "chi2_linear": chi2(linear_map, maps),
        "publications_after_last": [
            {"lag_s": p.published_at - last_arrival, "chi2": p.refined.chi2, "converged": p.refined.converged}
            for p in final if p.refined is not None
        ],
        "refined_map": final[-1].refined.map if final and final[-1].refined is not None else None,
        "worker_exitcodes": worker.exitcodes,
    }


class _Outputs(threading.Thread):
    """The linear global map computed on a thread of its own while submaps are joined, as the node's output thread does.

    At most every :data:`OUTPUT_PERIOD_S` and at most :data:`OUTPUT_DUTY` of the time, from the
    joiner's state as it is then (a value: the joins go on meanwhile); its estimate goes to the
    refiner. Nothing is computed before the first submap is joined.
    """

    def __init__(self, joiner: Joiner, worker: RefineWorker) -> None:
        super().__init__(name="race-outputs", daemon=True)
        self._joiner = joiner
        self._worker = worker
        self._done = threading.Event()
        self.seconds = 0.0
        self.cpu_seconds = 0.0  # this thread's CPU time
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self._loop()
        except BaseException as exc:  # raised again by stop(), in the race's thread
            self.error = exc

    def _loop(self) -> None:
        while not self._done.wait(OUTPUT_PERIOD_S if self.seconds else 0.01):
            state = self._joiner.state
            if state.n_joined == 0:
                continue
            t0, u0 = time.perf_counter(), time.thread_time()
            self._worker.linear(LinearEstimate.of_map(_linear_map(state), state.n_joined))
            cost = time.perf_counter() - t0
            self.seconds += cost
            self.cpu_seconds += time.thread_time() - u0
            if self._done.wait(max(0.0, cost / OUTPUT_DUTY - cost - OUTPUT_PERIOD_S)):
                return

    def stop(self) -> None:
        """End the loop (after the output under way), wait for it, and raise what it raised."""
        self._done.set()
        self.join()
        if self.error is not None:
            raise RuntimeError("the race's output thread failed") from self.error


def _linear_map(state: JoinerState) -> LocalMap:
    """The joiner's global map as the node's publisher computes it by default (``output_frame`` ``end_pose``)."""
    result = global_result(state, OutputFrame.END_POSE)
    assert isinstance(result, LocalMap)
    return result


# ---------------------------------------------------------------------------------------------- iSAM2


def _gtsam_factors(maps: Sequence[LocalMap]) -> list[list[tuple[int, int, Any, Any]]]:
    """Per local map, ``(from, to, measurement, noise)`` of its between factors (module docstring)."""
    gtsam = _gtsam()
    from linear_slam_ros.pose_graph.chunks import graph_from_local_maps
    from linear_slam_ros.pose_graph.g2o import graph_to_g2o

    out = []
    for m in maps:
        g2o = graph_to_g2o(graph_from_local_maps([m]))
        factors = []
        for e in range(g2o.from_ids.size):
            z, info = g2o.measurements[e], g2o.information[e]
            if g2o.dim == 2:
                meas: Any = gtsam.Pose2(z[0], z[1], z[2])
            else:
                qx, qy, qz, qw = z[3:]
                meas = gtsam.Pose3(gtsam.Rot3.Quaternion(qw, qx, qy, qz), gtsam.Point3(*z[:3]))
                # g2o's error [t; q_vec] = D [omega; t] with omega = 2 q_vec (gtsam's tangent order)
                d = np.zeros((6, 6))
                d[:3, 3:] = np.eye(3)
                d[3:, :3] = 0.5 * np.eye(3)
                info = d.T @ info @ d
            noise = gtsam.noiseModel.Gaussian.Information(0.5 * (info + info.T))
            factors.append((int(g2o.from_ids[e]), int(g2o.to_ids[e]), meas, noise))
        out.append(factors)
    return out


def _gtsam() -> Any:
    """gtsam, imported when the race runs (``requirements-bench.txt``; not a dependency of the package)."""
    import importlib

    return importlib.import_module("gtsam")


def _to_ours(dim: int, value: Any) -> np.ndarray:
    if dim == 2:
        return np.array([value.x(), value.y(), value.theta()])
    active = value.rotation().matrix()
    return np.concatenate([value.translation(), angles3(active.T[None])[0]])


def run_isam2(maps: Sequence[LocalMap]) -> dict[str, Any]:
    """iSAM2 with default parameters, one update per local map (module docstring)."""
    gtsam = _gtsam()
    dim = maps[0].dim
    factors = _gtsam_factors(maps)
    origin = maps[0].frame_id
    isam = gtsam.ISAM2(gtsam.ISAM2Params())
    pose_cls = gtsam.Pose2 if dim == 2 else gtsam.Pose3
    between = gtsam.BetweenFactorPose2 if dim == 2 else gtsam.BetweenFactorPose3
    prior = gtsam.PriorFactorPose2 if dim == 2 else gtsam.PriorFactorPose3
    current = isam.calculateEstimatePose2 if dim == 2 else isam.calculateEstimatePose3
    known: set[int] = set()
    steps = []
    query_cpu = 0.0
    c0 = time.process_time()
    for i, edges in enumerate(factors):
        t0 = time.perf_counter()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        new: dict[int, Any] = {}
        if i == 0:
            graph.add(prior(origin, pose_cls(), gtsam.noiseModel.Isotropic.Sigma(3 if dim == 2 else 6, 1e-6)))
            new[origin] = pose_cls()
        for f, t, meas, noise in edges:
            graph.add(between(f, t, meas, noise))
            if t not in known and t not in new:  # starts at its frame pose's current estimate composed with the edge
                if f in new:
                    start = new[f]
                else:
                    q0 = time.process_time()
                    start = current(f)
                    query_cpu += time.process_time() - q0
                new[t] = start.compose(meas)
        for key, value in new.items():
            values.insert(key, value)
        isam.update(graph, values)
        known.update(new)
        steps.append(time.perf_counter() - t0)
    cpu = time.process_time() - c0
    estimate = isam.calculateEstimate()
    ids = np.array(sorted(k for k in known if k != origin), dtype=np.int64)
    x = np.concatenate([_to_ours(dim, estimate.atPose2(k) if dim == 2 else estimate.atPose3(k)) for k in ids.tolist()])
    import scipy.sparse as sp

    result = LocalMap.trusted(dim, origin, None, ids, np.full(ids.size, POSE, np.int8), x, sp.identity(x.size, format="csr"))
    return {"cpu_total_s": cpu, "cpu_estimate_queries_s": query_cpu, **_latency("update", steps), "chi2": chi2(result, maps)}


def _latency(prefix: str, seconds: Sequence[float]) -> dict[str, float]:
    lat = latency(seconds)
    return {f"{prefix}_p50_ms": lat.p50_ms, f"{prefix}_p99_ms": lat.p99_ms, f"{prefix}_max_ms": lat.max_ms}


# ---------------------------------------------------------------------------------------------- driver


def race_stream(name: str, source: str, config: RefinerConfig | None = None, isam2: bool = True) -> dict[str, Any]:
    """Run ours (refiner settings ``config``) then iSAM2 (unless ``isam2`` is False) on one stream; return the
    figures and the target checks."""
    maps = _read(source)
    print(f"== {name}: {len(maps)} submaps", file=sys.stderr, flush=True)
    ours = run_ours(maps, config)
    ours["refiner_config"] = dataclasses.asdict(config or RefinerConfig())
    refined = ours.pop("refined_map")
    optimum = min([p["chi2"] for p in ours["publications_after_last"]], default=math.nan)
    ours["chi2_refined"] = chi2(refined, maps) if refined is not None else math.nan
    within = [p for p in ours["publications_after_last"] if p["chi2"] <= optimum * (1 + TARGETS["refined_within"])]
    ours["refined_lag_s"] = within[0]["lag_s"] if within else math.nan
    entry: dict[str, Any] = {"stream": name, "ours": ours, "optimum_chi2": optimum}
    has_features = any(np.any(m.kinds != POSE) for m in maps[:50])
    if has_features or not isam2:
        entry["isam2"] = None
    else:
        entry["isam2"] = run_isam2(maps)
    isam = entry["isam2"]
    entry["checks"] = {
        "refined_lag": ours["refined_lag_s"] <= TARGETS["refined_lag_s"],
        "cpu_third_of_isam2": _within_third(ours["cpu_join_refine_s"], isam),
        "cpu_third_of_isam2_with_outputs": _within_third(ours["cpu_total_s"], isam),
        "cpu_third_of_isam2_updates": _within_third(ours["cpu_join_refine_s"], isam, updates_only=True),
    }
    print(json.dumps(entry, indent=1, default=str), file=sys.stderr, flush=True)
    return entry


def _within_third(ours_cpu_s: float, isam: dict[str, Any] | None, updates_only: bool = False) -> bool | None:
    """Whether ``ours_cpu_s`` is within :data:`TARGETS`' fraction of iSAM2's CPU, or of its updates alone
    (without the estimate queries that start new poses); ``None``: no iSAM2 run."""
    if isam is None:
        return None
    cpu = isam["cpu_total_s"] - (isam["cpu_estimate_queries_s"] if updates_only else 0.0)
    return ours_cpu_s <= TARGETS["cpu_ratio"] * cpu


def _read(source: str) -> Sequence[LocalMap]:
    """The local maps of a dataset archive or folder, or of ``synthetic:NAME``."""
    import linear_slam_ros.evaluation.city  # noqa: F401 - registers synthetic:NAME
    from linear_slam_ros.io.datasets import read_dataset

    return read_dataset(source).maps


def to_markdown(entries: list[dict[str, Any]]) -> str:
    """The race table and the missed targets."""
    head = (
        "| stream | submaps | ours join p50 / p99 / max ms | ours CPU s: join + rest + refiner (+ outputs) "
        "| χ² linear / refined (optimum) | refined ≤0.1% after s | iSAM2 update p50 / p99 / max ms | iSAM2 CPU s "
        "| iSAM2 χ² | CPU ours / iSAM2 (with outputs) | CPU ours / iSAM2's updates alone |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|"
    )
    rows, missed = [], []
    for e in entries:
        o, i = e["ours"], e["isam2"]
        isam_cols = "– | – | – | – | –" if i is None else (
            f"{i['update_p50_ms']:.2f} / {i['update_p99_ms']:.1f} / {i['update_max_ms']:.0f} | {i['cpu_total_s']:.2f} "
            f"(queries {i['cpu_estimate_queries_s']:.2f}) "
            f"| {i['chi2']:.2f} | {o['cpu_join_refine_s'] / i['cpu_total_s']:.2f} ({o['cpu_total_s'] / i['cpu_total_s']:.2f}) "
            f"| {o['cpu_join_refine_s'] / (i['cpu_total_s'] - i['cpu_estimate_queries_s']):.2f}"
        )
        rows.append(
            f"| {e['stream']} | {o['n_submaps']} | {o['join_p50_ms']:.2f} / {o['join_p99_ms']:.1f} / {o['join_max_ms']:.0f} "
            f"| {o['cpu_join_s']:.2f} + {o['cpu_rest_s']:.2f} + {o['cpu_refiner_s']:.2f} = {o['cpu_join_refine_s']:.2f} "
            f"(+ {o['cpu_outputs_s']:.2f} = {o['cpu_total_s']:.2f}) "
            f"| {o['chi2_linear']:.2f} / {o['chi2_refined']:.2f} ({e['optimum_chi2']:.2f}) | {o['refined_lag_s']:.2f} "
            f"| {isam_cols} |"
        )
        missed += [f"{e['stream']}: {k}" for k, ok in e["checks"].items() if ok is False]
    return head + "\n" + "\n".join(rows) + "\n\nTargets missed: " + (", ".join(missed) if missed else "none") + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(prog="race", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets-dir", type=Path, default=Path("../shared/datasets"))
    ap.add_argument("--out", type=Path, default=Path("out/benchmark"))
    ap.add_argument("--only", nargs="*", default=None, help="stream names (e.g. Intel synthetic:city2d-20000)")
    ap.add_argument("--growth", type=float, default=RefinerConfig.growth,
                    help="refiner: take queued submaps in mid-round once they number this fraction of those taken")
    ap.add_argument("--no-reuse-analysis", action="store_true", help="refiner: analyse every step's system afresh")
    ap.add_argument("--idle-s", type=float, default=RefinerConfig.idle_s,
                    help="refiner: take queued submaps in once none has arrived for this long, s")
    ap.add_argument("--streaming-rtol", type=float, default=RefinerConfig.streaming_rtol,
                    help="refiner: while submaps arrive, a round ends once a step lowers χ² by at most this fraction "
                    "(0: only at chi2_rtol)")
    ap.add_argument("--settle-s", type=float, default=RefinerConfig.settle_s,
                    help="refiner: rounds run to chi2_rtol once no submap has arrived for this long, s")
    ap.add_argument("--place-steps", type=int, default=RefinerConfig.place_steps,
                    help="refiner: Gauss-Newton steps over a batch's submaps alone that place its new variables "
                    "before the round (0: the warm start as it is)")
    ap.add_argument("--no-isam2", action="store_true", help="ours only (the levers' comparisons)")
    args = ap.parse_args(argv)
    names = args.only or STREAMS
    sources = {n: n if n.startswith("synthetic:") else str(args.datasets_dir / f"{n}.tar.xz") for n in names}
    missing = [n for n, source in sources.items() if not n.startswith("synthetic:") and not Path(source).exists()]
    if missing:  # a table without them would read as a whole run
        print(f"race: no archive {', '.join(sources[n] for n in missing)} (names are case-sensitive, as the "
              f"archives': {', '.join(STREAMS)}); nothing run", file=sys.stderr)
        return 2
    entries = []
    for name in names:
        source = sources[name]
        config = RefinerConfig(
            growth=args.growth, idle_s=args.idle_s, streaming_rtol=args.streaming_rtol, settle_s=args.settle_s,
            reuse_analysis=not args.no_reuse_analysis, place_steps=args.place_steps,
        )
        entries.append(race_stream(name, source, config, isam2=not args.no_isam2))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "race.json").write_text(json.dumps({"targets": TARGETS, "streams": entries}, indent=2, default=str) + "\n")
    table = f"# Linear joining + refinement vs iSAM2 ({os.cpu_count()} cores, one run)\n\n" + to_markdown(entries)
    (args.out / "race.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
