"""Offline command line: ``python -m linear_slam_ros join|refine|lago|unpack|benchmark ...``.

Only parses arguments and calls library functions; everything it does is scriptable.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

import linear_slam_ros.evaluation.city  # noqa: F401 - registers the synthetic:NAME sources (generated on demand)
from linear_slam_ros.core.errors import ConfigError, LinearSlamError
from linear_slam_ros.core.geometry import pose_size
from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.core.timing import latency_summary, peak_rss_mb
from linear_slam_ros.evaluation.benchmark import run_benchmark
from linear_slam_ros.evaluation.nonlinear import gauss_newton, refine
from linear_slam_ros.evaluation.objective import MapObjective, chi2
from linear_slam_ros.evaluation.runner import JoinRun, run_feature_join, run_join, run_joiner
from linear_slam_ros.io.datasets import Dataset, MapKind, read_dataset, resolve_dataset_dir, write_poses
from linear_slam_ros.io.results import write_map, write_report, write_result, write_tum_poses
from linear_slam_ros.joiner.config import JoinerConfig
from linear_slam_ros.joiner.registry import get_strategy
from linear_slam_ros.joiner.robots import qualify, robot_slots
from linear_slam_ros.joiner.snapshot import read_snapshot, write_snapshot
from linear_slam_ros.joiner.strategy import PER_SUBMAP, FoldStrategy, JoinMethod, MapType
from linear_slam_ros.joining.hold import HeldClosure, without_held
from linear_slam_ros.joining.islands import maps_within
from linear_slam_ros.joining.reinit import Reinitialisation, as_joined
from linear_slam_ros.pose_graph.chunks import edge_maps, graph_from_local_maps, star_local_maps
from linear_slam_ros.pose_graph.g2o import read_g2o, write_g2o
from linear_slam_ros.pose_graph.graph import PoseGraph
from linear_slam_ros.pose_graph.lago import lago

logger = logging.getLogger("linear_slam_ros")

FloatArray = npt.NDArray[np.float64]

PROGRESS_MIN_MAPS = 100
"""Show a progress bar when joining at least this many local maps."""


FORMATS = ("reference", "tum", "g2o")
"""Output formats of join, refine and lago: ``poses.txt`` (+ ``features.txt``), ``poses.tum``, ``graph.g2o``."""


class HelpWithDefaults(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` shows each option's default, except for required options and ``None`` (no value)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.required or action.default is None:
            return action.help
        return super()._get_help_string(action)


def _progress(total: int, desc: str):  # type: ignore[no-untyped-def]
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="map", disable=None if total >= PROGRESS_MIN_MAPS else True, leave=False)


def read_source(path: Path, kind: str | None = None) -> Dataset:
    """Read what a command's dataset argument names: a dataset folder or archive, a rosbag2 bag of
    ``local_map`` / ``pose_graph`` messages (``bags/vicpark200``), or a ``.g2o`` file.

    A g2o pose graph (2D or 3D) becomes pose-only local maps, one per pose that edges leave
    (:func:`linear_slam_ros.pose_graph.chunks.star_local_maps`), of kind ``2DPG`` / ``3DPG``.

    Raises:
        LinearSlamError: the file cannot be read or is malformed; ``kind`` contradicts a g2o file.
    """
    if (path / "metadata.yaml").is_file():
        return read_bag(path, kind)
    if path.suffix != ".g2o":
        return read_dataset(path, kind=kind)
    graph = read_g2o(path)
    map_kind = MapKind.PG2D if graph.dim == 2 else MapKind.PG3D
    if kind is not None and MapKind(kind) is not map_kind:
        raise ConfigError(f"{path} is a {graph.dim}D pose graph ({map_kind.value}), not {MapKind(kind).value}")
    isolated = np.setdiff1d(graph.pose_ids, np.concatenate([graph.from_ids, graph.to_ids]))
    if isolated.size:  # no edge measures them: the result cannot hold them
        logger.warning("%s: %d vertices no edge names are left out (vertex %s%s)", path, isolated.size,
                       ", ".join(str(int(i)) for i in isolated[:5]), ", ..." if isolated.size > 5 else "")
    return Dataset(path.stem, map_kind, tuple(star_local_maps(graph)))


def read_bag(path: Path, kind: str | None = None) -> Dataset:
    """Read a rosbag2 bag's ``local_map`` / ``pose_graph`` messages as a dataset named after the bag's folder.

    The CLI is an application like the ROS nodes: it reads bags through :mod:`msg_adapters.bags`
    (rosbags, no ROS install), imported only when a bag is given. The maps are the ones the node
    would join (:func:`msg_adapters.bags.read_bag_submaps`); the kind is the bag's recorded one.

    Raises:
        DatasetError: the bag cannot be read or holds no valid submap; ``kind`` is not the bag's.
    """
    from msg_adapters.bags import read_bag_submaps

    submaps = read_bag_submaps(path, None if kind is None else MapKind(kind).value)
    return Dataset(path.name, MapKind(submaps.kind), submaps.maps)


def pose_values(local_map: LocalMap) -> dict[int, FloatArray]:
    """Return every pose of a map by id, its frame pose (the origin) included."""
    poses = {local_map.frame_id: np.zeros(pose_size(local_map.dim))}
    for i in np.flatnonzero(local_map.kinds == POSE).tolist():
        poses[int(local_map.ids[i])] = local_map.x[local_map.scalar_slice(i)]
    return poses


def _check_formats(formats: Sequence[str], map_type: MapType, dataset: Dataset | None = None) -> None:
    """Raise :class:`ConfigError` when the result cannot be written in one of ``formats``."""
    extra = sorted(set(formats) - {"reference"})
    if map_type is MapType.FEATURE_ONLY and extra:
        raise ConfigError(f"--format {' '.join(extra)} writes poses; feature-only maps hold none (use reference)")
    if dataset is not None and "g2o" in formats and dataset.kind.has_features:
        raise ConfigError(f"--format g2o writes a pose graph; {dataset.name} is a pose-feature dataset ({dataset.kind.value})")


def _write_g2o(out_dir: Path, source: Path, dataset: Dataset, joined: LocalMap) -> None:
    """Write ``graph.g2o``: the input's edges (a g2o file's own, else the local maps') and the joined poses.

    Only the poses the result holds are written, with the edges between them: a pose outside the
    main island, or the target of a loop closure still held, has no estimate (g2o would read the
    origin as one).
    """
    graph = read_g2o(source) if source.suffix == ".g2o" else graph_from_local_maps(dataset.maps)
    poses = pose_values(joined)
    if not np.isin(graph.pose_ids, list(poses)).all():
        inside = np.isin(graph.from_ids, list(poses)) & np.isin(graph.to_ids, list(poses))
        left_out = int(np.count_nonzero(~np.isin(graph.pose_ids, list(poses))))
        logger.warning("%s: graph.g2o holds the %d poses of the result; %d poses without an estimate (other islands, "
                       "loop closures still held) and their %d edges are left out", dataset.name, len(poses), left_out,
                       int(np.count_nonzero(~inside)))
        graph = PoseGraph.from_edges(graph.from_ids[inside], graph.to_ids[inside], graph.measurements[inside],
                                     graph.information[inside], np.intersect1d(graph.pose_ids, list(poses)),
                                     dim=graph.dim, name=graph.name)
    write_g2o(out_dir / "graph.g2o", graph, poses)


@dataclass(frozen=True)
class Sources:
    """What the dataset arguments of join / refine name, in joining order.

    Attributes:
        dataset: every local map, in the order they are joined (several robots' interleaved, one
            submap of each in turn, with global pose ids: :mod:`~linear_slam_ros.joiner.robots`).
        seqs: each map's sequence number in its robot's stream (its file's number in a folder).
        robots: each map's robot (``""``: a single robot).
        path: the first source (a ``.g2o`` file's edges are written back with ``--format g2o``).
        needs_joiner: the maps skip numbers or come from several robots: they are joined through the
            node's state machine (:func:`~linear_slam_ros.evaluation.runner.run_joiner`), with islands.
    """

    dataset: Dataset
    seqs: tuple[int, ...]
    robots: tuple[str, ...]
    path: Path
    needs_joiner: bool


def read_sources(paths: Sequence[Path], kind: str | None, robots: bool) -> Sources:
    """Read the dataset arguments: one dataset, or with ``robots`` one per robot (``robot0``, ``robot1``, ...).

    Raises:
        ConfigError: several datasets without ``robots``, or robots of different dimensions.
        LinearSlamError: a dataset cannot be read.
    """
    if len(paths) > 1 and not robots:
        raise ConfigError(f"{len(paths)} datasets given: joining several needs --robots (each one robot's stream)")
    sets = [read_source(p, kind=kind) for p in paths]
    if not robots:
        d = sets[0]
        return Sources(d, d.seqs, ("",) * len(d.maps), paths[0], bool(d.numbers))
    if len({d.dim for d in sets}) > 1:
        raise ConfigError("robots of different dimensions: " + ", ".join(f"{d.name} is {d.dim}D" for d in sets))
    names = [f"robot{k}" for k in range(len(sets))]
    slots = robot_slots(names)
    streams = [[(seq, qualify(m, slots[name]), name) for seq, m in zip(d.seqs, d.maps, strict=True)]
               for name, d in zip(names, sets, strict=True)]
    order = [item for turn in itertools.zip_longest(*streams) for item in turn if item is not None]
    kinds = [d.kind for d in sets if d.kind.has_features] or [sets[0].kind]
    dataset = Dataset("+".join(d.name for d in sets), kinds[0], tuple(m for _, m, _ in order))
    return Sources(dataset, tuple(s for s, _, _ in order), tuple(r for _, _, r in order), paths[0], True)


def join_dataset(dataset: Dataset, method: JoinMethod) -> JoinRun:
    """Join a dataset's local maps (as they are) with a progress bar on long runs."""
    n_steps = len(dataset.maps) if get_strategy(method).run_step == PER_SUBMAP else len(dataset.maps) - 1
    with _progress(n_steps, f"{method.value} {dataset.name}") as bar:
        return run_join(dataset.maps, method, progress=bar.update)


def report_for(run: JoinRun, dataset: Dataset, chi2_value: float) -> dict[str, object]:
    """Return the report dictionary of a joining run."""
    return {
        "dataset": dataset.name,
        "kind": dataset.kind.value,
        "method": run.method.value,
        "n_submaps": run.n_submaps,
        "state_dim": run.result.state_dim,
        "seconds": run.seconds,
        **latency_summary(run.step_seconds),
        "latency_unit": run.step_unit,
        "peak_rss_mb": peak_rss_mb(),
        "chi2": chi2_value,
        "info_nnz": run.result.info_nnz(),
    }


def cmd_join(args: argparse.Namespace) -> int:
    """Join a dataset and write poses, features and report.json."""
    return _join_command(args, refine_too=bool(args.refine))


def cmd_refine(args: argparse.Namespace) -> int:
    """Join, then refine by Gauss-Newton (Nonlinear LS), and write the refined result."""
    return _join_command(args, refine_too=True)


def _join_command(args: argparse.Namespace, refine_too: bool) -> int:
    config = JoinerConfig.from_mapping(
        {"mode": args.method, "map_type": args.map_type, "gate_probability": args.gate_probability,
         "hold_closures": args.hold_closures}, online=False,
    )
    gate = config.gate_probability or None  # a gate or holding the strategy cannot apply was refused above
    strategy_type: Any = type(get_strategy(config.mode, config.map_type))
    method_name = f"method {config.mode.value!r} with map type {config.map_type.value!r}"
    if refine_too and args.initial_state is not None:
        raise ConfigError(
            "refine / join --refine with --initial-state: a saved state holds its joined map, not the local maps it "
            "was joined from, so their measurements cannot be refined (refine the whole stream instead)"
        )
    gated: list[dict[str, object]] = []
    reinitialised: list[Reinitialisation] = []
    joined_at: list[int | None] = []
    before = None
    formats = list(args.format)
    _check_formats(formats, config.map_type)
    sources = read_sources(args.dataset, args.kind, args.robots)
    dataset = sources.dataset
    _check_formats(formats, config.map_type, dataset)
    if sources.needs_joiner and config.map_type is MapType.AS_IS and strategy_type.seed is FoldStrategy.seed:
        why = "come from several robots" if args.robots else "skip numbers (lost submaps)"
        raise ConfigError(
            f"{dataset.name}: the local maps {why} and are joined as islands, which {method_name} cannot do "
            "(use 'online-dc' or 'sequential')"
        )
    pose_formats = [f for f in formats if f != "g2o"]
    run: JoinRun | None = None
    origin = dataset.maps[0].frame_id  # results are written in the frame of the session's first pose
    islands: dict[str, object] = {"n_islands": 1, "island_sizes": [len(dataset.maps)]}
    held: tuple[HeldClosure, ...] = ()  # forward loop closures still held at the end (their pose never reached)
    numbers: list[tuple[str, int]] = []  # each map's (robot, sequence number) as offered to the joiner
    fused: list[LocalMap] = []  # what the joins fused (with the gate: what --refine refines, as the node's refiner)
    holding = config.hold_closures or gate is not None
    if args.initial_state is not None or args.save_state is not None or holding or sources.needs_joiner:
        initial = read_snapshot(args.initial_state) if args.initial_state is not None else None
        before = initial.state.relabels if initial is not None else None
        with _progress(len(dataset.maps), f"{config.mode.value} {dataset.name}") as bar:
            run, saved = run_joiner(dataset.maps, config.mode, config.map_type, initial, bar.update, gate, gated,
                                    sources.seqs if sources.needs_joiner else None, sources.robots, reinitialised,
                                    joined_at, config.hold_closures or None, fused, numbers)
        origin = saved.state.first_pose_id if saved.state.first_pose_id is not None else origin
        summary = saved.state.islands
        held = saved.state.held
        islands = {"n_islands": len(summary), "island_sizes": sorted((i.n_submaps for i in summary), reverse=True)}
        if len(summary) > 1:
            logger.warning("%s: the submaps form %d islands of %s submaps; the results hold the main island (the "
                           "first submap's): %d submaps", dataset.name, len(summary), islands["island_sizes"],
                           summary[0].n_submaps)
        if args.save_state is not None:
            write_snapshot(args.save_state, saved)
            logger.info("%s: joiner state written to %s", dataset.name, args.save_state)
    if config.map_type is MapType.FEATURE_ONLY:
        return _join_feature_only(args, dataset, refine_too, run)
    method = config.mode
    if run is None:
        run = join_dataset(dataset, method)
    # each map under the feature ids it was joined with (features the gate re-initialised renamed)
    seen = as_joined(dataset.maps, reinitialised, joined_at, before) if joined_at else list(dataset.maps)
    if held:  # closures whose pose was never reached were never joined: the objective leaves them out
        seen = without_held(seen, numbers, held)
    covered = maps_within(run.result, seen) if islands["n_islands"] != 1 else seen
    extra_keys: dict[str, object] = {}
    if gate is not None:
        extra_keys.update({"gate_probability": gate, "gated": gated, "n_gated": len(gated),
                          "reinitialised": [r.as_dict() for r in reinitialised], "n_reinitialised": len(reinitialised)})
    if holding:
        extra_keys.update({"hold_closures": True, "n_held": len(held)})
    extra_keys["chi2_submaps"] = len(covered)  # the local maps the χ² is over (not those of an --initial-state)
    if not refine_too:
        in_origin = write_result(args.out, run.result, origin, pose_formats)
        if "g2o" in formats:
            _write_g2o(args.out, sources.path, dataset, in_origin)
        report = {**report_for(run, dataset, chi2(in_origin, covered)), **islands, **extra_keys}
        write_report(args.out, report)
        logger.info(
            "%s: joined %d local maps with %s in %.3f s, chi2 %.3f", dataset.name, run.n_submaps, method.value,
            run.seconds, report["chi2"],
        )
        return 0
    # with the gate, the objective of what was joined (the gate's splits left out), as the node's refiner has it
    measurements = covered
    if gate is not None:  # with islands, the main island's part of it (the original maps had the splits back in)
        measurements = fused if islands["n_islands"] == 1 else maps_within(run.result, fused)
    t0 = time.perf_counter()
    if getattr(args, "refine", False):  # join --refine: the node's refiner, run over the whole stream to convergence
        from linear_slam_ros.evaluation.nonlinear import RefineResult
        from linear_slam_ros.refinement.online import RefinerConfig, refine_offline

        done = refine_offline(measurements, run.result, RefinerConfig(chi2_rtol=1e-13))
        refined = RefineResult(done.map, done.chi2, (done.initial_chi2, done.chi2), done.iterations, done.converged)
    else:
        refined = refine(run.result, measurements)
    seconds_refine = time.perf_counter() - t0
    in_origin = write_result(args.out, refined.map, origin, pose_formats)
    if "g2o" in formats:
        _write_g2o(args.out, sources.path, dataset, in_origin)
    report = {**report_for(run, dataset, refined.chi2), **islands, **extra_keys}
    report.update(
        {
            "linear_chi2": refined.chi2_history[0],
            "refine_seconds": seconds_refine,
            "refine_iterations": refined.iterations,
            "refine_converged": refined.converged,
            "info_nnz": refined.map.info_nnz(),
            "state_dim": refined.map.state_dim,
        }
    )
    write_report(args.out, report)
    logger.info("%s: Nonlinear LS chi2 %.3f after %d iterations", dataset.name, refined.chi2, refined.iterations)
    return 0


def _join_feature_only(args: argparse.Namespace, dataset: Dataset, refine_too: bool, run: JoinRun | None) -> int:
    """Feature-only (D-SLAM) joining of a pose-feature dataset: precondition, marginalise, join."""
    if not dataset.kind.has_features:
        logger.error("%s is a pose-only dataset: feature-only joining needs features", dataset.name)
        return 2
    feature_run = run_feature_join(dataset.maps, args.method, refine_too, run)
    report: dict[str, object] = {"dataset": dataset.name, "kind": dataset.kind.value, **feature_run.report}
    write_map(feature_run.refined if feature_run.refined is not None else feature_run.joined, args.out, None)
    write_report(args.out, report)
    logger.info("%s: feature-only %s joined %d maps (%d after preconditioning) in %.3f s, chi2 %.3f",
                dataset.name, args.method, len(dataset.maps), report["n_feature_maps"], report["seconds"], report["chi2"])
    return 0


def cmd_lago(args: argparse.Namespace) -> int:
    """Estimate a 2D pose graph by LAGO (g2o file or pose-only dataset); optionally refine.

    The poses written are the refined ones with ``--refine``, LAGO's otherwise.
    """
    source = Path(args.graph)
    graph = read_g2o(source) if source.suffix == ".g2o" else graph_from_local_maps(list(read_source(source).maps))
    result = lago(graph, args.anchor)
    edges = edge_maps(graph)
    report: dict[str, object] = {
        "graph": source.name,
        "n_poses": int(graph.pose_ids.size),
        "n_edges": graph.n_edges,
        "seconds": result.seconds,
        "chi2": MapObjective.build(result.map, edges).chi2(result.map.x),
        "chords_corrected": int((result.chord_corrections != 0).sum()),
        "edges_with_coupled_information": result.n_coupled_edges,
    }
    out_map = result.map
    if args.refine:
        t0 = time.perf_counter()
        refined = gauss_newton(result.map, edges)
        report.update({"nls_chi2": refined.chi2, "nls_iterations": refined.iterations, "nls_seconds": time.perf_counter() - t0})
        out_map = refined.map
    report["poses_written"] = "nls" if args.refine else "lago"
    args.out.mkdir(parents=True, exist_ok=True)
    if "reference" in args.format:
        write_poses(args.out / "poses.txt", out_map, out_map.frame_id)
    if "tum" in args.format:
        write_tum_poses(args.out / "poses.tum", out_map, out_map.frame_id)
    if "g2o" in args.format:
        write_g2o(args.out / "graph.g2o", graph, pose_values(out_map))
    write_report(args.out, report)
    logger.info("%s: LAGO chi2 %.3f in %.3f s", source.name, report["chi2"], result.seconds)
    return 0


def cmd_unpack(args: argparse.Namespace) -> int:
    """Unpack every ``*.tar.xz`` dataset of a folder into the cache (idempotent)."""
    archives = sorted(Path(args.datasets_dir).glob("*.tar.xz"))
    if not archives:
        logger.error("no *.tar.xz datasets in %s", args.datasets_dir)
        return 2
    for archive in archives:
        logger.info("%s -> %s", archive.name, resolve_dataset_dir(archive))
    return 0


def cmd_benchmark(args: argparse.Namespace) -> int:
    """Run the benchmark over every dataset (see :mod:`linear_slam_ros.evaluation.benchmark`)."""
    run_benchmark(args.datasets_dir, args.out, methods=args.methods, only=args.only)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``python -m linear_slam_ros``."""
    defaults = HelpWithDefaults
    parser = argparse.ArgumentParser(prog="python -m linear_slam_ros", description=__doc__, formatter_class=defaults)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    def output_format(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--format", nargs="+", choices=FORMATS, default=["reference"],
            help="result files: reference = poses.txt (k x y phi / k x y z alpha beta gamma) and features.txt; "
                 "tum = poses.tum (timestamp tx ty tz qx qy qz qw, the timestamp is the pose id); "
                 "g2o = graph.g2o (the input's pose graph with the result as vertex estimates; pose-only input)",
        )

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("dataset", type=Path, nargs="+",
                       help="folder of localmap_<i>.txt files (numbers may skip: lost submaps, joined as islands), "
                            "a .tar.xz archive, a bag of local_map or pose_graph messages (e.g. bags/vicpark200), or a "
                            ".g2o pose graph (2D or 3D: joined as pose-only local maps, one per pose that edges "
                            "leave); several with --robots")
        p.add_argument("--robots", action="store_true",
                       help="each dataset is one robot's stream (robot k: pose ids k * 2^32 + id, feature ids "
                            "shared), joined into one map as if published concurrently")
        p.add_argument("--method", choices=[m.value for m in JoinMethod], default=JoinMethod.DC.value, help="joining method")
        p.add_argument("--kind", choices=[k.value for k in MapKind], default=None, help="override the detected map kind")
        p.add_argument("--out", type=Path, required=True, help="output folder")
        output_format(p)
        p.add_argument(
            "--map-type", choices=[t.value for t in MapType], default=MapType.AS_IS.value,
            help="feature-only: marginalise poses and join feature-only (D-SLAM) maps in feature-defined frames",
        )
        p.add_argument("--initial-state", type=Path, default=None,
                       help="continue from a joiner state file (the node's ~/save_map or --save-state); "
                            "the dataset's maps get the sequence numbers that follow it")
        p.add_argument("--gate-probability", type=float, default=0.0,
                       help="χ² gate before each join at this probability (online-dc, sequential); 0: off. "
                            "report.json then lists the gate decisions (gated, n_gated)")
        p.add_argument("--hold-closures", action="store_true",
                       help="hold forward loop closures until the chain reaches their pose (always with the gate); "
                            "report.json then gives n_held, the closures whose pose was never reached")
        p.add_argument("--save-state", type=Path, default=None,
                       help="write the joiner's exact state here (for --initial-state, or the node's initial_map)")

    p_join = sub.add_parser("join", help="join a dataset's local maps", formatter_class=defaults)
    common(p_join)
    p_join.add_argument("--refine", action="store_true",
                        help="then refine by Gauss-Newton with the node's refiner (linear_slam_ros.refinement), "
                             "warm-started from the linear result; writes the refined map (as the refine command)")
    p_join.set_defaults(func=cmd_join)
    p_ref = sub.add_parser("refine", help="join, then refine by Gauss-Newton (Nonlinear LS)", formatter_class=defaults)
    common(p_ref)
    p_ref.set_defaults(func=cmd_refine)
    p_lago = sub.add_parser("lago", help="closed-form estimate of a 2D pose graph (LAGO)", formatter_class=defaults)
    p_lago.add_argument("graph", type=Path, help="a 2D .g2o file (VERTEX_SE2/EDGE_SE2) or a 2D pose-only dataset or bag")
    p_lago.add_argument("--out", type=Path, required=True, help="output folder")
    p_lago.add_argument("--anchor", type=int, default=None, help="pose held at the origin (None: the smallest id)")
    p_lago.add_argument("--refine", action="store_true",
                        help="also run Gauss-Newton from the LAGO estimate and write the refined poses")
    output_format(p_lago)
    p_lago.set_defaults(func=cmd_lago)
    p_unpack = sub.add_parser("unpack", help="unpack every dataset archive into .cache/datasets", formatter_class=defaults)
    p_unpack.add_argument("datasets_dir", type=Path, nargs="?", default=Path("../shared/datasets"),
                          help="folder of *.tar.xz archives")
    p_unpack.set_defaults(func=cmd_unpack)
    p_bench = sub.add_parser("benchmark", help="every dataset with every method; figures to --out", formatter_class=defaults)
    p_bench.add_argument("--datasets-dir", type=Path, default=Path("../shared/datasets"), help="folder of *.tar.xz archives")
    p_bench.add_argument("--out", type=Path, default=Path("out/benchmark"), help="output folder")
    p_bench.add_argument("--methods", nargs="+", choices=[m.value for m in JoinMethod], default=[m.value for m in JoinMethod],
                         help="joining methods")
    p_bench.add_argument("--only", nargs="+", default=None, help="dataset names to run (default: all)")
    p_bench.set_defaults(func=cmd_benchmark)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code (2 for bad input)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args))
    except (LinearSlamError, OSError) as exc:  # bad input or an unwritable output: one line, no traceback
        logger.error("%s", " ".join(str(exc).split()))
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
