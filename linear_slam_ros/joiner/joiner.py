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

from linear_slam_ros.core.errors import ConfigError, LinearSlamError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.core.timing import latency
from linear_slam_ros.joiner.config import OutputFrame
from linear_slam_ros.joiner.registry import AnyStrategy, get_strategy
from linear_slam_ros.joiner.strategy import JoinMethod, MapType
from linear_slam_ros.joining.background import MergeWorker
from linear_slam_ros.joining.gate import GateResult, gate_submap

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class JoinerState:
    """The whole joiner state: one value, saved and restored as a unit.

    Attributes:
        method: joining method (with ``map_type``, the registry key of the strategy).
        map_type: ``as-is`` or ``feature-only``.
        joined: the strategy's own state (see :meth:`strategy`).
        first_pose_id: frame pose of the first joined submap (``map_frame`` of the outputs).
        n_joined: submaps joined.
        next_seq: sequence number expected next (``None`` before the first submap).
        last_seq: sequence number of the last joined submap.
    """

    method: JoinMethod
    map_type: MapType
    joined: Any
    first_pose_id: int | None = None
    n_joined: int = 0
    next_seq: int | None = None
    last_seq: int | None = None

    @property
    def strategy(self) -> AnyStrategy:
        """The joining strategy of this state."""
        return get_strategy(self.method, self.map_type)


def new_state(method: JoinMethod, map_type: MapType = MapType.AS_IS) -> JoinerState:
    """Return the empty state of a joiner."""
    return JoinerState(method, map_type, get_strategy(method, map_type).empty())


def join_step(state: JoinerState, submap: LocalMap, seq: int) -> JoinerState:
    """Join one submap: a pure function of ``(state, submap)``.

    Raises:
        LinearSlamError: the submap cannot be joined (the state is unchanged).
    """
    joined = state.strategy.step(state.joined, submap)
    first = state.first_pose_id if state.first_pose_id is not None else submap.frame_id
    return replace(state, joined=joined, first_pose_id=first, n_joined=state.n_joined + 1, next_seq=seq + 1, last_seq=seq)


def gate_step(state: JoinerState, submap: LocalMap, probability: float) -> GateResult:
    """Test a submap against the state's global map by the χ² gate: a pure function of ``(state, submap)``.

    The NIS of the variables the submap shares with the map (after bringing both into one frame)
    against ``chi2.ppf(probability, dof)``; failing variables are split off, or the submap is gated
    whole (:func:`~linear_slam_ros.joining.gate.gate_submap`). Strategies that cannot gate
    (``marginal`` returns ``None``) pass everything.

    Raises:
        SolverError: a covariance is not positive definite.
    """
    if state.n_joined == 0:
        return GateResult(probability, 0.0, 0, float("inf"), submap=submap)
    strategy, joined = state.strategy, state.joined
    return gate_submap(lambda keys: strategy.marginal(joined, keys), submap, probability)


@dataclass(frozen=True)
class GateRecord:
    """A gate decision that kept something out of the map (for report.json's ``gated``, and the node).

    Attributes:
        submap: sequence number of the submap.
        name: the submap's name.
        variables: ids of the variables split off (all common variables' worst ones when gated whole).
        kinds: their kinds (0 pose, 1 feature).
        nis: NIS of all common variables before the decision; ``dof``: their scalars.
        threshold: ``chi2.ppf(gate_probability, dof)``.
        rejected: the whole submap was gated (else only ``variables`` were, and the rest joined).
    """

    submap: int
    name: str
    variables: tuple[int, ...]
    kinds: tuple[int, ...]
    nis: float
    dof: int
    threshold: float
    rejected: bool

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: ``{"submap", "name", "variables", "kinds", "nis", "dof", "threshold", "rejected"}``."""
        return {"submap": self.submap, "name": self.name, "variables": list(self.variables), "kinds": list(self.kinds),
                "nis": self.nis, "dof": self.dof, "threshold": self.threshold, "rejected": self.rejected}


def global_result(state: JoinerState, output_frame: OutputFrame | str = OutputFrame.END_POSE) -> Any | None:
    """Return the joined map of any strategy (``None`` while there is none).

    Pose maps are in the robocentric end-pose frame, or in the first pose's frame with
    ``output_frame`` ``first_pose``; feature-only maps in their feature frame.
    """
    if state.n_joined == 0:
        return None
    strategy = state.strategy
    result = strategy.result(state.joined)
    if result is None or OutputFrame(output_frame) is OutputFrame.END_POSE or state.first_pose_id is None:
        return result
    return strategy.express(result, state.first_pose_id)


@dataclass(frozen=True)
class SavedJoiner:
    """Everything a :class:`Joiner` needs to carry on exactly where it was (see :meth:`Joiner.save`).

    Attributes:
        state: the joiner state (map, sequence position, counts).
        rejected: ``(reason, count)`` of the rejections so far.
        pending: ``(seq, submap)`` of the early submaps waiting in the reorder buffer.
        n_skipped: submaps skipped because their sequence number was already handled.
        journal_records: how many records of the node's journal this value includes (0 offline).
    """

    state: JoinerState
    rejected: tuple[tuple[str, int], ...] = ()
    pending: tuple[tuple[int, LocalMap], ...] = ()
    n_skipped: int = 0
    journal_records: int = 0


FIRST_SEQ = 1
"""Sequence number of a stream's first submap (the bag tools and the layout examples start at 1)."""


