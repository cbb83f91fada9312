"""The joining-strategy seam: one small protocol for "a way of joining a stream of submaps".

A strategy is keyed by (:class:`JoinMethod`, :class:`MapType`) in
:mod:`linear_slam_ros.joiner.registry`. Its state is one immutable value and :meth:`step` a pure
function of (state, submap), so the joiner around it can keep, compare, save or restore states
freely. Everything that drives joining (the node, the CLI, the benchmark) goes through a
strategy; none of them dispatches on the method or the map type.

Room for what comes next: a gate runs between the arrival of a submap and :meth:`step` (it
reads the state and the submap, and either lets the step commit or rejects the submap); an
exact snapshot walks the state value (frozen dataclasses of numpy arrays and maps) and restores
it bit for bit.
"""

from __future__ import annotations

import enum
import time
from collections.abc import Callable, Sequence
from typing import ClassVar, Generic, Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import InvalidMapError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.joining.divide_conquer import Deferred
from linear_slam_ros.joining.gate import Marginal


class JoinMethod(enum.StrEnum):
    """How submaps are joined (the CLI's ``--method``, the node's ``mode``)."""

    SEQUENTIAL = "sequential"
    """Exact sequential joining in the robocentric end-pose frame (Sec. 5.1)."""
    DC = "dc"
    """Batch divide and conquer (Sec. 5.2)."""
    ONLINE_DC = "online-dc"
    """Divide and conquer as submaps arrive: a binary-counter stack, merged for output."""


class MapType(enum.StrEnum):
    """What the joiner keeps of the submaps (the node's ``map_type``)."""

    AS_IS = "as-is"
    """Join the submaps' variables as they are (pose-feature, pose-only)."""
    FEATURE_ONLY = "feature-only"
    """Marginalise the poses and join feature-only maps in feature-defined frames (Sec. 7)."""


StateT = TypeVar("StateT")
ResultT = TypeVar("ResultT")
PER_SUBMAP = "per submap"
PER_JOIN = "per pairwise join"
PER_LEVEL = "per tree level"
Progress = Callable[[int], None]
"""Called with the number of steps (submaps or pairwise joins) just completed."""
PoseEstimate = tuple[int, npt.NDArray[np.float64]]
"""A pose id and its pose (``(3,)`` or ``(6,)``) in a stated frame."""


class JoinStrategy(Protocol[StateT, ResultT]):
    """A way of joining a stream of submaps.

    Attributes:
        method: the registry key's method.
        map_type: the registry key's map type.
        online: whether :meth:`step` does the joining as submaps arrive (the node accepts only
            online strategies; a batch strategy's step only collects submaps).
        result_type: the type of the joined map (``LocalMap`` or ``FeatureMap``).
        blas_threads: BLAS threads measured best for this strategy (``None``: leave as is).
        mmap_threshold: glibc's mmap threshold measured best for this strategy, bytes
            (:func:`~linear_slam_ros.core.runtime.tune_allocator`).
        run_step: what one timed step of :meth:`run` is: ``"per submap"``, ``"per pairwise join"`` or
            ``"per tree level"``.
    """

    method: ClassVar[JoinMethod]
    map_type: ClassVar[MapType]
    online: ClassVar[bool]
    result_type: ClassVar[type]
    blas_threads: ClassVar[int | None]
    mmap_threshold: ClassVar[int]
    run_step: ClassVar[str]

    def empty(self) -> StateT:
        """Return the state before any submap."""
        ...

    def step(self, state: StateT, submap: LocalMap) -> StateT:
        """Return the state after ``submap`` (pure: ``state`` is not modified).

        Raises:
            LinearSlamError: the submap cannot be joined; the caller keeps ``state``.
        """
        ...

    def result(self, state: StateT) -> ResultT | None:
        """Return the joined map (``None`` while there is none).

        Pose maps are in the robocentric frame of the newest end pose; feature-only maps in the
        frame of their longest-baseline features.
        """
        ...

    def express(self, result: ResultT, pose_id: int) -> ResultT:
        """Return ``result`` in the frame of pose ``pose_id`` (unchanged for maps without pose frames)."""
        ...

    def seed(self, joined: ResultT, n_submaps: int) -> StateT:
        """Return the state of a map already joined from ``n_submaps`` submaps (islands joined into one).

        Raises:
            NotImplementedError: the strategy cannot start from a joined map (only strategies of
                pose maps that join online can: the ones that have islands).
        """
        ...

    def defer(self, state: StateT, above_scalars: int | None) -> StateT:
        """Return ``state`` set to defer its joins of more than ``above_scalars`` state scalars.

        A deferred join is computed by a background worker (:meth:`pending` lists them) or by
        :meth:`result`, whichever comes first; deferring changes when a join is computed, never
        its result. ``None`` joins everything in :meth:`step`. Strategies without large joins
        return ``state`` unchanged.
        """
        ...

    def pending(self, state: StateT) -> list[Deferred]:
        """Return the deferred joins of ``state`` not computed yet, inputs before results."""
        ...

    def current_pose(self, state: StateT, frame_pose_id: int) -> PoseEstimate | None:
        """Return the newest end pose in pose ``frame_pose_id``'s frame, cheaply (no global solve).

        ``None`` when the strategy's maps have no poses or the pose is not known yet.
        """
        ...

    def marginal(self, state: StateT, keys: npt.NDArray[np.int64]) -> Marginal | None:
        """Return the joined map's marginal (estimate and covariance) of the variables among ``keys`` it holds.

        What the χ² gate (:mod:`~linear_slam_ros.joining.gate`) compares a submap with, in the map's
        frame, without forming the whole joined map when the strategy can avoid it. ``None`` when
        the map holds none of them, or the strategy cannot gate (batch and feature-only strategies).

        Raises:
            SolverError: an information or covariance matrix is not positive definite.
        """
        ...

    def holds(self, state: StateT, keys: npt.NDArray[np.int64]) -> bool | None:
        """Whether the joined map holds any of ``keys``, cheaply (no join, no solve).

        The map's frame pose counts as held: a submap holding it as a variable shares it with the
        map. ``None`` when the strategy cannot tell cheaply (those that cannot gate).
        """
        ...

    def run(self, maps: Sequence[LocalMap], progress: Progress | None = None) -> tuple[ResultT, list[float]]:
        """Join a whole sequence, timing each step.

        Returns:
            The joined map and the wall time of each step in seconds (per submap, or per
            pairwise join for batch strategies).

        Raises:
            InvalidMapError: no map results from ``maps``.
            LinearSlamError: a submap cannot be joined.
        """
        ...


