"""The joiner's state machine without ROS: sequencing, joining, rejection counts, outputs.

The node feeds it decoded submaps and asks it for outputs; everything here is testable without
rclpy. The global map is one immutable value (:class:`JoinerState`): a submap either produces a
new state or is rejected with a reason, leaving the old one as it was.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import ConfigError, FrameError, InvalidMapError, LinearSlamError
from linear_slam_ros.core.frames import end_frame_fault, estimate_in_frame
from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.core.timing import latency
from linear_slam_ros.joiner.config import OutputFrame, check_strategy_can
from linear_slam_ros.joiner.islands import (
    MAIN_ISLAND,
    Chain,
    IslandCache,
    IslandSummary,
    Stream,
    collapse_frozen,
    island_result,
    link_islands,
    route,
    summarize,
)
from linear_slam_ros.joiner.registry import AnyStrategy, get_strategy
from linear_slam_ros.joiner.strategy import JoinMethod, MapType, PoseEstimate
from linear_slam_ros.joining.background import MergeWorker
from linear_slam_ros.joining.chain import compose
from linear_slam_ros.joining.gate import GateResult, VarianceFactor, gate_submap
from linear_slam_ros.joining.hold import HeldClosure, split_forward
from linear_slam_ros.joining.reinit import Reinitialisation, Relabels

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class JoinerState:
    """The whole joiner state: one value, saved and restored as a unit.

    Attributes:
        method: joining method (with ``map_type``, the registry key of the strategy).
        map_type: ``as-is`` or ``feature-only``.
        chains: the chains of submaps (:class:`~linear_slam_ros.joiner.islands.Chain`), oldest
            first; ``chains[0]`` holds the first submap and its island is the main island.
        streams: the sequence position of each robot's stream (the single robot's is ``""``).
        n_joined: submaps joined, in all chains.
        defer_above: the strategy's deferral setting for new chains (see :meth:`JoinStrategy.defer`).
        dim: 2 or 3, set by the first submap (``None`` before).
        variance: the χ² gate's variance of unit weight of the stream (what the gate let through so
            far; :class:`~linear_slam_ros.joining.gate.VarianceFactor`): the gate's thresholds are
            scaled by it. One for the whole map, whichever robot a submap comes from.
        relabels: the features the gate re-initialised (their front-end ids now name new
            landmarks) and those it suspects (:class:`~linear_slam_ros.joining.reinit.Relabels`).
        hold_closures: forward loop closures are held back until the chain reaches their pose
            (:func:`hold_step`; the joiner sets it, with the gate on by default).
        held: the forward loop closures held back, in arrival order
            (:class:`~linear_slam_ros.joining.hold.HeldClosure`).
        robots: the robot namespaces in slot order, whose pose ids the map holds
            (:func:`~linear_slam_ros.joiner.robots.qualify`: robot k's pose i is k · 2³² + i); a
            restore under a list that gives a robot another slot is refused (:meth:`Joiner.check_restorable`).
            ``()``: one robot, or not recorded (a state file of format 7 or older).
    """

    method: JoinMethod
    map_type: MapType
    chains: tuple[Chain, ...] = ()
    streams: tuple[Stream, ...] = ()
    n_joined: int = 0
    defer_above: int | None = None
    dim: int | None = None
    variance: VarianceFactor = field(default_factory=VarianceFactor)
    relabels: Relabels = field(default_factory=Relabels)
    hold_closures: bool = False
    held: tuple[HeldClosure, ...] = ()
    robots: tuple[str, ...] = ()

    @property
    def strategy(self) -> AnyStrategy:
        """The joining strategy of this state."""
        return get_strategy(self.method, self.map_type)

    @property
    def joined(self) -> Any:
        """The strategy state of the first chain (an empty one before the first submap)."""
        if self.chains:
            return self.chains[0].joined
        strategy = self.strategy
        return strategy.defer(strategy.empty(), self.defer_above)

    @property
    def first_pose_id(self) -> int | None:
        """Frame pose of the first joined submap (``map_frame`` of the outputs)."""
        return self.chains[0].first_pose_id if self.chains else None

    def stream(self, robot: str = "") -> Stream:
        """Return the sequence position of ``robot``'s stream."""
        for s in self.streams:
            if s.robot == robot:
                return s
        return Stream(robot)

    @property
    def next_seq(self) -> int | None:
        """Sequence number expected next from the single robot (``None`` before its first submap)."""
        return self.stream().next_seq

    @property
    def last_seq(self) -> int | None:
        """Sequence number of the single robot's last joined submap."""
        return self.stream().last_seq

    def with_stream(self, robot: str, **changes: Any) -> JoinerState:
        """Return the state with ``robot``'s stream position changed."""
        stream = replace(self.stream(robot), **changes)
        others = tuple(s for s in self.streams if s.robot != robot)
        return replace(self, streams=tuple(sorted((*others, stream), key=lambda s: s.robot)))

    def in_main_island(self, robot: str = "") -> bool:
        """Whether ``robot``'s newest submap is in the main island (``True`` before any)."""
        chain = self.stream(robot).chain
        return chain < 0 or self.chains[chain].island == MAIN_ISLAND

    @property
    def islands(self) -> list[IslandSummary]:
        """The islands: the main one first, then the others, largest first."""
        return summarize(self.chains)


def new_state(method: JoinMethod, map_type: MapType = MapType.AS_IS) -> JoinerState:
    """Return the empty state of a joiner."""
    return JoinerState(method, map_type)


CACHE = IslandCache()
"""Results and key sets of chains and islands (a cache of functions of state values)."""


def join_step(state: JoinerState, submap: LocalMap, seq: int, robot: str = "") -> JoinerState:
    """Join one submap: a pure function of ``(state, submap)``.

    The submap continues the chain whose end pose it starts from (its robot's first). Else, when
    a gap in its robot's sequence numbers precedes it (a lost submap, a restart, a robot's first
    submap), it starts a new chain in a new island (pose maps only); without a gap it is rejected:
    a submap that should continue the map and does not is an error of its sender. Islands it
    links are relabelled (:func:`~linear_slam_ros.joiner.islands.link_islands`).

    Raises:
        LinearSlamError: the submap cannot be joined (the state is unchanged).
    """
    strategy = state.strategy
    if state.dim is not None and submap.dim != state.dim:  # checked first: a new island must not differ either
        raise InvalidMapError(f"submap {submap.name!r} is {submap.dim}D, the global map is {state.dim}D")
    stream = state.stream(robot)
    chains = list(state.chains)
    stamp = state.n_joined + 1
    end = submap.end_id
    target = -1
    error: LinearSlamError | None = None
    islands = strategy.result_type is LocalMap and strategy.online  # pose maps chain; feature-only maps share features
    candidates = route(chains, submap, robot, stream.chain, strict=False) if islands else list(range(len(chains)))[:1]
    for i in candidates:
        c = chains[i]
        try:
            joined = strategy.step(c.joined, submap)
        except FrameError as exc:
            error = exc
            continue
        chains[i] = Chain(joined, c.robot, c.first_pose_id, end if end is not None else c.end_id, c.n_joined + 1,
                          c.island, stamp)
        target = i
        break
    if target < 0:
        after_gap = stream.last_seq is None or seq > stream.last_seq + 1
        if chains and (not islands or not after_gap):
            why = (
                f"{strategy.map_type.value!r} {strategy.method.value!r} maps cannot start islands" if not islands
                else f"it follows seq {stream.last_seq} without a gap, so it should continue the map (only a submap "
                "after a gap in its robot's sequence numbers may start an island)"
            )
            raise FrameError(f"{error}; {why}" if error is not None else
                             f"submap {submap.name!r} (frame pose {submap.frame_id}) continues no part of the map: {why}")
        joined = strategy.step(strategy.defer(strategy.empty(), state.defer_above), submap)
        target = len(chains)
        chains.append(Chain(joined, robot, submap.frame_id, end, 1, target, stamp))
        if target:
            logger.warning(
                "submap seq %d (%r, robot %r) starts island %d: its frame pose %d is not the end of any part of the "
                "map (a submap was lost, or the stream restarted); it joins the others when they share a pose or "
                "enough features", seq, submap.name, robot, target, submap.frame_id,
            )
    chains, streams, target = _linked(state, chains, target, submap, robot) if islands else (chains, state.streams, target)
    joined_state = replace(state, chains=tuple(chains), streams=streams, n_joined=stamp, dim=submap.dim)
    return joined_state.with_stream(robot, next_seq=seq + 1, last_seq=seq, chain=target)


def _linked(
    state: JoinerState, chains: list[Chain], target: int, submap: LocalMap, robot: str
) -> tuple[list[Chain], tuple[Stream, ...], int]:
    """Link the islands ``submap`` (just joined into chain ``target`` of ``chains``) connects, and collapse frozen chains.

    Returns:
        The chains, the streams (their chain indices moved with the collapse) and ``target``'s new index.
    """
    streams = state.streams
    if len(chains) < 2:
        return chains, streams, target
    strategy = state.strategy
    labels = [c.island for c in chains]
    def holds(joined: Any, keys: list[int]) -> bool | None:
        return strategy.holds(joined, np.asarray(keys, dtype=np.int64))

    chains = link_islands(chains, target, submap, strategy.result, CACHE, holds)
    if target == len(state.chains) or labels != [c.island for c in chains]:  # which chains are frozen changed
        active = {s.chain for s in streams if s.robot != robot and s.chain >= 0} | {target}
        def seed(joined: Any, n_submaps: int) -> Any:  # deferring as every other chain does (Joiner._scheduled)
            return strategy.defer(strategy.seed(joined, n_submaps), state.defer_above)

        chains, where = collapse_frozen(chains, active, seed, strategy.result, CACHE)
        target = where[target]
        streams = tuple(replace(s, chain=where[s.chain]) if s.chain >= 0 else s for s in streams)
    return chains, streams, target


def hold_step(state: JoinerState, submap: LocalMap, seq: int, robot: str = "") -> tuple[JoinerState, LocalMap | None]:
    """Hold a submap's forward loop closures back (:mod:`~linear_slam_ros.joining.hold`): a pure function of ``(state, submap)``.

    With ``state.hold_closures`` off, returns ``(state, submap)``. Else the uncoupled pose variables
    of ``submap`` that no chain holds (and that are not its end pose) go to ``state.held`` (a pose
    of another island's chain is not held: the closure links the islands now); strategies that
    cannot tell cheaply which variables the map holds
    (:meth:`~linear_slam_ros.joiner.strategy.JoinStrategy.holds` ``None``) hold nothing.

    Returns:
        The state with the new closures held, and what is left of the submap to join (``None``: nothing).
    """
    if not state.hold_closures:
        return state, submap
    strategy = state.strategy
    rest, held = split_forward(
        submap, lambda key: any(strategy.holds(c.joined, np.array([key], dtype=np.int64)) is not False for c in state.chains),
        seq, robot,
    )
    return (replace(state, held=state.held + held) if held else state), rest


def due_closures(state: JoinerState, robot: str = "") -> tuple[JoinerState, tuple[HeldClosure, ...]]:
    """Take the held closures whose pose is the end of ``robot``'s chain (just reached) off ``state.held``."""
    chain = state.stream(robot).chain
    end = state.chains[chain].end_id if chain >= 0 else None
    due = tuple(h for h in state.held if h.target == end)
    if not due:
        return state, ()
    return replace(state, held=tuple(h for h in state.held if h.target != end)), due


def join_held(state: JoinerState, closure: LocalMap, robot: str = "") -> JoinerState:
    """Join a held closure (or what the gate left of it) into ``robot``'s chain, which ends at its frame pose.

    A pure function of ``(state, closure)``; no sequence number is used and ``n_joined`` (submaps)
    does not change. A closure from a pose of another island links the two, as a submap does
    (:func:`~linear_slam_ros.joiner.islands.link_islands`).

    Raises:
        FrameError: the chain does not end at the closure's frame pose.
    """
    index = state.stream(robot).chain
    chain = state.chains[index] if index >= 0 else None
    if chain is None or chain.end_id != closure.frame_id:
        raise FrameError(
            f"held closure {closure.name!r} is in the frame of pose {closure.frame_id}, not the end of the chain of "
            f"robot {robot!r} (pose {None if chain is None else chain.end_id})"
        )
    chains = list(state.chains)
    chains[index] = replace(chain, joined=state.strategy.step(chain.joined, closure))
    if not state.strategy.online or state.strategy.result_type is not LocalMap:
        return replace(state, chains=tuple(chains))
    chains, streams, index = _linked(state, chains, index, closure, robot)  # a closure from another island links it
    return replace(state, chains=tuple(chains), streams=streams).with_stream(robot, chain=index)


def gate_chain(state: JoinerState, submap: LocalMap, robot: str = "") -> Any | None:
    """Return the strategy state of the chain ``submap`` would continue (``None``: it starts an island)."""
    candidates = route(state.chains, submap, robot, state.stream(robot).chain)
    return state.chains[candidates[0]].joined if candidates else None


def gate_step(state: JoinerState, submap: LocalMap, probability: float, robot: str = "") -> GateResult:
    """Test a submap against the state's global map by the χ² gate: a pure function of ``(state, submap)``.

    The NIS of the variables the submap shares with the map (after bringing both into one frame)
    against its quantile at ``probability``, scaled by the state's variance factor
    (``state.variance``); failing variables are split off, or the submap is gated whole
    (:func:`~linear_slam_ros.joining.gate.gate_submap`). The caller adds what the gate let through to
    ``state.variance`` once the submap is joined (:meth:`Joiner.offer` does). Strategies that cannot gate
    (``marginal`` returns ``None``) pass everything. The map compared with is the chain the submap
    continues (:func:`gate_chain`); a submap that starts an island passes. Features the gate
    re-initialised are renamed first, and a suspect feature that fails again is re-initialised
    (``state.relabels``, :mod:`~linear_slam_ros.joining.reinit`); the caller records that with
    :meth:`Relabels.after` once the submap is joined.

    Raises:
        SolverError: a covariance is not positive definite.
        InvalidMapError: the submap holds a feature id reserved for re-initialised landmarks.
    """
    relabels = state.relabels
    submap = relabels.apply(submap)
    joined = gate_chain(state, submap, robot) if state.n_joined else None
    if joined is None:  # the first submap, or the first of an island: nothing to compare with
        return GateResult(probability, 0.0, 0, float("inf"), submap=submap, variance_factor=state.variance.value)
    strategy = state.strategy
    result = gate_submap(
        lambda keys: strategy.marginal(joined, keys), submap, probability, state.variance,
        lambda keys: strategy.holds(joined, keys) is not False,
    )
    return relabels.reinitialise(result, submap)


@dataclass(frozen=True)
class GateRecord:
    """A gate decision that kept something out of the map (for report.json's ``gated``, and the node).

    Attributes:
        submap: sequence number of the submap.
        name: the submap's name.
        variables: ids of the variables split off (all common variables' worst ones when gated whole).
        kinds: their kinds (0 pose, 1 feature).
        nis: NIS of all common variables before the decision; ``dof``: their scalars.
        threshold: the threshold of that NIS (``chi2.ppf(gate_probability, dof)`` times the variance factor).
        rejected: the whole submap was gated (else only ``variables`` were, and the rest joined).
        variable_nis: each of ``variables``' own conditional NIS (when it was split off; gated whole: as first
            tested); a submap is gated when its NIS or one of these passes its threshold.
        variable_thresholds: each one's per-variable threshold (Šidák probability, its size, the variance factor).
        robot: the submap's robot (``""``: the single robot).
    """

    submap: int
    name: str
    variables: tuple[int, ...]
    kinds: tuple[int, ...]
    nis: float
    dof: int
    threshold: float
    rejected: bool
    variable_nis: tuple[float, ...] = ()
    variable_thresholds: tuple[float, ...] = ()
    robot: str = ""

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: ``{"submap", "robot", "name", "variables", "kinds", "nis", "dof", "threshold", "rejected",
        "variable_nis", "variable_thresholds"}``."""
        return {"submap": self.submap, "robot": self.robot, "name": self.name, "variables": list(self.variables),
                "kinds": list(self.kinds), "nis": self.nis, "dof": self.dof, "threshold": self.threshold,
                "rejected": self.rejected, "variable_nis": list(self.variable_nis),
                "variable_thresholds": list(self.variable_thresholds)}

    def describe(self) -> str:
        """One line saying which test failed: ``seq 17: feature 34 NIS 64.4 > 45.4; submap NIS 105.6 <= 154.5
        (60 dof)``, then ``(whole submap)`` when it was gated whole."""
        parts = [
            f"{'pose' if kind == POSE else 'feature'} {var} NIS {nis:.1f} {'>' if nis > limit else '<='} {limit:.1f}"
            for var, kind, nis, limit in zip(self.variables, self.kinds, self.variable_nis, self.variable_thresholds,
                                             strict=False)
        ]
        whole = f"submap NIS {self.nis:.1f} {'>' if self.nis > self.threshold else '<='} {self.threshold:.1f} ({self.dof} dof)"
        who = f"robot {self.robot} seq {self.submap}" if self.robot else f"seq {self.submap}"
        return f"{who}: " + "; ".join([*parts, whole]) + (" (whole submap)" if self.rejected else "")


@dataclass(frozen=True)
class SubmapStep:
    """What :func:`submap_step` did with one submap.

    Attributes:
        state: the state after it.
        joined: whether anything of the submap was joined (else its sequence number is used up,
            and the map is unchanged but for held closures and the gate's relabels).
        result: the gate's decision on the submap (``None``: no gate, or nothing left after holding).
        released: the held closures whose pose the submap reached, in order, each with the gate's
            decision (``None``: no gate); those in :attr:`failed` are not among them.
        failed: held closures that could not be joined, with why (dropped).
        fused: every measurement the step joined, as measured: what was joined of the submap (in
            its frame; without its held closures and what the gate split off; re-initialised
            features renamed), then each released closure that was joined
            (:attr:`HeldClosure.measured`). Their joining objective (eq. 7) is the map's: what a
            refiner of the joined map takes in.
    """

    state: JoinerState
    joined: bool
    result: GateResult | None = None
    released: tuple[tuple[HeldClosure, GateResult | None], ...] = ()
    failed: tuple[tuple[HeldClosure, str], ...] = ()
    fused: tuple[LocalMap, ...] = ()


def _fuse(
    state: JoinerState, submap: LocalMap, probability: float | None, join: Callable[[JoinerState, LocalMap], JoinerState],
    robot: str,
) -> tuple[JoinerState, GateResult | None, LocalMap | None]:
    """Gate ``submap`` (``probability``: the gate's, ``None``/0: none) and ``join`` what passes.

    Returns:
        The new state, the gate's decision (``None``: no gate) and what was joined (``None``:
        nothing; then only the state's relabels change, and the caller uses up the sequence number).
    """
    if not probability:  # features the gate re-initialised earlier (a state saved with the gate on) keep their new ids;
        # the ids of re-initialised landmarks are refused with the gate off too: it may be turned on later
        joined = state.relabels.apply(submap)
        return join(state, joined), None, joined
    result = gate_step(state, submap, probability, robot)
    if result.submap is None:
        return replace(state, relabels=state.relabels.after(result)), result, None
    state = join(state, result.submap)  # what the gate let through is now in the map: it counts in s²
    return (replace(state, variance=state.variance.updated(result), relabels=state.relabels.after(result)), result,
            result.submap)


def submap_step(
    state: JoinerState, submap: LocalMap, seq: int, robot: str = "", probability: float | None = None
) -> SubmapStep:
    """Hold, gate and join one submap, then the held closures it reaches: a pure function of ``(state, submap)``.

    The submap's forward loop closures are held back (:func:`hold_step`, when
    ``state.hold_closures``); the rest goes through the χ² gate at ``probability`` (:func:`gate_step`;
    ``None`` or 0: no gate) and is joined (:func:`join_step`); then the held closures whose pose is
    the new end of the chain are gated and joined the same way (:func:`due_closures`,
    :func:`join_held`). A held closure that fails to join is dropped and listed in
    :attr:`SubmapStep.failed`: the submap stays joined.

    Raises:
        LinearSlamError: the submap cannot be joined (nothing changes); among them
            :class:`InvalidMapError` for one not positive definite in the frame of its end pose
            (:func:`~linear_slam_ros.core.frames.end_frame_fault`): joined, it would leave no global
            map that could be factorised.
        numpy.linalg.LinAlgError: its numbers make a system singular (nothing changes).
    """
    fault = end_frame_fault(submap)
    if fault is not None:
        raise InvalidMapError(fault)
    state, rest = hold_step(state, submap, seq, robot)
    result, joined = None, None
    if rest is not None:
        state, result, joined = _fuse(state, rest, probability, lambda s, m: join_step(s, m, seq, robot), robot)
    if joined is None:
        return SubmapStep(state.with_stream(robot, next_seq=seq + 1, last_seq=seq), False, result)
    state, due = due_closures(state, robot)
    released: list[tuple[HeldClosure, GateResult | None]] = []
    failed: list[tuple[HeldClosure, str]] = []
    fused = [joined]
    for closure in due:
        try:
            state, decision, piece = _fuse(state, closure.in_target_frame(), probability,
                                           lambda s, m: join_held(s, m, robot), robot)
        except (LinearSlamError, np.linalg.LinAlgError) as exc:
            failed.append((closure, str(exc)))
            continue
        released.append((closure, decision))
        if piece is not None:  # the closure has one variable: joined whole, or not at all
            fused.append(closure.measured)
    return SubmapStep(state, True, result, tuple(released), tuple(failed), tuple(fused))


def global_result(state: JoinerState, output_frame: OutputFrame | str = OutputFrame.END_POSE) -> Any | None:
    """Return the joined map of any strategy (``None`` while there is none).

    Pose maps are in the robocentric end-pose frame, or in the first pose's frame with
    ``output_frame`` ``first_pose``; feature-only maps in their feature frame.
    """
    result = island_map(state, MAIN_ISLAND)
    if result is None or OutputFrame(output_frame) is OutputFrame.END_POSE or state.first_pose_id is None:
        return result
    return state.strategy.express(result, state.first_pose_id)


def island_map(state: JoinerState, label: int) -> Any | None:
    """Return the joined map of island ``label`` in its newest end pose's frame (``None``: no such island).

    The main island (``label`` :data:`~linear_slam_ros.joiner.islands.MAIN_ISLAND`) is
    :func:`global_result`'s map; the others are in frames of their own.
    """
    if state.n_joined == 0:
        return None
    strategy = state.strategy
    if len(state.chains) == 1:  # no islands: nothing to cache
        return strategy.result(state.joined) if label == MAIN_ISLAND else None
    joined = island_result(state.chains, label, strategy.result, CACHE)
    if label == MAIN_ISLAND and isinstance(joined, LocalMap) and state.first_pose_id is not None:
        _record_anchors(state, joined)
    return joined


def _record_anchors(state: JoinerState, joined: LocalMap) -> None:
    """Keep where the main island's map puts each of its chains' first poses, in ``map_frame`` (for :func:`current_pose`)."""
    first = state.first_pose_id
    assert first is not None
    in_map = joined if joined.frame_id == first else estimate_in_frame(joined, first)
    for chain in state.chains:
        if chain.island == MAIN_ISLAND and (chain.first_pose_id == first or in_map.has_pose(chain.first_pose_id)):
            CACHE.anchors[chain.first_pose_id] = in_map.pose(chain.first_pose_id)


def robot_poses(state: JoinerState, joined: LocalMap) -> dict[str, FloatArray]:
    """Return each robot's newest end pose in the first pose's frame, from the main island's map ``joined``.

    Robots whose newest submap is in another island have none.
    """
    first = state.first_pose_id
    if first is None:
        return {}
    in_map = joined if joined.frame_id == first else estimate_in_frame(joined, first)
    out: dict[str, FloatArray] = {}
    for stream in state.streams:
        end = state.chains[stream.chain].end_id if stream.chain >= 0 else None
        if end is None or not state.in_main_island(stream.robot):
            continue
        if end == first or in_map.has_pose(end):
            out[stream.robot] = in_map.pose(end)
    return out


def current_pose(state: JoinerState, robot: str = "") -> PoseEstimate | None:
    """Return ``robot``'s newest end pose in ``map_frame`` (the first pose's frame), cheaply.

    On the first chain: chained along it (the strategy's ``current_pose``). On another chain of
    the main island (after a gap): the robot's motion along its chain since the chain's first
    pose, composed with where the last joined map of the main island put that first pose
    (:func:`island_map` keeps it). ``None`` when it is not known cheaply: before the first
    submap, on a chain no joined map has placed yet or in another island, or when the strategy
    has no cheap current pose.
    """
    chain_index = state.stream(robot).chain
    if state.first_pose_id is None or chain_index < 0:
        return None
    chain = state.chains[chain_index]
    if chain_index == 0:
        return state.strategy.current_pose(chain.joined, state.first_pose_id)
    anchor = CACHE.anchors.get(chain.first_pose_id) if chain.island == MAIN_ISLAND else None
    along = state.strategy.current_pose(chain.joined, chain.first_pose_id) if anchor is not None else None
    if anchor is None or along is None or state.dim is None:
        return None
    return along[0], compose(state.dim, anchor, along[1])


@dataclass(frozen=True)
class SavedJoiner:
    """Everything a :class:`Joiner` needs to carry on exactly where it was (see :meth:`Joiner.save`).

    Attributes:
        state: the joiner state (map, sequence position, counts).
        rejected: ``(reason, count)`` of the rejections so far.
        pending: ``(seq, submap)`` of the single robot's early submaps waiting in the reorder buffer.
        n_skipped: submaps skipped because their sequence number was already handled.
        journal_records: how many records of the node's journal this value includes (0 offline).
        robot_pending: ``(robot, seq, submap)`` of the other robots' early submaps.
    """

    state: JoinerState
    rejected: tuple[tuple[str, int], ...] = ()
    pending: tuple[tuple[int, LocalMap], ...] = ()
    n_skipped: int = 0
    journal_records: int = 0
    robot_pending: tuple[tuple[str, int, LocalMap], ...] = ()


def _check_reorder(window: int | None, timeout: float | None, max_bytes: int | None) -> None:
    """Raise :class:`ConfigError` naming a reorder bound that cannot work (``None``: not checked)."""
    if window is not None and (isinstance(window, bool) or not isinstance(window, int) or window < 1):
        raise ConfigError(f"reorder_window={window!r} must be an integer >= 1 (0 would drop every early submap)")
    if timeout is not None and not 0.0 < timeout < float("inf"):
        raise ConfigError(f"reorder_timeout={timeout!r} must be a finite number of seconds > 0")
    if max_bytes is not None and (isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 1):
        raise ConfigError(f"reorder_max_bytes={max_bytes!r} must be an integer >= 1")


def _check_gate(probability: float | None) -> None:
    if probability is not None and not 0.0 <= probability < 1.0:
        raise ConfigError(f"gate_probability={probability!r} must be in [0, 1) (0 or None: no gate)")


FIRST_SEQ = 1
"""Sequence number of a stream's first submap (the bag tools and the layout examples start at 1)."""


@dataclass
class Joiner:
    """Sequencing and bookkeeping around :func:`join_step` (mutable; owned by one thread).

    The sequence policy (README, "Behaviour"): submaps are joined in sequence-number order,
    starting at :data:`FIRST_SEQ`.

    - A sequence number already handled (joined, skipped, or waiting: a front-end or a replayed
      bag sending it again) is skipped with a debug line and counted in :attr:`n_skipped`.
    - A rejected submap does not use up its sequence number: a valid submap with that number may
      still come, and is joined when it does.
    - An early submap waits in the reorder buffer. The gap before it is skipped, with a warning,
      when the buffer holds more than ``reorder_window`` submaps or ``reorder_max_bytes`` bytes,
      or when the stream has not advanced for ``reorder_timeout`` seconds (:meth:`expire`), and
      only to a credible next submap: one at most ``reorder_window`` ahead, or the first of two
      consecutive waiting sequence numbers. A lone far-ahead submap (a sequence number of 10^9)
      can therefore never move the stream; when the buffer is full it is the one dropped.
    - A valid submap that adds nothing (no variable) uses up its number and changes nothing.

    Attributes:
        mode: joining method.
        map_type: ``as-is`` or ``feature-only``.
        reorder_window: how many early submaps may wait for a missing one.
        reorder_timeout: seconds a gap may hold a stream up (from the first submap waiting behind it) before it
            is skipped.
        reorder_max_bytes: bytes of state and information the reorder buffer may hold.
        clock: monotonic clock of :attr:`reorder_timeout`, s.
        defer_above: joins of more state scalars than this are deferred to ``worker`` (strategies
            with large joins: online divide and conquer); ``None`` joins everything on arrival.
        worker: computes deferred joins in the background (owned by the caller, who stops it).
        gate_probability: χ² probability of the gate run before each join (:func:`gate_step`);
            ``None`` or 0 turns it off. A submap that fails has its failing common variables split
            off, or all of them when more than half fail ("gated whole"); the rest (its new
            variables, the pose chain) is joined. Every such decision is recorded in :attr:`gated`
            and counted (and reported) by :meth:`reject` under reason ``gated``, so a submap with
            gated variables counts as joined and under ``gated``. A submap left with nothing uses up
            its sequence number and leaves the map unchanged.
        hold_closures: hold forward loop closures back until the chain reaches their pose, so that
            the gate tests them then (:func:`hold_step`, :mod:`~linear_slam_ros.joining.hold`);
            ``None``: when the gate is on. Each is joined (through the gate) right after the submap
            whose end pose it measures, as part of joining that submap; its gate decisions are
            recorded under its own submap's sequence number. A closure that cannot be joined then
            is counted under ``held_closure``.
        max_held: at most this many closures wait (a closure is about 1 KB); beyond it the oldest
            is dropped and counted under ``held_closure`` (a front-end closing on poses its robot
            never reaches cannot grow the state without bound).
        robots: the robot namespaces in slot order when the submaps' pose ids are qualified
            (:func:`~linear_slam_ros.joiner.robots.qualify`), recorded in the state
            (:attr:`JoinerState.robots`); ``()``: one robot.
        gated: every gate decision that kept something out of the map, in order.
        reinitialised: each feature the gate re-initialised (:mod:`~linear_slam_ros.joining.reinit`), in order.
        state: the current state (:meth:`restore` a saved one).
        rejected: count of rejected submaps by reason.
        join_seconds: wall time of each successful join.
        n_skipped: submaps skipped as already handled.
        on_reject: called with ``(reason, message)`` of each rejection.
        on_join: called with ``(robot, seq)`` after each submap is joined, in join order.
        on_fused: called with ``(robot, seq, maps)`` before ``on_join``: the measurements joined
            with the submap, as measured (:attr:`SubmapStep.fused`; the submap itself when neither
            the gate nor holding touched it), for a refiner of the joined map.
    """

    mode: JoinMethod
    map_type: MapType = MapType.AS_IS
    reorder_window: int = 100
    reorder_timeout: float = 5.0
    reorder_max_bytes: int = 256 << 20
    clock: Callable[[], float] = time.monotonic
    defer_above: int | None = None
    worker: MergeWorker | None = None
    gate_probability: float | None = None
    hold_closures: bool | None = None
    max_held: int = 10_000
    robots: tuple[str, ...] = ()
    state: JoinerState = field(init=False)
    gated: list[GateRecord] = field(default_factory=list)
    reinitialised: list[Reinitialisation] = field(default_factory=list)
    rejected: collections.Counter[str] = field(default_factory=collections.Counter)
    join_seconds: list[float] = field(default_factory=list)
    on_reject: Callable[[str, str], None] | None = None
    on_join: Callable[[str, int], None] | None = None
    on_fused: Callable[[str, int, tuple[LocalMap, ...]], None] | None = None
    n_skipped: int = 0
    _pending: collections.defaultdict[str, dict[int, LocalMap]] = field(
        default_factory=lambda: collections.defaultdict(dict)
    )
    _pending_bytes: int = 0
    _progress_at: collections.defaultdict[str, float] = field(default_factory=lambda: collections.defaultdict(float))

    def __post_init__(self) -> None:
        if self.max_held < 0:
            raise ConfigError(f"max_held={self.max_held!r} must be >= 0")
        if self.defer_above is not None and self.defer_above < 0:
            raise ConfigError(f"defer_above={self.defer_above!r} must be >= 0 (None: no join deferred)")
        _check_reorder(self.reorder_window, self.reorder_timeout, self.reorder_max_bytes)
        _check_gate(self.gate_probability)
        strategy = get_strategy(self.mode, self.map_type)  # ConfigError: not a method or map type
        check_strategy_can(strategy.method, strategy.map_type, self.gate_probability, self.hold_closures)
        self.robots = tuple(self.robots)
        self.state = self._scheduled(replace(new_state(strategy.method, strategy.map_type), robots=self.robots))
        self._progress_at = collections.defaultdict(self.clock, {"": self.clock()})
        CACHE.anchors.clear()  # they place chains of a joiner's map: one joiner per process

    def set_gate(self, probability: float | None) -> None:
        """Change the gate's probability from the next submap on (``None`` or 0: off).

        Holding closures follows it unless :attr:`hold_closures` says otherwise; closures already
        held are joined as the chain reaches them either way.

        Raises:
            ConfigError: ``probability`` is not in [0, 1).
        """
        _check_gate(probability)
        check_strategy_can(self.state.method, self.state.map_type, probability, None)
        self.gate_probability = probability
        self.state = self._scheduled(self.state)

    def _scheduled(self, state: JoinerState) -> JoinerState:
        """Return ``state`` set to defer its large joins, and to hold closures, as this joiner is configured to."""
        strategy = state.strategy
        chains = tuple(replace(c, joined=strategy.defer(c.joined, self.defer_above)) for c in state.chains)
        holding = self.hold_closures if self.hold_closures is not None else bool(self.gate_probability)
        return replace(state, chains=chains, defer_above=self.defer_above, hold_closures=holding)

    def reset(self) -> None:
        """Forget every submap, count and buffered message (queued background joins included)."""
        if self.worker is not None:
            self.worker.clear()
        self.state = self._scheduled(replace(new_state(self.state.method, self.state.map_type), robots=self.robots))
        CACHE.anchors.clear()
        self.rejected.clear()
        self.join_seconds.clear()
        self.gated.clear()
        self.reinitialised.clear()
        self._pending.clear()
        self._pending_bytes = 0
        self._progress_at = collections.defaultdict(self.clock, {"": self.clock()})
        self.n_skipped = 0

    def check_restorable(self, saved: SavedJoiner) -> tuple[str, ...]:
        """Check that this joiner can carry on from ``saved``; return the robots its state will record.

        A robot list may grow or shrink at its end: each robot the saved map knows keeps its slot, and a
        new one takes a slot no saved robot had (the longer list is kept, so a slot given up stays
        reserved). Reordering or replacing robots would give one robot's submaps another's pose ids.

        Raises:
            ConfigError: the saved state was joined with another mode or map type, or its robots'
                slots differ from this joiner's (naming both lists).
        """
        state = saved.state
        if (state.method, state.map_type) != (self.state.method, self.state.map_type):
            raise ConfigError(
                f"the saved map was joined with mode={state.method.value!r}, map_type="
                f"{state.map_type.value!r}; this joiner runs mode={self.state.method.value!r}, "
                f"map_type={self.state.map_type.value!r}"
            )
        named = sorted({s.robot for s in state.streams if s.robot})
        if not state.robots and named and self.robots:  # a state file of format 7 or older: the names alone
            if not set(named) <= set(self.robots):
                raise ConfigError(f"the saved map has robots {named}, not all in robots={list(self.robots)}")
            logger.warning("the saved map (an older state file) does not record its robots' order: robots=%s is "
                           "taken to be the order it was joined with", list(self.robots))
            return self.robots
        shorter, longer = sorted((state.robots, self.robots), key=len)
        if longer[:len(shorter)] != shorter:
            raise ConfigError(
                f"the saved map was joined with robots={list(state.robots)}, this joiner runs robots={list(self.robots)}: "
                "each robot's pose ids depend on its place in the list (robot k's pose i is k * 2^32 + i), so a robot "
                "may only be added or removed at the end"
            )
        return longer

    def save(self, journal_records: int = 0) -> SavedJoiner:
        """Return the joiner's state, counts and reorder buffer as one immutable value."""
        pending = tuple(sorted((seq, submap) for seq, submap in self._pending.get("", {}).items()))
        robots = tuple(
            (robot, seq, submap)
            for robot in sorted(self._pending) if robot
            for seq, submap in sorted(self._pending[robot].items())
        )
        return SavedJoiner(
            self.state, tuple(sorted(self.rejected.items())), pending, self.n_skipped, journal_records, robots
        )

    def restore(self, saved: SavedJoiner) -> None:
        """Carry on from a saved value (its method and map type replace this joiner's; latency figures and the
        gate's decision records, :attr:`gated` and :attr:`reinitialised`, restart: the counts by reason stay).

        Raises:
            ConfigError: the saved state cannot be restored here (:meth:`check_restorable`).
        """
        robots = self.check_restorable(saved)
        if self.worker is not None:
            self.worker.clear()
        self.state = self._scheduled(replace(saved.state, robots=robots))
        if self.worker is not None:  # merges the saved state had not computed (snapshots keep them deferred)
            for chain in self.state.chains:
                self.worker.submit(self.state.strategy.pending(chain.joined))
        CACHE.anchors.clear()
        self.rejected = collections.Counter(dict(saved.rejected))
        self._pending = collections.defaultdict(dict)
        for seq, submap in saved.pending:
            self._pending[""][seq] = submap
        for robot, seq, submap in saved.robot_pending:
            self._pending[robot][seq] = submap
        self._pending_bytes = sum(m.nbytes for waiting in self._pending.values() for m in waiting.values())
        self._progress_at = collections.defaultdict(self.clock, {r: self.clock() for r in ("", *self._pending)})
        self.n_skipped = saved.n_skipped
        self.join_seconds.clear()
        self.gated.clear()  # they described the map this one replaces
        self.reinitialised.clear()

    @property
    def n_rejected(self) -> int:
        """Total number of rejected submaps."""
        return int(sum(self.rejected.values()))

    def reject(self, reason: str, message: str) -> None:
        """Count a rejection under ``reason`` and report ``message``."""
        self.rejected[reason] += 1
        if self.on_reject is not None:
            self.on_reject(reason, message)

    @property
    def expected(self) -> int:
        """The sequence number joined next (of the single robot; :meth:`expected_of` for others)."""
        return self.expected_of("")

    def expected_of(self, robot: str) -> int:
        """The sequence number of ``robot``'s stream joined next."""
        next_seq = self.state.stream(robot).next_seq
        return next_seq if next_seq is not None else FIRST_SEQ

    def already_handled(self, seq: int, robot: str = "") -> bool:
        """Return whether :meth:`offer` would skip ``seq`` as already handled (joined, skipped or waiting)."""
        return seq < self.expected_of(robot) or seq in self._pending.get(robot, {})

    @staticmethod
    def _who(seq: int, robot: str) -> str:
        return f"submap seq {seq}" if not robot else f"robot {robot!r} submap seq {seq}"

    def offer(self, submap: LocalMap, seq: int, robot: str = "") -> list[int]:
        """Take a decoded submap of ``robot``'s stream; join it (and any buffered successors) when its turn comes.

        Each robot's stream has its own sequence numbers, reorder buffer and gaps; all join one map.

        Returns:
            Sequence numbers joined by this call, in order (of ``robot``'s stream).
        """
        if seq < FIRST_SEQ:
            self.reject("seq_out_of_range", f"{self._who(seq, robot)} rejected: sequence numbers start at {FIRST_SEQ}")
            return []
        if self.already_handled(seq, robot):
            self.n_skipped += 1
            logger.debug("%s was already handled (next expected: %d): skipped", self._who(seq, robot),
                         self.expected_of(robot))
            return []
        _ = self._progress_at[robot]  # a new robot's stream starts its clock now
        if seq > self.expected_of(robot):
            if not self._pending[robot]:  # the gap holds the stream up from now (not from its last join: an idle
                self._progress_at[robot] = self.clock()  # robot's late submap would be given up at once)
            self._pending[robot][seq] = submap
            self._pending_bytes += submap.nbytes
            return self._relieve(robot)
        return self._join(submap, seq, robot) + self._drain(robot)

    def expire(self) -> list[tuple[str, int]]:
        """Skip gaps that have held a stream up for ``reorder_timeout`` seconds (call it periodically).

        A gap holds its stream up from the arrival of the first submap that waits behind it (or the
        stream's last progress since).

        Returns:
            ``(robot, sequence number)`` of each submap joined, in order.
        """
        joined: list[tuple[str, int]] = []
        for robot in sorted(self._pending):
            idle = self.clock() - self._progress_at[robot]
            if self._pending[robot] and idle >= self.reorder_timeout:
                joined += [(robot, seq) for seq in self._skip_gap(robot, f"no progress for {idle:.1f} s")]
        return joined

    def set_reorder(
        self, window: int | None = None, timeout: float | None = None, max_bytes: int | None = None
    ) -> list[tuple[str, int]]:
        """Change the reorder bounds (``None``: unchanged) and bring every robot's buffer within them now.

        What a lowered bound no longer admits is handled as when the buffer fills (:meth:`offer`):
        a credible gap is skipped and the submaps behind it joined, else the farthest submap dropped.

        Returns:
            ``(robot, sequence number)`` of each submap joined, in order.
        """
        _check_reorder(window, timeout, max_bytes)
        if window is not None:
            self.reorder_window = window
        if timeout is not None:
            self.reorder_timeout = timeout
        if max_bytes is not None:
            self.reorder_max_bytes = max_bytes
        return [(robot, seq) for robot in sorted(self._pending) for seq in self._relieve(robot)]

    def flush(self) -> list[int]:
        """Skip every gap now: the streams are complete (an offline run's end), what is missing never comes.

        Returns:
            Sequence numbers joined (of all robots).
        """
        joined: list[int] = []
        for robot in sorted(self._pending):
            while self._pending[robot]:  # each skip joins (or rejects) at least the lowest waiting submap
                joined += self._skip_gap(robot, "the stream has ended", force=True)
        return joined

    def _credible(self, seq: int, robot: str) -> bool:
        """Whether the stream may move on to waiting ``seq``: near, or the first of two consecutive numbers."""
        return seq - self.expected_of(robot) <= self.reorder_window or seq + 1 in self._pending[robot]

    def _relieve(self, robot: str) -> list[int]:
        """Keep ``robot``'s buffer within its count and the buffers within their bytes: skip the gap, else drop
        the farthest submap.

        Only ``robot``'s buffer is relieved (what is joined is of its stream); :meth:`set_reorder`
        relieves every robot's.
        """
        joined: list[int] = []
        waiting = self._pending[robot]
        while waiting and (len(waiting) > self.reorder_window or self._pending_bytes > self.reorder_max_bytes):
            if self._credible(min(waiting), robot):
                joined += self._skip_gap(robot, f"the reorder buffer holds {len(waiting)} submaps, {self._pending_bytes} bytes")
                continue
            far = max(waiting)
            self._pending_bytes -= waiting.pop(far).nbytes
            self.reject(
                "reorder_buffer_full",
                f"{self._who(far, robot)} dropped: it waits for seq {self.expected_of(robot)} and the reorder buffer "
                f"is full ({self.reorder_window} submaps, {self.reorder_max_bytes} bytes)",
            )
        return joined

    def _skip_gap(self, robot: str, why: str, force: bool = False) -> list[int]:
        """Move the stream to the lowest credible waiting submap, if there is one, and join from there."""
        start = min(self._pending[robot])
        if not force and not self._credible(start, robot):
            return []
        gap = f"seq {self.expected_of(robot)}..{start - 1}"
        whose = f" of robot {robot!r}" if robot else ""
        self.reject("gap", f"submaps {gap}{whose} never arrived or were rejected ({why}): skipped")
        self.state = self.state.with_stream(robot, next_seq=start)
        self._progress_at[robot] = self.clock()
        return self._drain(robot)

    def _drain(self, robot: str) -> list[int]:
        joined: list[int] = []
        waiting = self._pending[robot]
        while self.expected_of(robot) in waiting:
            seq = self.expected_of(robot)
            submap = waiting.pop(seq)
            self._pending_bytes -= submap.nbytes
            done = self._join(submap, seq, robot)
            if not done and self.expected_of(robot) == seq:  # rejected: its number stays open for a valid one
                break
            joined += done
        return joined

    def _join(self, submap: LocalMap, seq: int, robot: str) -> list[int]:
        if submap.n_vars == 0:  # valid, and adds nothing: its number is used, the map unchanged
            logger.info("%s holds no variable: nothing to join", self._who(seq, robot))
            self.state = self.state.with_stream(robot, next_seq=seq + 1, last_seq=seq)
            self._progress_at[robot] = self.clock()
            return []
        t0 = time.perf_counter()
        try:
            step = submap_step(self.state, submap, seq, robot, self.gate_probability)
        except (LinearSlamError, np.linalg.LinAlgError) as exc:  # numpy's: a system the numbers make singular
            self.reject(type(exc).__name__, f"{self._who(seq, robot)} rejected: {exc}")
            return []
        self.state = step.state
        if step.result is not None:
            self._record_gate(step.result, submap, seq, robot)
        for closure, result in step.released:
            if result is not None:
                self._record_gate(result, submap, closure.seq, closure.robot, closure)
        for closure, why in step.failed:
            self.reject("held_closure", f"{closure.describe()}, held until the chain reached pose {closure.target}, "
                                        f"not joined: {why}")
        if len(self.state.held) > self.max_held:
            dropped = self.state.held[: len(self.state.held) - self.max_held]
            self.state = replace(self.state, held=self.state.held[len(dropped):])
            for closure in dropped:
                self.reject("held_closure", f"{closure.describe()} dropped: more than max_held={self.max_held} closures "
                                            f"wait for their pose (pose {closure.target} not reached)")
        self._progress_at[robot] = self.clock()
        if not step.joined:
            return []
        if self.on_fused is not None:
            self.on_fused(robot, seq, step.fused)
        if self.worker is not None:
            chain = self.state.chains[self.state.stream(robot).chain]
            self.worker.submit(self.state.strategy.pending(chain.joined))
        self.join_seconds.append(time.perf_counter() - t0)
        if self.on_join is not None:
            self.on_join(robot, seq)
        return [seq]

    def _record_gate(
        self, result: GateResult, submap: LocalMap, seq: int, robot: str, closure: HeldClosure | None = None
    ) -> None:
        """Record and report what the gate did to a submap, once that is settled (joined, or nothing left to join).

        For a held ``closure``, the record names its submap and the pose it measured (``closure.target``).
        """
        for front, landmark in result.reinitialised:
            self.reinitialised.append(Reinitialisation(seq, robot, front, landmark, self.state.n_joined))
            logger.warning("%s: feature %d failed the gate again after a sighting of it was split off: re-initialised "
                           "as landmark %d (its later sightings join that one)", self._who(seq, robot), front, landmark)
        if result.passed:
            return
        variables = result.split if not result.rejected else result.worst
        ids, kinds = tuple(v.var_id for v in variables), tuple(v.kind for v in variables)
        own = tuple(v.nis for v in variables), tuple(result.threshold_of(v) for v in variables)
        label = self._who(seq, robot) + f" ({submap.name!r})"
        if closure is not None:  # its one variable is the submap's frame pose, seen from the pose it measured
            ids, kinds = (closure.target,), (POSE,)
            label = f"{closure.describe()}, held until the chain reached pose {closure.target}"
        record = GateRecord(seq, closure.name if closure is not None else submap.name, ids, kinds, result.nis,
                            result.dof, result.threshold, result.rejected, *own, robot=robot)
        self.gated.append(record)
        self.reject("gated", result.message(label))

    def stats(self) -> dict[str, float]:
        """Return counts, join-latency figures (ms) and the number of islands for the global map message."""
        lat = latency(self.join_seconds)
        return {
            "n_joined": float(self.state.n_joined),
            "n_rejected": float(self.n_rejected),
            "last_join_ms": self.join_seconds[-1] * 1e3 if self.join_seconds else 0.0,
            "join_ms_p50": lat.p50_ms,
            "join_ms_p99": lat.p99_ms,
            "join_ms_max": lat.max_ms,
            "join_seconds_total": float(sum(self.join_seconds)),
            "n_islands": float(len(self.state.islands)),
        }