def _nbytes(submap: LocalMap) -> int:
    """Bytes of a submap's arrays (what it holds in the reorder buffer)."""
    info = submap.info
    info_bytes = info.nbytes if isinstance(info, np.ndarray) else info.data.nbytes + info.indices.nbytes + info.indptr.nbytes
    return int(submap.x.nbytes + submap.ids.nbytes + submap.kinds.nbytes + info_bytes)


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
        reorder_timeout: seconds without progress after which a gap is skipped.
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
        gated: every gate decision that kept something out of the map, in order.
        state: the current state (:meth:`restore` a saved one).
        rejected: count of rejected submaps by reason.
        join_seconds: wall time of each successful join.
        n_skipped: submaps skipped as already handled.
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
    state: JoinerState = field(init=False)
    gated: list[GateRecord] = field(default_factory=list)
    rejected: collections.Counter[str] = field(default_factory=collections.Counter)
    join_seconds: list[float] = field(default_factory=list)
    on_reject: Callable[[str, str], None] | None = None
    n_skipped: int = 0
    _pending: dict[int, LocalMap] = field(default_factory=dict)
    _pending_bytes: int = 0
    _progress_at: float = field(default=0.0)

    def __post_init__(self) -> None:
        if self.gate_probability is not None and not 0.0 <= self.gate_probability < 1.0:
            raise ConfigError(f"gate_probability={self.gate_probability!r} must be in [0, 1) (0 or None: no gate)")
        self.state = self._scheduled(new_state(JoinMethod(self.mode), MapType(self.map_type)))
        self._progress_at = self.clock()

    def _scheduled(self, state: JoinerState) -> JoinerState:
        """Return ``state`` set to defer its large joins as this joiner is configured to."""
        return replace(state, joined=state.strategy.defer(state.joined, self.defer_above))

    def reset(self) -> None:
        """Forget every submap, count and buffered message (queued background joins included)."""
        if self.worker is not None:
            self.worker.clear()
        self.state = self._scheduled(new_state(self.state.method, self.state.map_type))
        self.rejected.clear()
        self.join_seconds.clear()
        self.gated.clear()
        self._pending.clear()
        self._pending_bytes = 0
        self._progress_at = self.clock()
        self.n_skipped = 0

    def save(self, journal_records: int = 0) -> SavedJoiner:
        """Return the joiner's state, counts and reorder buffer as one immutable value."""
        return SavedJoiner(
            self.state, tuple(sorted(self.rejected.items())), tuple(sorted(self._pending.items())), self.n_skipped,
            journal_records,
        )

    def restore(self, saved: SavedJoiner) -> None:
        """Carry on from a saved value (its method and map type replace this joiner's; latency figures restart).

        Raises:
            ConfigError: the saved state's strategy differs from this joiner's.
        """
        if (saved.state.method, saved.state.map_type) != (self.state.method, self.state.map_type):
            raise ConfigError(
                f"the saved map was joined with mode={saved.state.method.value!r}, map_type="
                f"{saved.state.map_type.value!r}; this joiner runs mode={self.state.method.value!r}, "
                f"map_type={self.state.map_type.value!r}"
            )
        if self.worker is not None:
            self.worker.clear()
        self.state = self._scheduled(saved.state)
        self.rejected = collections.Counter(dict(saved.rejected))
        self._pending = dict(saved.pending)
        self._pending_bytes = sum(_nbytes(m) for m in self._pending.values())
        self._progress_at = self.clock()
        self.n_skipped = saved.n_skipped
        self.join_seconds.clear()

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
        """The sequence number joined next."""
        return self.state.next_seq if self.state.next_seq is not None else FIRST_SEQ

    def already_handled(self, seq: int) -> bool:
        """Return whether :meth:`offer` would skip ``seq`` as already handled (joined, skipped or waiting)."""
        return seq < self.expected or seq in self._pending

    def offer(self, submap: LocalMap, seq: int) -> list[int]:
        """Take a decoded submap; join it (and any buffered successors) when its turn comes.

        Returns:
            Sequence numbers joined by this call, in order.
        """
        if seq < FIRST_SEQ:
            self.reject("seq_out_of_range", f"submap seq {seq} rejected: sequence numbers start at {FIRST_SEQ}")
            return []
        if self.already_handled(seq):
            self.n_skipped += 1
            logger.debug("submap seq %d was already handled (next expected: %d): skipped", seq, self.expected)
            return []
        if seq > self.expected:
            self._pending[seq] = submap
            self._pending_bytes += _nbytes(submap)
            return self._relieve()
        return self._join(submap, seq) + self._drain()

    def expire(self) -> list[int]:
        """Skip a gap that has held the stream up for ``reorder_timeout`` seconds (call it periodically).

        Returns:
            Sequence numbers joined.
        """
        if self._pending and self.clock() - self._progress_at >= self.reorder_timeout:
            return self._skip_gap(f"no progress for {self.clock() - self._progress_at:.1f} s")
        return []

    def _credible(self, seq: int) -> bool:
        """Whether the stream may move on to waiting ``seq``: near, or the first of two consecutive numbers."""
        return seq - self.expected <= self.reorder_window or seq + 1 in self._pending

    def _relieve(self) -> list[int]:
        """Keep the buffer within its count and byte bounds: skip the gap, else drop the farthest submap."""
        joined: list[int] = []
        while len(self._pending) > self.reorder_window or self._pending_bytes > self.reorder_max_bytes:
            if self._credible(min(self._pending)):
                joined += self._skip_gap(
                    f"the reorder buffer holds {len(self._pending)} submaps, {self._pending_bytes} bytes"
                )
                continue
            far = max(self._pending)
            self._pending_bytes -= _nbytes(self._pending.pop(far))
            self.reject(
                "reorder_buffer_full",
                f"submap seq {far} dropped: it waits for seq {self.expected} and the reorder buffer is full "
                f"({self.reorder_window} submaps, {self.reorder_max_bytes} bytes)",
            )
        return joined

    def _skip_gap(self, why: str) -> list[int]:
        """Move the stream to the lowest credible waiting submap, if there is one, and join from there."""
        start = min(self._pending)
        if not self._credible(start):
            return []
        self.reject("gap", f"submaps seq {self.expected}..{start - 1} never arrived or were rejected ({why}): skipped")
        self.state = replace(self.state, next_seq=start)
        self._progress_at = self.clock()
        return self._drain()

    def _drain(self) -> list[int]:
        joined: list[int] = []
        while self.expected in self._pending:
            seq = self.expected
            submap = self._pending.pop(seq)
            self._pending_bytes -= _nbytes(submap)
            done = self._join(submap, seq)
            if not done and self.expected == seq:  # rejected: its number stays open for a valid one
                break
            joined += done
        return joined

    def _join(self, submap: LocalMap, seq: int) -> list[int]:
        if submap.n_vars == 0:  # valid, and adds nothing: its number is used, the map unchanged
            logger.info("submap seq %d holds no variable: nothing to join", seq)
            self.state = replace(self.state, next_seq=seq + 1, last_seq=seq)
            self._progress_at = self.clock()
            return []
        t0 = time.perf_counter()
        try:
            if self.gate_probability:
                gated = self._gate(submap, seq)
                if gated is None:
                    return []
                submap = gated
            self.state = join_step(self.state, submap, seq)
        except (LinearSlamError, np.linalg.LinAlgError) as exc:  # numpy's: a system the numbers make singular
            self.reject(type(exc).__name__, f"submap seq {seq} rejected: {exc}")
            return []
        if self.worker is not None:
            self.worker.submit(self.state.strategy.pending(self.state.joined))
        self.join_seconds.append(time.perf_counter() - t0)
        self._progress_at = self.clock()
        return [seq]

    def _gate(self, submap: LocalMap, seq: int) -> LocalMap | None:
        """Run the gate; return what to join (``None``: nothing left, its number used up)."""
        assert self.gate_probability is not None
        result = gate_step(self.state, submap, self.gate_probability)
        if result.passed:
            return submap
        variables = result.split if not result.rejected else result.worst
        record = GateRecord(
            seq, submap.name, tuple(v.var_id for v in variables), tuple(v.kind for v in variables), result.nis,
            result.dof, result.threshold, result.rejected,
        )
        self.gated.append(record)
        self.reject("gated", result.message(f"submap seq {seq} ({submap.name!r})"))
        if result.submap is None:  # nothing left to join: its number is used, the map unchanged
            self.state = replace(self.state, next_seq=seq + 1, last_seq=seq)
            self._progress_at = self.clock()
        return result.submap

    def stats(self) -> dict[str, float]:
        """Return counts and join-latency figures (ms) for the global map message."""
        lat = latency(self.join_seconds)
        return {
            "n_joined": float(self.state.n_joined),
            "n_rejected": float(self.n_rejected),
            "last_join_ms": self.join_seconds[-1] * 1e3 if self.join_seconds else 0.0,
            "join_ms_p50": lat.p50_ms,
            "join_ms_p99": lat.p99_ms,
            "join_ms_max": lat.max_ms,
            "join_seconds_total": float(sum(self.join_seconds)),
        }
