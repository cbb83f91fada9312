"""Divide and conquer (Sec. 5.2), batch and online, for any map type with a pairwise join.

The two shapes of the tree are generic in the map type: :func:`divide_and_conquer` pairs
neighbours level by level; :func:`counter_push` keeps a binary-counter stack whose entries are
joined subtrees and :func:`merge_stack` folds it into one map. Pose maps
(:class:`~linear_slam_ros.core.local_map.LocalMap`) join at the seam (:func:`join_at_seam`);
feature-only maps pass their own join.
"""

from __future__ import annotations

import threading
import time
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import FrameError, InvalidMapError, LinearSlamError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.joining.batched import divide_and_conquer_levels
from linear_slam_ros.joining.chain import compose, relative_end
from linear_slam_ros.joining.pairwise import join_at_seam, to_end_frame

T = TypeVar("T")
FloatArray = npt.NDArray[np.float64]


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
    maps: Sequence[LocalMap], on_level: Callable[[float, int], None] | None = None
) -> LocalMap:
    """Join pose maps by divide and conquer, at the seams; the result is in the last end pose's frame.

    The tree of ``divide_and_conquer(maps, join_at_seam)``, each level's joins done together
    (:func:`~linear_slam_ros.joining.batched.divide_and_conquer_levels`: the same result up to round-off).

    Args:
        maps: local maps in order; map ``i + 1`` starts where map ``i`` ends.
        on_level: called after every level of the tree with its wall time (s) and its number of pairwise joins.

    Raises:
        InvalidMapError: ``maps`` is empty, or the maps differ in dimension.
        FrameError: neighbours share no frame.
    """
    return to_end_frame(divide_and_conquer_levels(maps, on_level))


class Deferred:
    """A pairwise join at the seam, described now and computed at most once, by whoever needs it first.

    It stands for ``join_at_seam(left, right)`` as a value: :meth:`value` returns that map,
    computing it on first use (and the inputs' first if they are deferred too). A background
    worker (:class:`~linear_slam_ros.joining.background.MergeWorker`) computes deferred joins
    ahead of time, in the order they were made, so that the thread joining arrivals never runs
    a large merge; the result is the same map whichever thread computes it. Thread-safe: one
    lock per join, taken parent before inputs, so two threads never wait on each other in a cycle.

    Attributes:
        dim: 2 or 3.
        end_id: end pose of the joined map (the later input's, or the earlier's if it has none).
        count: submaps the joined map is made of.
        size: state scalars of the two inputs together (an upper bound of the joined map's).
    """

    def __init__(self, left: Entry, right: Entry, count: int) -> None:
        self.dim: int = left.dim
        self.end_id: int | None = right.end_id if right.end_id is not None else left.end_id
        self.count = count
        self.size = entry_size(left) + entry_size(right)
        self._inputs: tuple[Entry, Entry] | None = (left, right)
        self._result: LocalMap | None = None
        self._error: LinearSlamError | None = None  # a failed join fails again the same way: kept, not recomputed
        self._lock = threading.Lock()

    @property
    def done(self) -> bool:
        """Whether the joined map has been computed."""
        return self._result is not None

    @property
    def failed(self) -> bool:
        """Whether the join failed (:meth:`value` raises that error again without recomputing it)."""
        return self._error is not None

    @property
    def inputs(self) -> tuple[Entry, Entry] | None:
        """The two entries joined (``None`` once computed: they are released)."""
        return self._inputs

    def value(self) -> LocalMap:
        """Return the joined map, computing it (and any deferred input) if nobody has yet.

        Raises:
            LinearSlamError: the join fails (the same error a synchronous join would raise).
        """
        result = self._result
        if result is None:
            self.compute()
            result = self._result
        assert result is not None
        return result

    def compute(self) -> int:
        """Compute the joined map if nobody has; return how many joins this call made (it and the deferred
        inputs it computed; 0: made by another thread; what the worker counts).

        Raises:
            LinearSlamError: the join fails (the same error a synchronous join would raise).
        """
        if self._result is not None:
            return 0
        with self._lock:
            if self._result is not None:  # another thread computed it while this one waited
                return 0
            if self._error is not None:
                raise self._error
            assert self._inputs is not None
            try:
                made = sum(e.compute() for e in self._inputs if isinstance(e, Deferred))
                left, right = (resolve(e) for e in self._inputs)
                result = join_at_seam(left, right)
            except LinearSlamError as exc:  # deterministic: the same inputs fail the same way (other errors: retried)
                self._error = exc
                raise
            _ = result.key_set  # built here, not by the thread that next looks a pose up in it
            self._result = result
            self._inputs = None  # the inputs' memory goes as soon as nothing else holds them
            return made + 1


Entry = LocalMap | Deferred
"""A stack entry of online divide and conquer: a joined map, or a join still to compute."""


def resolve(entry: Entry) -> LocalMap:
    """Return the map an entry stands for (computing a deferred join if needed)."""
    return entry.value() if isinstance(entry, Deferred) else entry


