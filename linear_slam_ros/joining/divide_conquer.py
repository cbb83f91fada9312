"""Divide and conquer (Sec. 5.2), batch and online, for any map type with a pairwise join.

The two shapes of the tree are generic in the map type: :func:`divide_and_conquer` pairs
neighbours level by level; :func:`counter_push` keeps a binary-counter stack whose entries are
joined subtrees and :func:`merge_stack` folds it into one map. Pose maps
(:class:`~linear_slam_ros.core.local_map.LocalMap`) join at the seam (:func:`join_at_seam`);
feature-only maps pass their own join.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypeVar

from linear_slam_ros.core.errors import FrameError, InvalidMapError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.joining.pairwise import join_at_seam, to_end_frame

T = TypeVar("T")


def divide_and_conquer(
    items: Sequence[T], join: Callable[[T, T], T], on_join: Callable[[float], None] | None = None
) -> T:
    """Join items level by level: ``(1, 2), (3, 4), ...``; an odd last item moves up unchanged.

    Args:
        items: maps in order; each later one is joined to the earlier as ``join(earlier, later)``.
        join: the pairwise join.
        on_join: called after every pairwise join with its wall time in seconds.

    Raises:
        InvalidMapError: ``items`` is empty.
    """
    if not items:
        raise InvalidMapError("no local maps to join")
    level = list(items)
    while len(level) > 1:
        nxt = []
        for i in range(0, len(level) - 1, 2):
            t0 = time.perf_counter()
            nxt.append(join(level[i], level[i + 1]))
            if on_join is not None:
                on_join(time.perf_counter() - t0)
        if len(level) % 2:
            nxt.append(level[-1])
        level = nxt
    return level[0]


def counter_push(
    stack: Sequence[T], counts: Sequence[int], item: T, join: Callable[[T, T], T]
) -> tuple[tuple[T, ...], tuple[int, ...]]:
    """Push ``item`` on a binary-counter stack and merge equal-sized neighbours with ``join``.

    Args:
        stack: joined entries, oldest first.
        counts: number of items in each entry (powers of two, strictly decreasing).
        item: the new item (count 1).
        join: ``join(older, newer)``.

    Returns:
        The new stack and counts.
    """
    stack_l, counts_l = [*stack, item], [*counts, 1]
    while len(counts_l) >= 2 and counts_l[-1] == counts_l[-2]:
        right, left = stack_l.pop(), stack_l.pop()
        c = counts_l.pop() + counts_l.pop()
        stack_l.append(join(left, right))
        counts_l.append(c)
    return tuple(stack_l), tuple(counts_l)


def merge_stack(stack: Sequence[T], join: Callable[[T, T], T]) -> T:
    """Fold a stack into one map, newest entries first (so the small joins come first).

    Raises:
        InvalidMapError: the stack is empty.
    """
    if not stack:
        raise InvalidMapError("no submaps joined yet")
    result = stack[-1]
    for older in reversed(stack[:-1]):
        result = join(older, result)
    return result


def join_divide_and_conquer(
    maps: Sequence[LocalMap], on_join: Callable[[float], None] | None = None
) -> LocalMap:
    """Join pose maps by divide and conquer, at the seams; the result is in the last end pose's frame.

    Args:
        maps: local maps in order; map ``i + 1`` starts where map ``i`` ends.
        on_join: called after every pairwise join with its wall time in seconds.

    Raises:
        InvalidMapError: ``maps`` is empty.
        FrameError: neighbours share no frame.
    """
    return to_end_frame(divide_and_conquer(maps, join_at_seam, on_join))


@dataclass(frozen=True)
class OnlineDCState:
    """State of online divide-and-conquer joining: a binary-counter stack of joined maps.

    Attributes:
        stack: joined maps, oldest first, each in the frame of its seam (or its own start);
            ``counts[i]`` submaps make up ``stack[i]``, and counts strictly decrease along the
            stack (each a power of two).
        counts: number of submaps in each stack entry.
        n_joined: total number of submaps joined.
    """

    stack: tuple[LocalMap, ...] = ()
    counts: tuple[int, ...] = ()
    n_joined: int = 0


def online_dc_step(state: OnlineDCState, submap: LocalMap) -> OnlineDCState:
    """Push a submap and merge equal-sized neighbours (a pure function of state and submap).

    Each merge is one :func:`join_at_seam`; a submap triggers as many merges as trailing ones
    in the binary count of joined submaps, so the amortised cost per submap stays constant and
    the largest merge happens once every power of two.

    Raises:
        FrameError: the submap neither is in nor holds the end pose of the newest stack entry.
    """
    if state.stack:
        if submap.dim != state.stack[-1].dim:  # checked now: an odd submap waits on the stack unjoined
            raise InvalidMapError(f"submap {submap.name!r} is {submap.dim}D, the global map is {state.stack[-1].dim}D")
        seam = state.stack[-1].end_id
        if seam is not None and submap.frame_id != seam and not submap.has_pose(seam):
            raise FrameError(
                f"submap {submap.name!r} is in the frame of pose {submap.frame_id} and does not hold pose {seam}, "
                "the end pose of the global map"
            )
    new_stack, new_counts = counter_push(state.stack, state.counts, submap, join_at_seam)
    return OnlineDCState(new_stack, new_counts, state.n_joined + 1)


def online_dc_result(state: OnlineDCState) -> LocalMap:
    """Merge the stack at the seams; the result is in the frame of the newest end pose.

    Raises:
        InvalidMapError: nothing joined yet.
    """
    return to_end_frame(merge_stack(state.stack, join_at_seam))
