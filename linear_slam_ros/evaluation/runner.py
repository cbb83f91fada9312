"""Run a joining method over a sequence of local maps, timing every step (for CLI and benchmark)."""

from __future__ import annotations

import enum
import resource
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence, TypeVar

from linear_slam_ros.core.errors import InvalidMapError
from linear_slam_ros.joining.pairwise import OnlineDCState, join_divide_and_conquer, online_dc_result, online_dc_step
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.core.runtime import blas_threads, blas_threads_for, tune_allocator
from linear_slam_ros.joining.sequential import SequentialState, sequential_step


class JoinMethod(str, enum.Enum):
    """Joining methods of the CLI and the node."""

    SEQUENTIAL = "sequential"
    """Exact sequential joining in the robocentric end-pose frame (Sec. 5.1)."""
    DC = "dc"
    """Batch divide and conquer (Sec. 5.2)."""
    ONLINE_DC = "online-dc"
    """Divide and conquer as submaps arrive: a binary-counter stack, merged for output."""


class MapType(str, enum.Enum):
    """What the joiner keeps of pose-feature submaps (the node's ``map_type``)."""

    AS_IS = "as-is"
    """Join the submaps' variables as they are (pose-feature, pose-only or feature-only)."""
    FEATURE_ONLY = "feature-only"
    """Marginalise the poses and join feature-only maps in feature-defined frames (Sec. 7)."""


@dataclass(frozen=True)
class JoinRun:
    """A timed joining run.

    Attributes:
        method: the method used.
        result: the joined map, in the frame of the last end pose.
        seconds: wall time of the joining only (no reading, no output), s.
        step_seconds: per-step wall times, s: one per submap for ``sequential`` and ``online-dc``
            (for ``online-dc`` the final merge is added to the last step), one per pairwise join
            for ``dc``.
        n_submaps: number of local maps joined.
    """

    method: JoinMethod
    result: LocalMap
    seconds: float
    step_seconds: tuple[float, ...] = field(repr=False)
    n_submaps: int


def peak_rss_mb() -> float:
    """Return this process's peak resident set size in MiB (Linux ``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


S = TypeVar("S")


def _timed_fold(
    step: Callable[[S, LocalMap], S], state: S, maps: Sequence[LocalMap], steps: list[float],
    progress: Callable[[int], None] | None,
) -> S:
    """Apply ``step`` to each map in turn, appending each step's wall time to ``steps``."""
    for m in maps:
        t0 = time.perf_counter()
        state = step(state, m)
        steps.append(time.perf_counter() - t0)
        if progress:
            progress(1)
    return state


def run_join(
    maps: Sequence[LocalMap], method: JoinMethod | str, progress: Callable[[int], None] | None = None
) -> JoinRun:
    """Join ``maps`` with ``method``, timing each step.

    Args:
        maps: local maps in order.
        method: a :class:`JoinMethod` or its value.
        progress: called with the number of submaps (or joins) just completed.

    Raises:
        InvalidMapError: ``maps`` is empty.
    """
    method = JoinMethod(method)
    if not maps:
        raise InvalidMapError("no local maps to join")
    tune_allocator()
    steps: list[float] = []
    clock = time.perf_counter
    with blas_threads(blas_threads_for(method.value)):
        start = clock()
        if method is JoinMethod.SEQUENTIAL:
            state = _timed_fold(sequential_step, SequentialState(), maps, steps, progress)
            assert state.global_map is not None
            result = state.global_map.to_local_map()
        elif method is JoinMethod.ONLINE_DC:
            dc_state = _timed_fold(online_dc_step, OnlineDCState(), maps, steps, progress)
            t0 = clock()
            result = online_dc_result(dc_state)
            steps[-1] += clock() - t0
        else:

            def on_join(seconds: float) -> None:
                steps.append(seconds)
                if progress:
                    progress(1)

            result = join_divide_and_conquer(maps, on_join)
        seconds = clock() - start
    return JoinRun(method, result, seconds, tuple(steps), len(maps))