class FoldStrategy(Generic[StateT, ResultT]):
    """Base of streaming strategies: :meth:`run` folds :meth:`step` over the maps.

    Subclasses define ``empty``, ``step``, ``result``, ``express`` and the class attributes of
    :class:`JoinStrategy`.

    Attributes:
        finish_in_last_step: add the time of the final :meth:`result` to the last step's (the
            online D&C stack's final merge is part of joining the last submap).
    """

    finish_in_last_step: ClassVar[bool] = False
    run_step: ClassVar[str] = PER_SUBMAP

    def empty(self) -> StateT:  # pragma: no cover - abstract
        raise NotImplementedError

    def step(self, state: StateT, submap: LocalMap) -> StateT:  # pragma: no cover - abstract
        raise NotImplementedError

    def result(self, state: StateT) -> ResultT | None:  # pragma: no cover - abstract
        raise NotImplementedError

    def defer(self, state: StateT, above_scalars: int | None) -> StateT:
        """Return ``state`` (nothing to defer; see :meth:`JoinStrategy.defer`)."""
        return state

    def seed(self, joined: ResultT, n_submaps: int) -> StateT:
        """Raise: this strategy cannot start from a joined map (see :meth:`JoinStrategy.seed`)."""
        raise NotImplementedError(f"{type(self).__name__} cannot start from a joined map")

    def pending(self, state: StateT) -> list[Deferred]:
        """Return no deferred joins."""
        return []

    def current_pose(self, state: StateT, frame_pose_id: int) -> PoseEstimate | None:
        """Return ``None``: no cheap current pose (see :meth:`JoinStrategy.current_pose`)."""
        return None

    def marginal(self, state: StateT, keys: npt.NDArray[np.int64]) -> Marginal | None:
        """Return ``None``: this strategy cannot gate (see :meth:`JoinStrategy.marginal`)."""
        return None

    def holds(self, state: StateT, keys: npt.NDArray[np.int64]) -> bool | None:
        """Return ``None``: not known cheaply (see :meth:`JoinStrategy.holds`)."""
        return None

    def run(self, maps: Sequence[LocalMap], progress: Progress | None = None) -> tuple[ResultT, list[float]]:
        """Fold :meth:`step` over ``maps``, one timed step per submap, then take :meth:`result`."""
        steps: list[float] = []
        state = self.empty()
        for m in maps:
            t0 = time.perf_counter()
            state = self.step(state, m)
            steps.append(time.perf_counter() - t0)
            if progress is not None:
                progress(1)
        t0 = time.perf_counter()
        result = self.result(state)
        if self.finish_in_last_step and steps:
            steps[-1] += time.perf_counter() - t0
        if result is None:
            raise InvalidMapError(f"no joined map: the {len(maps)} local maps gave none")
        return result, steps


class BatchStrategy(FoldStrategy[tuple[LocalMap, ...], ResultT]):
    """Base of batch strategies: :meth:`step` collects the submaps, :meth:`result` runs :meth:`run` on them.

    Subclasses define ``run``, ``express`` and the class attributes of :class:`JoinStrategy`.
    """

    online: ClassVar[bool] = False
    run_step: ClassVar[str] = PER_JOIN

    def empty(self) -> tuple[LocalMap, ...]:
        """Return no submaps."""
        return ()

    def step(self, state: tuple[LocalMap, ...], submap: LocalMap) -> tuple[LocalMap, ...]:
        """Collect one submap."""
        return (*state, submap)

    def result(self, state: tuple[LocalMap, ...]) -> ResultT | None:
        """Join the collected submaps (``None`` when there is none)."""
        return self.run(state)[0] if state else None
