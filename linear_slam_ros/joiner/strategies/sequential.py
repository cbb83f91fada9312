"""Exact sequential joining of pose maps (Sec. 5.1), in covariance form."""

from __future__ import annotations

import logging
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import LocalMap, pose_key
from linear_slam_ros.core.runtime import MMAP_THRESHOLD_REUSE
from linear_slam_ros.joiner.strategy import FoldStrategy, JoinMethod, MapType, PoseEstimate
from linear_slam_ros.joining.chain import chain_end_pose
from linear_slam_ros.joining.gate import Marginal
from linear_slam_ros.joining.sequential import CovarianceMap, SequentialState, sequential_step

logger = logging.getLogger(__name__)

SEQUENTIAL_MAX_SCALARS = 3000
"""State scalars up to which exact sequential joining keeps up with a stream: beyond, each submap
costs O(n^2) in the global state size n (tens of ms at 3000 scalars on two cores, growing)."""


class Sequential(FoldStrategy[SequentialState, LocalMap]):
    """Each submap joined into the global map in the robocentric frame of the newest end pose.

    O(n^2) per submap (n: global state size): the exact recursion of the paper, for maps up to
    a few thousand state scalars.
    """

    method: ClassVar[JoinMethod] = JoinMethod.SEQUENTIAL
    map_type: ClassVar[MapType] = MapType.AS_IS
    online: ClassVar[bool] = True
    result_type: ClassVar[type] = LocalMap
    blas_threads: ClassVar[int | None] = 1
    mmap_threshold: ClassVar[int] = MMAP_THRESHOLD_REUSE
    """Rank-c updates of one dense matrix: one BLAS thread is twice as fast on two cores."""

    def empty(self) -> SequentialState:
        """Return the state before any submap."""
        return SequentialState()

    def step(self, state: SequentialState, submap: LocalMap) -> SequentialState:
        """Join one submap (see :func:`~linear_slam_ros.joining.sequential.sequential_step`).

        Logs one warning when the global map first grows past :data:`SEQUENTIAL_MAX_SCALARS`.
        """
        joined = sequential_step(state, submap)
        before = 0 if state.global_map is None else state.global_map.state_dim
        after = 0 if joined.global_map is None else joined.global_map.state_dim
        if before <= SEQUENTIAL_MAX_SCALARS < after:
            logger.warning(
                "mode 'sequential' passed %d state scalars (%d now): each submap now costs O(n^2) and the joiner "
                "will fall behind a fast stream; use mode 'online-dc' for long streams",
                SEQUENTIAL_MAX_SCALARS, after,
            )
        return joined

    def seed(self, joined: LocalMap, n_submaps: int) -> SequentialState:
        """Return the joined map in covariance form (one dense inversion, O(n^3)) in its own frame."""
        return SequentialState(CovarianceMap.from_local_map(joined), n_submaps)

    def result(self, state: SequentialState) -> LocalMap | None:
        """Return the global map in information form, in the newest end pose's frame."""
        return None if state.global_map is None else state.global_map.to_local_map()

    def express(self, result: LocalMap, pose_id: int) -> LocalMap:
        """Return the map in the frame of pose ``pose_id``."""
        return change_frame(result, pose_id)

    def current_pose(self, state: SequentialState, frame_pose_id: int) -> PoseEstimate | None:
        """Return the end pose, from the global map's estimate of pose ``frame_pose_id`` (its frame is the end pose)."""
        return None if state.global_map is None else chain_end_pose([state.global_map], frame_pose_id)

    def marginal(self, state: SequentialState, keys: npt.NDArray[np.int64]) -> Marginal | None:
        """Return the marginal of ``keys`` from the covariance form: ``S_cc = Q_c S~_cc Q_c^T``, O(c^2)."""
        return None if state.global_map is None else Marginal.of_covariance_map(state.global_map, keys)

    def holds(self, state: SequentialState, keys: npt.NDArray[np.int64]) -> bool:
        """Whether the global map holds any of ``keys`` (its key set and its frame pose)."""
        m = state.global_map
        if m is None:
            return False
        wanted = np.asarray(keys).tolist()
        return pose_key(m.frame_id) in wanted or any(map(m.key_set.__contains__, wanted))