def entry_size(entry: Entry) -> int:
    """State scalars of an entry (for a deferred join, its inputs' together)."""
    return entry.size if isinstance(entry, Deferred) else entry.state_dim


def pending_joins(stack: Sequence[Entry]) -> list[Deferred]:
    """Return the deferred joins not yet computed that ``stack`` depends on, inputs before results."""
    out: list[Deferred] = []
    seen: set[int] = set()

    def visit(entry: Entry) -> None:
        if not isinstance(entry, Deferred) or entry.done or entry.failed or id(entry) in seen:
            return
        inputs = entry.inputs
        if inputs is not None:
            visit(inputs[0])
            visit(inputs[1])
        if not entry.done:
            seen.add(id(entry))
            out.append(entry)

    for e in stack:
        visit(e)
    return out


def leaf_entries(stack: Sequence[Entry], counts: Sequence[int]) -> tuple[tuple[Entry, ...], tuple[int, ...]]:
    """Return entries that together make up ``stack``, in order, and their counts, without computing any join.

    A map or a computed deferred join stays as it is; a deferred join not computed yet is replaced
    by its inputs, recursively, each holding half its submaps (the online stack joins entries of
    equal count). Every entry starts where the one before it ends (it is in, or holds, that end
    pose), as the stack's entries do.
    """
    entries: list[Entry] = []
    entry_counts: list[int] = []

    def add(entry: Entry, count: int) -> None:
        inputs = entry.inputs if isinstance(entry, Deferred) else None
        if inputs is None:  # a map, or a join computed by now (its inputs are released then)
            entries.append(entry)
            entry_counts.append(count)
            return
        add(inputs[0], count // 2)
        add(inputs[1], count - count // 2)

    for entry, count in zip(stack, counts, strict=True):
        add(entry, count)
    return tuple(entries), tuple(entry_counts)


def leaf_maps(stack: Sequence[Entry]) -> list[LocalMap]:
    """Return maps that together make up ``stack``, in order, without computing any join (:func:`leaf_entries`).

    Poses can be chained along them (:func:`~linear_slam_ros.joining.chain.chain_end_pose`).
    """
    return [resolve(entry) for entry in leaf_entries(stack, [0] * len(stack))[0]]


Relative = tuple[int, FloatArray] | None
"""An entry's end pose id and pose seen from the end of the entry before it (``None``: no chain)."""
_Cached = tuple["weakref.ref[Entry]", int, tuple[Relative, Relative] | None, Relative]
"""A :class:`StackChain` cache entry: the entry (weakly: a merge that lands lets its inputs go, and the
cache must not keep them), its start pose id, its inputs' relative poses (``None`` for a computed
entry) and its own."""


class StackChain:
    """The newest end pose chained along an online D&C stack, without computing any join (the node's ``pose``).

    :func:`~linear_slam_ros.joining.chain.chain_end_pose` over :func:`leaf_maps`, computed over the
    stack's tree instead: a computed entry contributes its end pose seen from its start (the end
    of the entry before it, :func:`~linear_slam_ros.joining.chain.relative_end`), a deferred one the
    composition of its two inputs' (recursively). Each is kept while the entry and its inputs'
    relative poses are the same objects: an arrival composes along the entries it created and the
    stack's few entries, a merge that lands along the path above it. Chaining the leaves again from
    the first one that changed cost every part after it: hundreds of them while a 3D stream's large
    merges were pending (garage3d-5000 through the node: ``pose`` published 115-270 ms after its
    submap's arrival, README "Scale"). The same pose up to round-off (composition is associative).
    A cache only: the result depends on the stack alone.
    """

    def __init__(self) -> None:
        self._relative: dict[int, _Cached] = {}  # by the entry's id, valid while the weak reference is to it
        self._prefix: list[tuple[weakref.ref[Entry], Relative, tuple[int, FloatArray]]] = []  # the last stack, chained

    def end_pose(self, stack: Sequence[Entry], frame_pose_id: int) -> tuple[int, FloatArray] | None:
        """Return the newest end pose in the frame of pose ``frame_pose_id`` (see :func:`chain_end_pose`)."""
        relative: dict[int, _Cached] = {}
        prefix: list[tuple[weakref.ref[Entry], Relative, tuple[int, FloatArray]]] = []
        end: tuple[int, FloatArray | None] = (frame_pose_id, None)
        result: tuple[int, FloatArray] | None = None
        for i, entry in enumerate(stack):
            step = self._entry(entry, end[0], relative)
            if step is None:
                break
            same = i < len(self._prefix) and self._prefix[i][0]() is entry and self._prefix[i][1] is step
            if same and (i == 0 or prefix[-1][2] is self._prefix[i - 1][2]):
                chained = self._prefix[i][2]
            else:
                chained = step if end[1] is None else (step[0], compose(entry.dim, end[1], step[1]))
            prefix.append((weakref.ref(entry), step, chained))
            end = chained
        else:
            result = prefix[-1][2] if prefix else None
        self._relative, self._prefix = relative, prefix  # only what this stack holds is kept
        return result

    def _entry(self, entry: Entry, start_id: int, memo: dict[int, _Cached]) -> Relative:
        """Return the entry's relative pose from ``start_id``, reused while the entry and its inputs' are the same."""
        inputs = entry.inputs if isinstance(entry, Deferred) else None  # read once: a worker may finish it meanwhile
        parts: tuple[Relative, Relative] | None = None  # a computed entry's own pose depends on nothing else
        if inputs is not None:  # the inputs' composed (their own caches decide whether they changed)
            left = self._entry(inputs[0], start_id, memo)
            parts = (left, None if left is None else self._entry(inputs[1], left[0], memo))
        cached = self._relative.get(id(entry))
        if cached is not None and cached[0]() is entry and cached[1] == start_id and _same(cached[2], parts):
            step = cached[3]
        elif parts is None:
            step = relative_end(resolve(entry), start_id)  # computed: resolve only reads its result
        else:
            left, right = parts
            step = None if left is None or right is None else (right[0], compose(entry.dim, left[1], right[1]))
        memo[id(entry)] = (weakref.ref(entry), start_id, parts, step)
        return step


def _same(a: tuple[Relative, Relative] | None, b: tuple[Relative, Relative] | None) -> bool:
    """Whether two inputs' relative poses are the same objects (both ``None``: a computed entry)."""
    if a is None or b is None:
        return a is b
    return a[0] is b[0] and a[1] is b[1]


@dataclass(frozen=True)
class OnlineDCState:
    """State of online divide-and-conquer joining: a binary-counter stack of joined maps.

    Attributes:
        stack: joined maps, oldest first, each in the frame of its seam (or its own start);
            ``counts[i]`` submaps make up ``stack[i]``, and counts strictly decrease along the
            stack (each a power of two, except a first entry seeded from a map joined elsewhere:
            it keeps its count, and merges when an entry of that count forms). An entry may be a :class:`Deferred` join.
        counts: number of submaps in each stack entry.
        n_joined: total number of submaps joined.
        defer_above: joins of entries with more state scalars than this together are deferred
            (left to a background worker), as is any join with a deferred input; ``None`` joins
            everything at once. Only when a join is computed depends on it, never its result.
    """

    stack: tuple[Entry, ...] = ()
    counts: tuple[int, ...] = ()
    n_joined: int = 0
    defer_above: int | None = None


def online_dc_step(state: OnlineDCState, submap: LocalMap) -> OnlineDCState:
    """Push a submap and merge equal-sized neighbours (a pure function of state and submap).

    Each merge is one :func:`join_at_seam`; a submap triggers as many merges as trailing ones
    in the binary count of joined submaps, so the amortised cost per submap stays constant and
    the largest merge happens once every power of two. With ``state.defer_above`` set, the large
    merges are :class:`Deferred` instead: the step stays cheap, and the merges are the same.

    Raises:
        FrameError: the submap neither is in nor holds the end pose of the newest stack entry.
    """
    if state.stack:
        top = state.stack[-1]
        if submap.dim != top.dim:  # checked now: an odd submap waits on the stack unjoined
            raise InvalidMapError(f"submap {submap.name!r} is {submap.dim}D, the global map is {top.dim}D")
        seam = top.end_id
        if seam is not None and submap.frame_id != seam and not submap.has_pose(seam):
            raise FrameError(
                f"submap {submap.name!r} is in the frame of pose {submap.frame_id} and does not hold pose {seam}, "
                "the end pose of the global map"
            )
    if state.defer_above is None:
        new_stack, new_counts = counter_push(state.stack, state.counts, submap, _join_now)
        return replace(state, stack=new_stack, counts=new_counts, n_joined=state.n_joined + 1)
    limit = state.defer_above
    stack: list[Entry] = [e.value() if isinstance(e, Deferred) and e.done else e for e in state.stack]
    stack.append(submap)
    counts = [*state.counts, 1]
    while len(counts) >= 2 and counts[-1] == counts[-2]:
        right, left = stack.pop(), stack.pop()
        count = counts.pop() + counts.pop()
        big = isinstance(left, Deferred) or isinstance(right, Deferred) or entry_size(left) + entry_size(right) > limit
        stack.append(Deferred(left, right, count) if big else join_at_seam(left, right))  # type: ignore[arg-type]
        counts.append(count)
    return replace(state, stack=tuple(stack), counts=tuple(counts), n_joined=state.n_joined + 1)


def _join_now(left: Entry, right: Entry) -> Entry:
    return join_at_seam(resolve(left), resolve(right))


def online_dc_result(state: OnlineDCState) -> LocalMap:
    """Merge the stack at the seams; the result is in the frame of the newest end pose.

    Deferred joins not computed yet are computed first (or waited for, if a worker is on them).

    Raises:
        InvalidMapError: nothing joined yet.
    """
    return to_end_frame(merge_stack([resolve(e) for e in state.stack], join_at_seam))
