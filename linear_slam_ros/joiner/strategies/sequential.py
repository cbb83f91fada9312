"""Exact sequential joining of pose maps (Sec. 5.1), in covariance form."""

from __future__ import annotations

from typing import ClassVar

from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.joiner.strategy import FoldStrategy, JoinMethod, MapType
from linear_slam_ros.joining.sequential import SequentialState, sequential_step


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
    """Rank-c updates of one dense matrix: one BLAS thread is twice as fast on two cores."""

    def empty(self) -> SequentialState:
        """Return the state before any submap."""
        return SequentialState()

    def step(self, state: SequentialState, submap: LocalMap) -> SequentialState:
        """Join one submap (see :func:`~linear_slam_ros.joining.sequential.sequential_step`)."""
        return sequential_step(state, submap)

    def result(self, state: SequentialState) -> LocalMap | None:
        """Return the global map in information form, in the newest end pose's frame."""
        return None if state.global_map is None else state.global_map.to_local_map()

    def express(self, result: LocalMap, pose_id: int) -> LocalMap:
        """Return the map in the frame of pose ``pose_id``."""
        return change_frame(result, pose_id)
