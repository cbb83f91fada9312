"""Feature-only (D-SLAM) joining of pose-feature submaps (Sec. 7, 8.3): sequential, online D&C, batch D&C.

The online strategies precondition and marginalise as submaps arrive
(:mod:`linear_slam_ros.feature_only.online`); their batch :meth:`run` converts every group first
and times each pairwise join, as the paper's figures do.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import ClassVar

from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.core.runtime import MMAP_THRESHOLD_RETURN
from linear_slam_ros.feature_only.conversion import to_feature_only
from linear_slam_ros.feature_only.joining import join_features_dc, join_features_sequential
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.feature_only.online import FeatureJoinState, feature_result, feature_step
from linear_slam_ros.feature_only.precondition import precondition
from linear_slam_ros.joiner.strategy import PER_JOIN, BatchStrategy, FoldStrategy, JoinMethod, MapType, Progress

BatchJoin = Callable[[Sequence[FeatureMap], Callable[[float], None] | None], FeatureMap]


def _run_batch(join: BatchJoin, maps: Sequence[LocalMap], progress: Progress | None) -> tuple[FeatureMap, list[float]]:
    """Precondition and convert every group, then join them with ``join``, timing each pairwise join."""
    steps: list[float] = []

    def on_join(seconds: float) -> None:
        steps.append(seconds)
        if progress is not None:
            progress(1)

    return join([to_feature_only(g) for g in precondition(maps)], on_join), steps


class _FeatureStreaming(FoldStrategy[FeatureJoinState, FeatureMap]):
    """Shared by the feature-only strategies: the state, the result and the frame."""

    map_type: ClassVar[MapType] = MapType.FEATURE_ONLY
    result_type: ClassVar[type] = FeatureMap
    blas_threads: ClassVar[int | None] = None
    mmap_threshold: ClassVar[int] = MMAP_THRESHOLD_RETURN
    divide_and_conquer: ClassVar[bool] = False

    def empty(self) -> FeatureJoinState:
        """Return the state before any submap."""
        return FeatureJoinState()

    def step(self, state: FeatureJoinState, submap: LocalMap) -> FeatureJoinState:
        """Take one pose-feature submap (see :func:`~linear_slam_ros.feature_only.online.feature_step`)."""
        return feature_step(state, submap, self.divide_and_conquer)

    def result(self, state: FeatureJoinState) -> FeatureMap | None:
        """Return the feature-only map, the open group included (``None`` while no frame exists)."""
        return feature_result(state)

    def express(self, result: FeatureMap, pose_id: int) -> FeatureMap:
        """Return ``result`` unchanged: a feature-only map has no pose frame."""
        return result


class FeatureSequential(_FeatureStreaming):
    """Closed groups joined one at a time into one feature-only map."""

    method: ClassVar[JoinMethod] = JoinMethod.SEQUENTIAL
    online: ClassVar[bool] = True
    run_step: ClassVar[str] = PER_JOIN

    def run(self, maps: Sequence[LocalMap], progress: Progress | None = None) -> tuple[FeatureMap, list[float]]:
        """Convert every group, then join them in order, timing each pairwise join."""
        return _run_batch(join_features_sequential, maps, progress)


class FeatureOnlineDC(_FeatureStreaming):
    """Closed groups pushed on a binary-counter stack, merged for output."""

    method: ClassVar[JoinMethod] = JoinMethod.ONLINE_DC
    online: ClassVar[bool] = True
    divide_and_conquer: ClassVar[bool] = True


class FeatureBatchDC(BatchStrategy[FeatureMap]):
    """The submaps collected, then preconditioned, converted and joined by divide and conquer."""

    method: ClassVar[JoinMethod] = JoinMethod.DC
    map_type: ClassVar[MapType] = MapType.FEATURE_ONLY
    result_type: ClassVar[type] = FeatureMap
    blas_threads: ClassVar[int | None] = None
    mmap_threshold: ClassVar[int] = MMAP_THRESHOLD_RETURN

    def express(self, result: FeatureMap, pose_id: int) -> FeatureMap:
        """Return ``result`` unchanged: a feature-only map has no pose frame."""
        return result

    def run(self, maps: Sequence[LocalMap], progress: Progress | None = None) -> tuple[FeatureMap, list[float]]:
        """Convert every group, then join them by divide and conquer, timing each pairwise join."""
        return _run_batch(join_features_dc, maps, progress)
