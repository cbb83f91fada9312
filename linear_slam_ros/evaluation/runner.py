"""Timed joining runs over a sequence of local maps, through the strategy registry (CLI and benchmark)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import scipy.sparse as sp

from linear_slam_ros.core.errors import InvalidMapError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.core.runtime import blas_threads, tune_allocator
from linear_slam_ros.core.timing import latency_summary, peak_rss_mb
from linear_slam_ros.feature_only.conversion import to_feature_only
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.feature_only.precondition import precondition
from linear_slam_ros.feature_only.refine import feature_residuals, feature_rmse, refine_features
from linear_slam_ros.joiner.joiner import FIRST_SEQ, Joiner, SavedJoiner, global_result
from linear_slam_ros.joiner.registry import get_strategy
from linear_slam_ros.joiner.strategy import PER_SUBMAP, JoinMethod, MapType
from linear_slam_ros.joining.reinit import Reinitialisation


@dataclass(frozen=True)
class JoinRun:
    """A timed joining run.

    Attributes:
        method: the method used.
        result: the joined map (pose maps: in the frame of the last end pose; feature-only
            maps: in their feature frame).
        seconds: wall time of the joining only (no reading, no output), s.
        step_seconds: per-step wall times, s: one per submap for streaming strategies (for
            ``online-dc`` the final merge is added to the last step), one per pairwise join for
            batch ones (one per level of the tree for pose-map divide and conquer, whose joins of a level are done together).
        n_submaps: number of local maps joined.
        step_unit: what one step is: ``"per submap"``, ``"per pairwise join"`` or ``"per tree level"``.
        cpu_seconds: CPU time of the process over the same span, s (every thread's: the reference
            program's ``Used Time`` is CPU time, so a comparison with it uses this one).
    """

    method: JoinMethod
    result: Any
    seconds: float
    step_seconds: tuple[float, ...] = field(repr=False)
    n_submaps: int
    step_unit: str
    cpu_seconds: float = math.nan


def run_join(
    maps: Sequence[LocalMap],
    method: JoinMethod | str,
    map_type: MapType | str = MapType.AS_IS,
    progress: Callable[[int], None] | None = None,
) -> JoinRun:
    """Join ``maps`` with the strategy registered for ``(method, map_type)``, timing each step.

    The process is tuned as the strategy asks (BLAS threads, allocator; :mod:`~linear_slam_ros.core.runtime`).

    Args:
        maps: local maps in order.
        method: a :class:`JoinMethod` or its value.
        map_type: a :class:`MapType` or its value.
        progress: called with the number of submaps (or joins) just completed.

    Raises:
        InvalidMapError: ``maps`` is empty.
    """
    strategy = get_strategy(method, map_type)
    if not maps:
        raise InvalidMapError("no local maps to join")
    tune_allocator(strategy.mmap_threshold)
    with blas_threads(strategy.blas_threads):
        start, cpu_start = time.perf_counter(), time.process_time()
        result, steps = strategy.run(maps, progress)
        seconds, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    return JoinRun(strategy.method, result, seconds, tuple(steps), len(maps), strategy.run_step, cpu)


def run_joiner(
    maps: Sequence[LocalMap],
    method: JoinMethod | str,
    map_type: MapType | str = MapType.AS_IS,
    initial: SavedJoiner | None = None,
    progress: Callable[[int], None] | None = None,
    gate_probability: float | None = None,
    gated: list[dict[str, Any]] | None = None,
    seqs: Sequence[int] | None = None,
    robots: Sequence[str] | None = None,
    reinitialised: list[Reinitialisation] | None = None,
    joined_at: list[int | None] | None = None,
    hold_closures: bool | None = None,
    fused: list[LocalMap] | None = None,
    numbers: list[tuple[str, int]] | None = None,
) -> tuple[JoinRun, SavedJoiner]:
    """Join ``maps`` through the node's state machine (:class:`Joiner`), from a saved state or from scratch.

    The maps get the sequence numbers that follow the saved state's (1, 2, ... from scratch), so
    the saved result can be continued by the node or by another run; ``seqs`` gives each map's
    number in its robot's stream instead (``robots``: each map's robot, ``""`` for one robot; named robots
    first appear in their slot order, :func:`~linear_slam_ros.joiner.robots.qualify`, which the state records;
    after a saved state, each robot's first map takes the number that follows the state's and
    the others keep their distance to it); numbers that are skipped are lost submaps, and the
    streams are complete: every gap is skipped at the end (:meth:`Joiner.flush`) and the maps
    after it start islands. ``numbers`` receives each map's ``(robot, sequence number)`` as
    offered. Timing is per submap. With ``gate_probability`` the χ² gate runs before each join; its decisions are appended to
    ``gated`` (:meth:`GateRecord.as_dict`) and are not errors, and the features it re-initialised
    to ``reinitialised``; ``joined_at`` receives each map's place in the join order (``None``: not
    joined), to score the result with :func:`~linear_slam_ros.joining.reinit.as_joined`.
    ``hold_closures``: forward loop closures held until the chain reaches their pose
    (:class:`Joiner`; ``None``: while the gate is on). ``fused`` receives every measurement the
    joins fused, as measured (:attr:`~linear_slam_ros.joiner.joiner.SubmapStep.fused`): the joined
    map's objective, what the node's refiner is given.

    Returns:
        The timed run and the joiner's final saved value (for ``--save-state``).

    Raises:
        InvalidMapError: ``maps`` is empty, or a map was rejected (the message lists the reasons).
        ConfigError: ``initial`` was joined with another method or map type.
    """
    if not maps:
        raise InvalidMapError("no local maps to join")
    named = tuple(dict.fromkeys(r for r in robots if r)) if robots else ()  # in slot order (robots' first maps come in it)
    joiner = Joiner(JoinMethod(method), MapType(map_type), gate_probability=gate_probability, hold_closures=hold_closures,
                    robots=named)
    reasons: list[str] = []
    joiner.on_reject = lambda reason, message: None if reason in ("gated", "gap") else reasons.append(message)
    if initial is not None:
        joiner.restore(initial)
    order: dict[tuple[str, int], int] = {}
    joiner.on_join = lambda robot, seq: order.__setitem__((robot, seq), joiner.state.n_joined)
    if fused is not None:
        joiner.on_fused = lambda robot, seq, maps: fused.extend(maps)
    who = list(robots) if robots is not None else [""] * len(maps)
    if seqs is None:
        first_seq = joiner.state.next_seq if joiner.state.next_seq is not None else 1
        offered = [(robot, first_seq + i) for i, robot in enumerate(who)]
    elif initial is None:
        offered = list(zip(who, seqs, strict=True))
    else:  # each robot's first map takes the number after the saved state's; the gaps stay
        first = {robot: min(s for r, s in zip(who, seqs, strict=True) if r == robot) for robot in set(who)}
        after = {robot: joiner.state.stream(robot).next_seq or FIRST_SEQ for robot in set(who)}
        offered = [(robot, after[robot] + seq - first[robot]) for robot, seq in zip(who, seqs, strict=True)]
    if numbers is not None:
        numbers.extend(offered)
    strategy = joiner.state.strategy
    tune_allocator(strategy.mmap_threshold)
    with blas_threads(strategy.blas_threads):
        start, cpu_start = time.perf_counter(), time.process_time()
        for m, (robot, seq) in zip(maps, offered, strict=True):
            joiner.offer(m, seq, robot)
            if progress is not None:
                progress(1)
        joiner.flush()
        result = global_result(joiner.state)
        seconds, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    if reasons:
        raise InvalidMapError(f"{len(reasons)} local map(s) rejected: " + "; ".join(reasons[:3]))
    if result is None:
        raise InvalidMapError(f"no joined map: the {len(maps)} local maps gave none")
    run = JoinRun(strategy.method, result, seconds, tuple(joiner.join_seconds), len(maps), PER_SUBMAP, cpu)
    if gated is not None:
        gated.extend(g.as_dict() for g in joiner.gated)
    if reinitialised is not None:
        reinitialised.extend(joiner.reinitialised)
    if joined_at is not None:
        joined_at.extend(order.get(number) for number in offered)
    return run, joiner.save()


@dataclass(frozen=True)
class FeatureRun:
    """A timed feature-only joining run of pose-feature local maps (CLI and benchmark).

    Attributes:
        joined: the linear result.
        refined: the feature-only Nonlinear LS from ``joined`` (I-DMJ's optimum), if asked.
        report: figures: seconds (joining only), latency, χ² (of the refined map when there is
            one, with ``linear_chi2``), RMSE of the linear result against the refined one.
    """

    joined: FeatureMap
    refined: FeatureMap | None
    report: dict[str, Any]


def run_feature_join(
    maps: Sequence[LocalMap], method: JoinMethod | str, refine_too: bool = False, run: JoinRun | None = None
) -> FeatureRun:
    """Precondition, marginalise and join pose-feature maps as feature-only maps, timed, with figures.

    ``online-dc`` times each submap; ``sequential`` and ``dc`` convert every group first and
    time each pairwise join. ``run``: a feature-only run of ``maps`` already made (e.g. by
    :func:`run_joiner` from a saved state), to report on instead.
    """
    if run is None:
        run = run_join(maps, method, MapType.FEATURE_ONLY)
    joined: FeatureMap = run.result
    feature_maps = [to_feature_only(g) for g in precondition(maps)]  # for the objective (not timed)
    residual, _ = feature_residuals(joined, joined.x, feature_maps, jacobian=False)
    weight = sp.block_diag([sp.csr_matrix(m.info) for m in feature_maps], format="csr")
    report: dict[str, Any] = {
        "map_type": MapType.FEATURE_ONLY.value,
        "method": run.method.value,
        "n_submaps": len(maps),
        "n_feature_maps": len(feature_maps),
        "state_dim": joined.state_dim,
        "seconds": run.seconds,
        **latency_summary(run.step_seconds),
        "latency_unit": run.step_unit,
        "peak_rss_mb": peak_rss_mb(),
        "chi2": float(residual @ (weight @ residual)),
        "info_nnz": int(sp.csr_matrix(joined.info).count_nonzero()),
        "frame_features": list(joined.frame_ids),
    }
    refined = None
    if refine_too:
        nls = refine_features(joined, feature_maps)
        refined = nls.map
        report.update({"linear_chi2": report["chi2"], "chi2": nls.chi2, "refine_iterations": nls.iterations,
                       "rmse_feature_linear_vs_nls": feature_rmse(joined, refined)})
    return FeatureRun(joined, refined, report)
