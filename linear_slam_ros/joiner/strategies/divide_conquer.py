"""Divide and conquer of pose maps (Sec. 5.2): online (binary-counter stack) and batch."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.core.runtime import MMAP_THRESHOLD_RETURN, MMAP_THRESHOLD_REUSE
from linear_slam_ros.joiner.strategy import PER_LEVEL, BatchStrategy, FoldStrategy, JoinMethod, MapType, PoseEstimate, Progress
from linear_slam_ros.joining.divide_conquer import (
    Deferred,
    OnlineDCState,
    StackChain,
    join_divide_and_conquer,
    online_dc_result,
    online_dc_step,
    pending_joins,
)
from linear_slam_ros.joining.gate import EntryCache, Marginal, online_dc_holds, online_dc_marginal_by_entries


class OnlineDC(FoldStrategy[OnlineDCState, LocalMap]):
    """Each submap pushed on a binary-counter stack; the stack is merged for output."""

    method: ClassVar[JoinMethod] = JoinMethod.ONLINE_DC
    map_type: ClassVar[MapType] = MapType.AS_IS
    online: ClassVar[bool] = True
    result_type: ClassVar[type] = LocalMap
    blas_threads: ClassVar[int | None] = None
    mmap_threshold: ClassVar[int] = MMAP_THRESHOLD_RETURN
    finish_in_last_step: ClassVar[bool] = True

    def empty(self) -> OnlineDCState:
        """Return the empty stack."""
        return OnlineDCState()

    def step(self, state: OnlineDCState, submap: LocalMap) -> OnlineDCState:
        """Push one submap (see :func:`~linear_slam_ros.joining.divide_conquer.online_dc_step`)."""
        return online_dc_step(state, submap)

    def result(self, state: OnlineDCState) -> LocalMap | None:
        """Return the merged stack in the newest end pose's frame (``None`` when empty)."""
        return online_dc_result(state) if state.stack else None

    def express(self, result: LocalMap, pose_id: int) -> LocalMap:
        """Return the map in the frame of pose ``pose_id``."""
        return change_frame(result, pose_id)

    def seed(self, joined: LocalMap, n_submaps: int) -> OnlineDCState:
        """Return a stack of one entry, the joined map, counting ``n_submaps`` submaps."""
        return OnlineDCState(stack=(joined,), counts=(n_submaps,), n_joined=n_submaps)

    def defer(self, state: OnlineDCState, above_scalars: int | None) -> OnlineDCState:
        """Defer the merges of more than ``above_scalars`` state scalars (see :class:`OnlineDCState`)."""
        return replace(state, defer_above=above_scalars)

    def pending(self, state: OnlineDCState) -> list[Deferred]:
        """Return the stack's merges not computed yet, inputs first."""
        return pending_joins(state.stack)

    def __init__(self) -> None:
        self._chain = StackChain()  # a cache only: the result depends on the state alone
        self._entries = EntryCache()  # a cache only, for marginal()

    def current_pose(self, state: OnlineDCState, frame_pose_id: int) -> PoseEstimate | None:
        """Chain the newest end pose along the stack's parts, computing no merge (only what changed: :class:`StackChain`)."""
        return self._chain.end_pose(state.stack, frame_pose_id)

    def marginal(self, state: OnlineDCState, keys: npt.NDArray[np.int64]) -> Marginal | None:
        """Return the merged stack's marginal of ``keys``: each entry reduced (its factorisation kept), the small maps joined.

        See :func:`~linear_slam_ros.joining.gate.online_dc_marginal_by_entries`. Merges still deferred
        are made first (or waited for, when the background worker is making them): folded from their
        inputs instead, the marginal would be linearised in another grouping (centimetres and 0.1% of
        covariance apart on VicPark200), so the gate's NIS, and the variance factor in the state,
        would depend on how far the worker had got.
        """
        for merge in self.pending(state):  # inputs first
            merge.value()
        return online_dc_marginal_by_entries(state, keys, self._entries)

    def holds(self, state: OnlineDCState, keys: npt.NDArray[np.int64]) -> bool:
        """Whether a part of the stack holds any of ``keys`` (their key sets and frame poses)."""
        return online_dc_holds(state, keys)


class BatchDC(BatchStrategy[LocalMap]):
    """The submaps collected, then joined by divide and conquer when the result is asked for."""

    method: ClassVar[JoinMethod] = JoinMethod.DC
    map_type: ClassVar[MapType] = MapType.AS_IS
    result_type: ClassVar[type] = LocalMap
    run_step: ClassVar[str] = PER_LEVEL
    blas_threads: ClassVar[int | None] = None
    mmap_threshold: ClassVar[int] = MMAP_THRESHOLD_REUSE  # a level's arrays are large: reused, not mapped anew (10% faster)

    def express(self, result: LocalMap, pose_id: int) -> LocalMap:
        """Return the map in the frame of pose ``pose_id``."""
        return change_frame(result, pose_id)

    def run(self, maps: Sequence[LocalMap], progress: Progress | None = None) -> tuple[LocalMap, list[float]]:
        """Join by divide and conquer, timing each level of the tree (its pairwise joins are done together)."""
        steps: list[float] = []

        def on_level(seconds: float, joins: int) -> None:
            steps.append(seconds)
            if progress is not None:
                progress(joins)

        return join_divide_and_conquer(maps, on_level), steps
