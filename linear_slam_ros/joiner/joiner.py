"""The joiner's state machine without ROS: sequencing, joining, rejection counts, outputs.

The node feeds it decoded submaps and asks it for outputs; everything here is testable without
rclpy. The global map is one immutable value (:class:`JoinerState`): a submap either produces a
new state or is rejected with a reason, leaving the old one as it was.
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from linear_slam_ros.core.errors import InvalidMapError, LinearSlamError
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.feature_only.online import FeatureJoinState, feature_result, feature_step
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.joining.pairwise import OnlineDCState, online_dc_result, online_dc_step
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.runner import JoinMethod, MapType
from linear_slam_ros.joining.sequential import SequentialState, sequential_step

logger = logging.getLogger(__name__)

OUTPUT_FRAMES = ("end_pose", "first_pose")


@dataclass(frozen=True)
class JoinerState:
    """The whole joiner state: one value, saved and restored as a unit.

    Attributes:
        mode: ``sequential`` or ``online-dc``.
        sequential: state of exact sequential joining (mode ``sequential``).
        online: state of online divide and conquer (mode ``online-dc``).
        features: state of feature-only joining; set exactly when ``map_type`` is
            ``feature-only`` (then the other joining states stay empty).
        first_pose_id: frame pose of the first joined submap (``map_frame`` of the outputs).
        n_joined: submaps joined.
        next_seq: sequence number expected next (``None`` before the first submap).
        last_seq: sequence number of the last joined submap.
    """

    mode: JoinMethod
    sequential: SequentialState = SequentialState()
    online: OnlineDCState = OnlineDCState()
    features: FeatureJoinState | None = None
    first_pose_id: int | None = None
    n_joined: int = 0
    next_seq: int | None = None
    last_seq: int | None = None

    @property
    def map_type(self) -> MapType:
        """``feature-only`` when the state joins feature-only maps, else ``as-is``."""
        return MapType.AS_IS if self.features is None else MapType.FEATURE_ONLY


def join_step(state: JoinerState, submap: LocalMap, seq: int) -> JoinerState:
    """Join one submap: a pure function of ``(state, submap)``.

    Raises:
        LinearSlamError: the submap cannot be joined (the state is unchanged).
    """
    if state.features is not None:
        new = replace(state, features=feature_step(state.features, submap))
    elif state.mode is JoinMethod.SEQUENTIAL:
        new = replace(state, sequential=sequential_step(state.sequential, submap))
    else:
        new = replace(state, online=online_dc_step(state.online, submap))
    first = state.first_pose_id if state.first_pose_id is not None else submap.frame_id
    return replace(new, first_pose_id=first, n_joined=state.n_joined + 1, next_seq=seq + 1, last_seq=seq)


def new_state(mode: JoinMethod, map_type: MapType = MapType.AS_IS) -> JoinerState:
    """Return the empty state of a joiner."""
    features = FeatureJoinState(mode) if map_type is MapType.FEATURE_ONLY else None
    return JoinerState(mode, features=features)


def global_map_of(state: JoinerState, output_frame: str = "end_pose") -> LocalMap | None:
    """Return the global map in the robocentric end-pose frame or the first pose's frame.

    Raises:
        InvalidMapError: the state is feature-only (see :func:`global_feature_map_of`).
    """
    if state.map_type is MapType.FEATURE_ONLY:
        raise InvalidMapError("a feature-only joiner has no pose frame: use global_feature_map_of")
    if state.n_joined == 0:
        return None
    if state.mode is JoinMethod.SEQUENTIAL:
        assert state.sequential.global_map is not None
        joined = state.sequential.global_map.to_local_map()
    else:
        joined = online_dc_result(state.online)
    if output_frame == "first_pose" and state.first_pose_id is not None and joined.frame_id != state.first_pose_id:
        joined = change_frame(joined, state.first_pose_id)
    return joined


def global_feature_map_of(state: JoinerState) -> FeatureMap | None:
    """Return the feature-only global map (in the frame of its longest-baseline features)."""
    if state.features is None:
        raise InvalidMapError(f"a joiner with map_type {state.map_type.value!r} has no feature-only map")
    return feature_result(state.features)


@dataclass
class Joiner:
    """Sequencing and bookkeeping around :func:`join_step` (mutable; owned by one thread).

    Submaps are joined in sequence-number order. A duplicate or late sequence number is
    rejected; an early one waits in a reorder buffer until the gap fills, or until the buffer
    holds ``reorder_window`` submaps, when the gap is skipped with a warning.

    Attributes:
        mode: joining method.
        map_type: ``as-is`` or ``feature-only``.
        reorder_window: how many early submaps may wait for a missing one.
        state: the current state (replace it to restore a saved one).
        rejected: count of rejected submaps by reason.
        join_seconds: wall time of each successful join.
    """

    mode: JoinMethod
    map_type: MapType = MapType.AS_IS
    reorder_window: int = 100
    state: JoinerState = field(init=False)
    rejected: collections.Counter[str] = field(default_factory=collections.Counter)
    join_seconds: list[float] = field(default_factory=list)
    on_reject: Callable[[str, str], None] | None = None
    _pending: dict[int, LocalMap] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.state = new_state(JoinMethod(self.mode), MapType(self.map_type))

    def reset(self) -> None:
        """Forget every submap, count and buffered message."""
        self.state = new_state(self.state.mode, self.state.map_type)
        self.rejected.clear()
        self.join_seconds.clear()
        self._pending.clear()

    @property
    def n_rejected(self) -> int:
        """Total number of rejected submaps."""
        return int(sum(self.rejected.values()))

    def reject(self, reason: str, message: str) -> None:
        """Count a rejection under ``reason`` and report ``message``."""
        self.rejected[reason] += 1
        if self.on_reject is not None:
            self.on_reject(reason, message)

    def offer(self, submap: LocalMap, seq: int) -> list[int]:
        """Take a decoded submap; join it (and any buffered successors) when its turn comes.

        Returns:
            Sequence numbers joined by this call, in order.
        """
        expected = self.state.next_seq
        if expected is not None and seq < expected or seq in self._pending:
            self.reject("duplicate_or_late", f"submap seq {seq} arrived after seq {expected - 1 if expected else seq} was handled: dropped")
            return []
        if expected is not None and seq > expected:
            self._pending[seq] = submap
            if len(self._pending) <= self.reorder_window:
                return []
            skipped = min(self._pending) - expected
            self.reject("gap", f"submaps seq {expected}..{min(self._pending) - 1} never arrived ({skipped} missing): skipped")
            self.state = replace(self.state, next_seq=min(self._pending))
            return self._drain()
        joined = self._join(submap, seq)
        return joined + self._drain()

    def _drain(self) -> list[int]:
        joined: list[int] = []
        while self.state.next_seq in self._pending:
            seq = self.state.next_seq
            assert seq is not None
            joined += self._join(self._pending.pop(seq), seq)
        return joined

    def _join(self, submap: LocalMap, seq: int) -> list[int]:
        t0 = time.perf_counter()
        try:
            self.state = join_step(self.state, submap, seq)
        except LinearSlamError as exc:
            self.reject(type(exc).__name__, f"submap seq {seq} rejected: {exc}")
            if self.state.next_seq in (None, seq):  # its sequence number is used up
                self.state = replace(self.state, next_seq=seq + 1)
            return []
        self.join_seconds.append(time.perf_counter() - t0)
        return [seq]

    def stats(self) -> dict[str, float]:
        """Return counts and join-latency figures (ms) for the global map message."""
        ms = np.asarray(self.join_seconds) * 1e3
        return {
            "n_joined": float(self.state.n_joined),
            "n_rejected": float(self.n_rejected),
            "last_join_ms": float(ms[-1]) if ms.size else 0.0,
            "join_ms_p50": float(np.percentile(ms, 50)) if ms.size else 0.0,
            "join_ms_p99": float(np.percentile(ms, 99)) if ms.size else 0.0,
            "join_ms_max": float(ms.max()) if ms.size else 0.0,
            "join_seconds_total": float(ms.sum() / 1e3),
        }
