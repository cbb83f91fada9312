"""Gauss-Newton on the map-joining objective (eq. (7)) over a growing stream of submaps.

:class:`OnlineRefiner` keeps every submap it is given and an estimate of all their variables in
the frame of the first submap's frame pose (the origin, not a variable). It works one step at a
time, so its owner (:mod:`linear_slam_ros.refinement.worker`) decides between steps whether to
take in new submaps, publish, or stop:

- :meth:`OnlineRefiner.submit` queues a submap (what the linear joiner fused of it:
  :attr:`~linear_slam_ros.joiner.joiner.SubmapStep.fused`, the gate's splits and held closures
  out); :meth:`OnlineRefiner.linear` hands over the newest linear estimate of the joiner.
- :meth:`OnlineRefiner.absorb` takes the queued submaps in. The previous solution is kept (warm
  start); a variable it has not seen takes the newest linear estimate's value, moved rigidly so
  that the newest pose both share (the anchor) sits where the refined solution has it; a
  variable the linear estimate lacks too is chained from its submap's frame pose, and then, with
  the absorbed variables held, a few Gauss-Newton steps over the batch's submaps alone place the
  batch's new variables (``place_steps``: a chain over a long batch drifts). The objective
  is extended, not rebuilt: the variable layout only grows, so earlier submaps' index records
  stay valid.
- :meth:`OnlineRefiner.iterate` takes one Gauss-Newton step (step halving, angles wrapped): the
  same step as :func:`linear_slam_ros.evaluation.nonlinear.gauss_newton`.

Queued submaps are taken in mid-round (:meth:`OnlineRefiner.absorb_due`) once they number
``growth`` times those already absorbed, or once none has arrived for ``idle_s``: rounds then
cost a geometric series, about ``(1 + growth) / growth`` times the last one, whatever the stream
length. :func:`refine_offline` runs the same refiner over a whole dataset (``join --refine``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core import cholmod, least_squares, solvers
from linear_slam_ros.core.errors import ConfigError, InvalidMapError, LinearSlamError
from linear_slam_ros.core.geometry import (
    angles3,
    points_from_frame,
    points_to_frame,
    pose_size,
    poses_from_frame,
    poses_to_frame,
    rot3,
    single_rotation,
    wrap_angle,
)
from linear_slam_ros.core.local_map import (
    POSE,
    InfoMatrix,
    LocalMap,
    angle_mask,
    block_diagonal,
    pose_key,
    to_csr,
    var_keys,
    var_offsets,
    var_sizes,
)
from linear_slam_ros.evaluation.objective import MapObjective

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class RefinerConfig:
    """When the refiner takes in new submaps, stops iterating and publishes.

    Attributes:
        growth: absorb queued submaps in mid-round once they number at least this fraction of
            the submaps absorbed so far (> 0; 0.25: rounds at 1, 1.25, 1.56, ... times the data).
        idle_s: absorb queued submaps once none has arrived for this long, s (the end of a stream).
        chi2_rtol: a round has converged when a step lowers χ² by at most this fraction.
        streaming_rtol: while submaps still arrive, a round also ends once a step lowers χ² by
            at most this fraction (when above ``chi2_rtol``): its remaining steps would be redone
            over more data at the next round. Once none has arrived for ``settle_s``, a round
            ended so resumes until ``chi2_rtol`` (:meth:`OnlineRefiner.resume`).
        settle_s: how long without a new submap before rounds run to ``chi2_rtol``, s (at least
            ``idle_s``; longer, so that the short pauses of a stream, an output computed by the
            sender for instance, do not make every round run to the end).
        step_tol: ... or when its largest component is below this (m, rad).
        publish_period: least time between two publications of a round that has not converged
            (the worker also publishes, once the stream is idle, each step that is near the optimum).
        max_round_iterations: a round stops after this many steps, not converged (it was reported
            converged: Manhattan capped at 3 steps, 138.44 against 137.91): like a round ended at
            ``streaming_rtol``, it resumes once the stream has settled; offline the result says
            it has not converged.
        reuse_analysis: keep CHOLMOD's analysis (ordering, symbolic factorisation) across the
            steps of a round, whose normal equations share one pattern (with the ``libcholmod``
            backend; otherwise each step solves afresh).
        place_steps: before a round over more submaps of which some new variables were chained
            (the linear estimate lacks them), at most this many Gauss-Newton steps over the new
            submaps alone move the new variables, the absorbed ones held where the refined
            solution has them (0: the new variables start where the warm start put them).
        place_rtol: ... stopping at the first such step that lowers the new submaps' χ² by at
            most this fraction.
    """

    growth: float = 0.25
    idle_s: float = 0.05
    chi2_rtol: float = 1e-7
    streaming_rtol: float = 1e-2
    settle_s: float = 0.5
    step_tol: float = 1e-10
    publish_period: float = 1.0
    max_round_iterations: int = 50
    reuse_analysis: bool = True
    place_steps: int = 2
    place_rtol: float = 1e-3

    def __post_init__(self) -> None:
        checks = (
            ("growth", self.growth > 0 and math.isfinite(self.growth)),
            ("idle_s", self.idle_s >= 0 and math.isfinite(self.idle_s)),
            ("chi2_rtol", 0 <= self.chi2_rtol < 1),
            ("streaming_rtol", 0 <= self.streaming_rtol < 1),
            ("settle_s", self.settle_s >= 0 and math.isfinite(self.settle_s)),
            ("step_tol", self.step_tol >= 0),
            ("publish_period", self.publish_period >= 0),
            ("max_round_iterations", self.max_round_iterations >= 1),
            ("place_steps", self.place_steps >= 0),
            ("place_rtol", 0 <= self.place_rtol < 1),
        )
        for name, ok in checks:
            if not ok:
                raise ConfigError(f"refiner {name}={getattr(self, name)!r} is out of range")


@dataclass(frozen=True)
class Submission:
    """A submap the linear joiner joined, for the refiner.

    Attributes:
        seq: its sequence number.
        submap: what the joiner fused of it, in its own frame pose's frame.
        arrived: when it arrived, ``time.monotonic()`` s (the same clock in every process).
        stamp: its message stamp ``(sec, nanosec)``.
        extra: a further measurement joined with submap ``seq`` (a held loop closure of an earlier
            submap, released then): absorbed like a submap, not counted as one (:attr:`RefinedMap.n_submaps`).
    """

    seq: int
    submap: LocalMap
    arrived: float
    stamp: tuple[int, int] = (0, 0)
    extra: bool = False


@dataclass(frozen=True)
class LinearEstimate:
    """The linear joiner's estimate of its map's variables (no information: only the warm start needs it).

    Attributes:
        dim: 2 or 3.
        frame_id: pose whose frame ``x`` is in (not a variable).
        ids: ``(m,)`` variable ids.
        kinds: ``(m,)`` variable kinds.
        x: ``(n,)`` estimate, m and rad.
        n_submaps: submaps joined into it.
    """

    dim: int
    frame_id: int
    ids: IntArray
    kinds: npt.NDArray[np.int8]
    x: FloatArray
    n_submaps: int

    @classmethod
    def of_map(cls, joined: LocalMap, n_submaps: int) -> LinearEstimate:
        """Take a joined map's estimate (its information is left behind)."""
        return cls(joined.dim, joined.frame_id, joined.ids, joined.kinds, joined.x, n_submaps)


@dataclass(frozen=True)
class RefinedMap:
    """A refined map and where it stands.

    Attributes:
        map: the estimate in the origin's frame (the first submap's frame pose), with information
            ``J^T W J`` at the estimate (or the identity, a placeholder, when asked without).
        chi2: eq. (7) summed over the ``n_submaps`` submaps, at the estimate.
        n_submaps: submaps it covers; ``last_seq``, ``stamp``, ``last_arrival`` (monotonic s): of the newest.
        iterations: Gauss-Newton steps taken since the refiner started.
        converged: whether the round on these submaps has converged to ``chi2_rtol`` (not a round
            ended at ``streaming_rtol`` while submaps still arrived).
        initial_chi2: χ² of the warm start of this round (after the last absorb).
    """

    map: LocalMap
    chi2: float
    n_submaps: int
    last_seq: int
    stamp: tuple[int, int]
    last_arrival: float
    iterations: int
    converged: bool
    initial_chi2: float


@dataclass
class _Records:
    """The objective's index records, grown by one batch of submaps at a time (see :class:`MapObjective`)."""

    z: list[FloatArray] = field(default_factory=list)
    angle_rows: list[npt.NDArray[np.bool_]] = field(default_factory=list)
    feat_rows: list[IntArray] = field(default_factory=list)
    feat_cols: list[IntArray] = field(default_factory=list)
    feat_ref: list[IntArray] = field(default_factory=list)
    pose_rows: list[IntArray] = field(default_factory=list)
    pose_cols: list[IntArray] = field(default_factory=list)
    pose_ref: list[IntArray] = field(default_factory=list)
    weights: list[InfoMatrix] = field(default_factory=list)  # the absorbed ones: one CSR matrix


_RECORDS = ("z", "angle_rows", "feat_rows", "feat_cols", "feat_ref", "pose_rows", "pose_cols", "pose_ref")
"""The index records of :class:`MapObjective` (one array each) the refiner keeps and extends."""


def _cat(parts: list[npt.NDArray[np.generic]], dtype: type) -> npt.NDArray[np.generic]:
    return np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros(0, dtype)


class OnlineRefiner:
    """Gauss-Newton over every submap absorbed so far, warm-started across rounds (module docstring).

    Not thread-safe: one owner calls it. Attributes of interest: :attr:`n_absorbed`,
    :attr:`n_pending`, :attr:`iterations`, :attr:`converged`, :attr:`settled`, :attr:`chi2`.
    """

    def __init__(self, config: RefinerConfig | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config or RefinerConfig()
        self._clock = clock
        self._pending: list[Submission] = []
        self._parked: list[Submission] = []  # submaps whose frame pose is not placed yet (another island's)
        self._last_received = -math.inf
        self._linear: LinearEstimate | None = None
        self.n_absorbed = 0
        self.n_submaps = 0  # absorbed submissions that are submaps (not extra measurements)
        self.n_skipped = 0
        self.iterations = 0
        self.round_iterations = 0
        self.converged = True  # the round has ended (nothing to do yet)
        self.settled = True  # ... and at ``chi2_rtol``, not ``streaming_rtol``
        self.chi2 = 0.0
        self.initial_chi2 = 0.0
        self.last_relative_decrease = math.inf  # of χ² by the last step, as a fraction of χ² after it
        self._dim = 0
        self._origin: int | None = None
        self._index: dict[int, int] = {}  # variable key -> variable index; the origin pose -> -2
        self._ids: list[int] = []
        self._kinds: list[int] = []
        self._offsets: list[int] = []
        self._n_state = 0
        self._x = np.zeros(0)
        self._buf = np.zeros(0)  # the state while absorbing: absorbed values, then the new ones' warm start
        self._angles = np.zeros(0, dtype=bool)
        self._n_rows = 0
        self._records = _Records()
        self._objective: MapObjective | None = None
        self._r = np.zeros(0)
        self._jac: sp.csr_matrix | None = None
        self._analysis = (
            cholmod.ReusedAnalysis() if self.config.reuse_analysis and solvers.backend_name() == "libcholmod" else None
        )
        self._last: Submission | None = None
        self._end_id: int | None = None

    # ------------------------------------------------------------------ inputs

    def submit(self, submission: Submission) -> None:
        """Queue a joined submap; it is taken in by the next :meth:`absorb`."""
        self._pending.append(submission)
        self._last_received = self._clock()

    def linear(self, estimate: LinearEstimate) -> None:
        """Keep the newest linear estimate (older ones are ignored) for the warm start of new variables."""
        if self._linear is None or estimate.n_submaps >= self._linear.n_submaps:
            self._linear = estimate
            if self._parked:  # it may place their frame poses now (the joiner linked their island)
                self._pending, self._parked = self._pending + self._parked, []

    @property
    def n_pending(self) -> int:
        """Submaps queued and not absorbed yet."""
        return len(self._pending)

    @property
    def n_parked(self) -> int:
        """Submaps waiting for their frame pose to be placed (another island's, not linked yet)."""
        return len(self._parked)

    def absorb_due(self) -> bool:
        """Whether queued submaps should be taken in now (``growth`` reached, or ``idle_s`` without arrivals)."""
        if not self._pending:
            return False
        if self.n_absorbed == 0 or self.converged:
            return self.n_absorbed == 0 or self._clock() - self._last_received >= self.config.idle_s or (
                len(self._pending) >= self.config.growth * self.n_absorbed
            )
        return len(self._pending) >= self.config.growth * self.n_absorbed or (
            self._clock() - self._last_received >= self.config.idle_s
        )

    def stream_idle(self) -> bool:
        """Whether nothing is queued and no submap has arrived for ``idle_s`` s (the end of a stream, a pause)."""
        return not self._pending and self._clock() - self._last_received >= self.config.idle_s

    def stream_settled(self) -> bool:
        """Whether nothing is queued and no submap has arrived for ``settle_s`` s (nor ``idle_s``)."""
        return self.seconds_until_settled() == 0.0

    def seconds_until_settled(self) -> float:
        """Seconds until :meth:`stream_settled` if nothing more arrives (0: it is; inf: submaps are queued)."""
        if self._pending:
            return math.inf
        return max(0.0, max(self.config.idle_s, self.config.settle_s) - (self._clock() - self._last_received))

    def resume(self) -> bool:
        """Resume a round that ended at ``streaming_rtol``, once no submap has arrived for ``settle_s``.

        Returns:
            Whether the round resumed (it runs on until ``chi2_rtol``).
        """
        if not self.converged or self.settled or not self.stream_settled():
            return False
        self.converged = False
        self.round_iterations = 0
        return True

    def seconds_until_due(self) -> float | None:
        """Seconds until queued submaps become due by ``idle_s`` (``None``: nothing queued)."""
        if not self._pending:
            return None
        return max(0.0, self.config.idle_s - (self._clock() - self._last_received))

    # ------------------------------------------------------------------ absorbing

    def absorb(self) -> int:
        """Take every queued submap in: extend the variables (warm start) and the objective.

        A submap whose frame pose is neither among the variables nor in the linear estimate (a
        submap after a lost one, another robot's, before the joiner has linked their islands) is
        parked (:attr:`n_parked`) and taken in by a later absorb once the linear estimate places
        its frame pose; one of another dimension is skipped with a warning (:attr:`n_skipped`).

        Returns:
            The number of submaps absorbed.
        """
        if not self._pending:
            return 0
        # the parked last: the new submaps may hold their frame poses
        batch, self._pending, self._parked = self._pending + self._parked, [], []
        if self._origin is None:
            self._origin = batch[0].submap.frame_id
            self._dim = batch[0].submap.dim
            self._index[pose_key(self._origin)] = -2
        lin = self._anchored_linear()
        n_state_before, n_rows_before = self._n_state, self._n_rows
        self._buf = np.empty(max(2 * self._n_state, 1024))
        self._buf[: self._n_state] = self._x
        rec = _Records()
        taken, chained = self._take_batch(batch, lin, rec)
        if not taken:  # all parked: nothing changes (the round goes on as it was)
            self._buf = np.zeros(0)
            return 0
        for sub in taken:
            self.n_submaps += not sub.extra
            self._last = sub
            self._end_id = sub.submap.end_id if sub.submap.end_id is not None else self._end_id
        self._x = self._buf[: self._n_state].copy()
        self._buf = np.zeros(0)
        self._angles = angle_mask(self._dim, np.asarray(self._kinds, dtype=np.int8))
        batch_records = {
            name: _cat(getattr(rec, name), bool if name == "angle_rows" else (float if name == "z" else np.int64))
            for name in _RECORDS
        }
        for name, value in batch_records.items():
            getattr(self._records, name).append(value)
        if rec.weights:
            batch_weight = block_diagonal(rec.weights)
            if self.config.place_steps and chained and n_state_before:
                self._place_new(batch_records, batch_weight, n_state_before, n_rows_before)
            self._records.weights = [
                block_diagonal([batch_weight], self._records.weights[0]) if self._records.weights else batch_weight
            ]
        self.n_absorbed += len(taken)
        self._build_objective()
        self.round_iterations = 0
        self.converged = self.settled = False
        self.last_relative_decrease = math.inf
        return len(taken)

    def _place_new(
        self, batch: dict[str, npt.NDArray[Any]], weight: sp.csr_matrix, n_old: int, row0: int
    ) -> None:
        """Move the variables new in this batch to the optimum of the batch's submaps alone, the others held.

        The warm start chains a variable the linear estimate lacks from its submap's frame pose,
        so over a long batch (the end of a stream, the linear map not out yet) the chain drifts
        and the round's first full steps are spent undoing it. The batch's rows are the only ones
        that see new variables, so Gauss-Newton over them and the new columns (at most
        ``place_steps`` steps, until one lowers their χ² by at most ``place_rtol``) is small
        beside a step over the whole map. A step that fails leaves the warm start as it is.

        Args:
            batch: the batch's index records (rows from ``row0``; columns over the whole state).
            weight: the batch's block-diagonal information, ``(rows, rows)``.
            n_old: state scalars absorbed before the batch (held); the rest are new.
            row0: the batch's first row in the whole objective.
        """
        objective = self._make_objective(batch, weight, row0)
        held = self._x[:n_old]
        angles = self._angles[n_old:]

        def residuals(x_new: FloatArray) -> tuple[FloatArray, sp.csr_matrix]:
            r, jac = objective.residuals(np.concatenate([held, x_new]), jacobian=True)
            assert jac is not None
            return r, jac[:, n_old:].tocsr()

        def apply_step(x_new: FloatArray, dx: FloatArray) -> FloatArray:
            moved = x_new + dx
            moved[angles] = wrap_angle(moved[angles])
            return moved

        x_new = self._x[n_old:].copy()
        r, jac = residuals(x_new)
        chi2 = float(r @ (weight @ r))
        for _ in range(self.config.place_steps):
            try:
                step = least_squares.gauss_newton_step(residuals, weight, x_new, r, jac, chi2, apply_step)
            except LinearSlamError as exc:
                logger.debug("refiner: placing %d new scalars stopped: %s", x_new.size, exc)
                break
            if step is None:
                break
            decrease = chi2 - step.chi2
            x_new, r, jac, chi2 = step.x, step.r, step.jacobian, step.chi2
            if decrease <= self.config.place_rtol * max(chi2, 1e-300):
                break
        self._x[n_old:] = x_new

    def _take_batch(
        self, batch: list[Submission], lin: tuple[dict[int, int], FloatArray, IntArray] | None, rec: _Records
    ) -> tuple[list[Submission], int]:
        """Index a batch's variables (appending new ones with their warm start) and its records.

        One pass over the submaps' keys in Python (the variable index is a dict); the records'
        rows, columns and frames and the warm start are array operations over the batch.

        Returns:
            The submissions taken (a submap of another dimension is left out with a warning and
            counted in :attr:`n_skipped`; one whose frame pose is neither in the refined map nor in
            the linear estimate is parked for a later batch; a frame pose only the linear estimate
            holds becomes a variable, at that estimate), and how many of their new variables were
            chained from their frame poses.
        """
        dim, p = self._dim, pose_size(self._dim)
        index, ids, kinds, offsets = self._index, self._ids, self._kinds, self._offsets
        taken: list[Submission] = []
        refs: list[int] = []  # per submap taken: its frame pose's first state scalar (-1: the origin)
        var_counts: list[int] = []
        positions: list[int] = []  # per variable of the submaps taken: its variable index (-2: the origin)
        fresh: list[tuple[int, int, int]] = []  # per new variable: (submap taken, place in ``positions``, index)
        n_state = self._n_state
        from_linear: list[tuple[int, int]] = []  # (state offset, linear offset) of frame poses placed by the estimate
        for sub in batch:
            m = sub.submap
            if m.dim != dim:
                self.n_skipped += 1
                logger.warning("refiner: submap seq %d left out: submap %r is %dD; the refiner's map is %dD",
                               sub.seq, m.name, m.dim, dim)
                continue
            ref = -1
            if m.frame_id != self._origin:
                frame_key = pose_key(m.frame_id)
                ref_index = index.get(frame_key)
                if ref_index is None and lin is not None and frame_key in lin[0]:  # an island the joiner has linked
                    ref_index = index[frame_key] = len(ids)
                    ids.append(m.frame_id)
                    kinds.append(POSE)
                    offsets.append(n_state)
                    from_linear.append((n_state, int(lin[2][lin[0][frame_key]])))
                    n_state += p
                if ref_index is None:  # nothing places it yet: parked, tried again at the next absorb
                    self._parked.append(sub)
                    continue
                ref = offsets[ref_index]
            for k, var_id, kind in zip(m.keys.tolist(), m.ids.tolist(), m.kinds.tolist(), strict=True):
                j = index.get(k)
                if j is None:
                    j = len(ids)
                    index[k] = j
                    ids.append(var_id)
                    kinds.append(kind)
                    offsets.append(n_state)
                    n_state += p if kind == POSE else dim
                    fresh.append((len(taken), len(positions), j))
                positions.append(j)
            taken.append(sub)
            refs.append(ref)
            var_counts.append(m.n_vars)
        self._n_state = n_state
        if from_linear and lin is not None:
            self._grow_buffer()
            for start, at in from_linear:
                self._buf[start : start + p] = lin[1][at : at + p]
        if not taken:
            return taken, 0
        maps = [sub.submap for sub in taken]
        kinds_batch = np.concatenate([m.kinds for m in maps]).astype(np.int8, copy=False)
        is_pose = kinds_batch == POSE
        sizes = np.where(is_pose, p, dim)
        local_rows = var_offsets(sizes)  # each variable's first row in the batch
        rows = self._n_rows + local_rows
        pos = np.asarray(positions, dtype=np.int64)
        state_offsets = np.asarray(offsets, dtype=np.int64)
        cols = np.where(pos >= 0, state_offsets[np.maximum(pos, 0)], -1)  # -1: the origin pose (a zero pose, no column)
        ref_of_var = np.repeat(np.asarray(refs, dtype=np.int64), var_counts)
        rec.pose_rows.append(rows[is_pose])
        rec.pose_cols.append(cols[is_pose])
        rec.pose_ref.append(ref_of_var[is_pose])
        rec.feat_rows.append(rows[~is_pose])
        rec.feat_cols.append(cols[~is_pose])
        rec.feat_ref.append(ref_of_var[~is_pose])
        z = np.concatenate([m.x for m in maps])
        rec.z.append(z)
        rec.angle_rows.append(angle_mask(dim, kinds_batch))
        rec.weights.extend(m.info for m in maps)
        self._n_rows += int(sizes.sum())
        if not fresh:
            return taken, 0
        new = np.asarray(fresh, dtype=np.int64)
        keys_batch = np.concatenate([m.keys for m in maps])
        return taken, self._initial_values(new, keys_batch, is_pose, local_rows, z, refs, state_offsets, lin)

    def _initial_values(
        self, new: IntArray, keys: IntArray, is_pose: npt.NDArray[np.bool_], local_rows: IntArray, z: FloatArray,
        refs: list[int], state_offsets: IntArray, lin: tuple[dict[int, int], FloatArray, IntArray] | None,
    ) -> int:
        """Write the warm start of a batch's new variables into the state buffer, growing it as needed.

        A variable takes the anchored linear estimate's value, else it is chained from its
        submap's frame pose, a submap at a time in the batch's order (a frame pose may be new in
        an earlier submap of the batch).

        Args:
            new: ``(k, 3)`` per new variable, its submap (place among those taken), its place among
                the batch's variables, and its variable index.
            keys, is_pose, local_rows: per variable of the batch: its key, whether it is a pose, its
                first row in the batch's stacked estimate ``z``.
            z: the batch's local estimates, stacked.
            refs: per submap, its frame pose's first state scalar (-1: the origin).
            state_offsets: every variable's first state scalar.
            lin: the anchored linear estimate (:meth:`_anchored_linear`), if any.

        Returns:
            How many new variables were chained.
        """
        dim, p = self._dim, pose_size(self._dim)
        self._grow_buffer()
        buf = self._buf
        submap, place, var = new[:, 0], new[:, 1], new[:, 2]
        start = state_offsets[var]
        pose = is_pose[place]
        row = local_rows[place]
        lin_pos = np.full(var.size, -1, dtype=np.int64)
        if lin is not None:
            lookup = lin[0]
            lin_pos[:] = [lookup.get(k, -1) for k in keys[place].tolist()]
            for mask, size in ((pose & (lin_pos >= 0), p), (~pose & (lin_pos >= 0), dim)):
                if mask.any():
                    buf[start[mask, None] + np.arange(size)] = lin[1][lin[2][lin_pos[mask], None] + np.arange(size)]
        chain = np.flatnonzero(lin_pos < 0)
        if not chain.size:
            return 0
        groups = np.split(chain, np.flatnonzero(np.diff(submap[chain])) + 1)
        for group in groups:  # a submap at a time: its frame pose may have been chained by the one before
            ref = refs[int(submap[group[0]])]
            frame = np.zeros(p) if ref < 0 else buf[ref : ref + p].copy()
            rot, _ = single_rotation(dim, frame[dim:])  # local coordinates to the world's: R^T p + t, as rows p R + t
            poses, points = group[pose[group]], group[~pose[group]]
            if poses.size:
                local = z[row[poses, None] + np.arange(p)]
                buf[start[poses, None] + np.arange(dim)] = local[:, :dim] @ rot + frame[:dim]
                if dim == 2:
                    buf[start[poses] + dim] = wrap_angle(local[:, dim] + frame[dim])
                else:
                    buf[start[poses, None] + np.arange(dim, p)] = angles3(rot3(local[:, dim:]) @ rot)
            if points.size:
                local = z[row[points, None] + np.arange(dim)]
                buf[start[points, None] + np.arange(dim)] = local @ rot + frame[:dim]
        return int(chain.size)

    def _grow_buffer(self) -> None:
        """Grow the state buffer to hold :attr:`_n_state` scalars (doubling)."""
        if self._n_state > self._buf.size:
            grown = np.empty(max(2 * self._buf.size, self._n_state))
            grown[: self._buf.size] = self._buf
            self._buf = grown

    def _anchored_linear(self) -> tuple[dict[int, int], FloatArray, IntArray] | None:
        """The linear estimate moved rigidly onto the refined solution at their newest common pose.

        Returns:
            ``(key -> variable index, values, offsets)`` of the moved estimate (its frame pose
            included as a variable), or ``None`` without a usable estimate.
        """
        est = self._linear
        if est is None or est.dim != self._dim:
            return None
        dim, p = self._dim, pose_size(self._dim)
        ids = np.concatenate([est.ids, [est.frame_id]]).astype(np.int64)
        kinds = np.concatenate([est.kinds, [POSE]]).astype(np.int8)
        x = np.concatenate([est.x, np.zeros(p)])
        sizes = var_sizes(dim, kinds)
        offsets = var_offsets(sizes)
        keys = var_keys(ids, kinds)
        lookup = {int(k): i for i, k in enumerate(keys.tolist())}
        common = [int(i) for i, k in zip(ids.tolist(), keys.tolist(), strict=True) if k % 2 == 0 and k in self._index]
        if not common:
            return None
        anchor = max(common)
        a_lin = x[offsets[lookup[pose_key(anchor)]] :][:p]
        j = self._index[pose_key(anchor)]
        a_ref = np.zeros(p) if j == -2 else self._x[self._offsets[j] : self._offsets[j] + p]
        moved = np.empty_like(x)
        is_pose = kinds == POSE
        pose_idx = offsets[is_pose][:, None] + np.arange(p)
        feat_idx = offsets[~is_pose][:, None] + np.arange(dim)
        if pose_idx.size:
            rel = poses_to_frame(dim, a_lin[:dim], a_lin[dim:], x[pose_idx[:, :dim]], x[pose_idx[:, dim:]])
            t, a = poses_from_frame(dim, a_ref[:dim], a_ref[dim:], rel.translations, rel.angles)
            moved[pose_idx[:, :dim]] = t
            moved[pose_idx[:, dim:]] = a
        if feat_idx.size:
            rel_f = points_to_frame(dim, a_lin[:dim], a_lin[dim:], x[feat_idx])
            moved[feat_idx] = points_from_frame(dim, a_ref[:dim], a_ref[dim:], rel_f.points)
        return lookup, moved, offsets

    def _make_objective(
        self, records: dict[str, npt.NDArray[Any]], weight: sp.csr_matrix, row0: int = 0
    ) -> MapObjective:
        """The objective of these index records (:data:`_RECORDS`; rows from ``row0``) over the whole state."""
        assert self._origin is not None
        r = records
        return MapObjective(
            dim=self._dim, n_state=self._n_state, origin_id=self._origin, z=r["z"], weight=weight,
            angle_rows=r["angle_rows"], feat_rows=r["feat_rows"] - row0 if row0 else r["feat_rows"],
            feat_cols=r["feat_cols"], feat_ref=r["feat_ref"],
            pose_rows=r["pose_rows"] - row0 if row0 else r["pose_rows"], pose_cols=r["pose_cols"], pose_ref=r["pose_ref"],
        )

    def _build_objective(self) -> None:
        rec = self._records
        self._objective = self._make_objective(
            {name: np.concatenate(getattr(rec, name)) for name in _RECORDS}, to_csr(rec.weights[0])
        )
        # one array per record kind from now on: the next absorb appends to it
        for name in _RECORDS:
            setattr(rec, name, [getattr(self._objective, name)])
        self._r, self._jac = self._residuals(self._x)
        self.chi2 = self.initial_chi2 = float(self._r @ (self._objective.weight @ self._r))
        if self._analysis is not None:  # every step's J^T W J has its entries within |J|^T |W| |J|: one analysis a round
            ones = self._jac.copy()
            ones.data = np.ones_like(ones.data)
            self._analysis.expect(ones.T @ (abs(self._objective.weight) @ ones))

    # ------------------------------------------------------------------ iterating

    def _residuals(self, x: FloatArray) -> tuple[FloatArray, sp.csr_matrix]:
        assert self._objective is not None
        r, jac = self._objective.residuals(x, jacobian=True)
        assert jac is not None
        return r, jac

    def _apply_step(self, x: FloatArray, dx: FloatArray) -> FloatArray:
        x_new = x + dx
        x_new[self._angles] = wrap_angle(x_new[self._angles])
        return x_new

    def iterate(self) -> bool:
        """Take one Gauss-Newton step on the absorbed submaps.

        Returns:
            Whether the round has ended (no step is taken once it has): converged to
            ``chi2_rtol`` (:attr:`settled`), or, while submaps arrive (:meth:`stream_settled`
            is false), to ``streaming_rtol``. A singular system
            ends the round with a warning (the estimate stays as it was).
        """
        if self.converged or self._objective is None or self._jac is None:
            return True
        try:
            step = least_squares.gauss_newton_step(
                self._residuals, self._objective.weight, self._x, self._r, self._jac, self.chi2, self._apply_step,
                self._analysis.solve if self._analysis is not None else None,
            )
        except LinearSlamError as exc:
            logger.warning("refiner: Gauss-Newton step failed on %d submaps: %s", self.n_absorbed, exc)
            self.converged = self.settled = True
            return True
        self.round_iterations += 1
        if step is None:
            self.converged = self.settled = True
            return True
        self.iterations += 1
        decrease = self.chi2 - step.chi2
        self._x, self._r, self._jac, self.chi2 = step.x, step.r, step.jacobian, step.chi2
        self.last_relative_decrease = decrease / max(self.chi2, 1e-300)
        cfg = self.config
        scale = max(self.chi2, 1e-300)
        self.settled = step.max_step < cfg.step_tol or decrease <= cfg.chi2_rtol * scale
        capped = self.round_iterations >= cfg.max_round_iterations  # ends the round, not converged: it resumes
        streaming = cfg.streaming_rtol > cfg.chi2_rtol and not self.stream_settled()
        self.converged = self.settled or capped or (streaming and decrease <= cfg.streaming_rtol * scale)
        return self.converged

    def result(self, information: bool = True) -> RefinedMap:
        """Return the current estimate as a map in the origin's frame.

        Args:
            information: attach ``J^T W J`` at the estimate (a sparse product); else the identity.

        Raises:
            InvalidMapError: nothing has been absorbed yet.
        """
        if self._objective is None or self._last is None or self._jac is None or self._origin is None:
            raise InvalidMapError("the refiner holds no submap yet")
        if information:
            jac = self._jac
            hessian = (jac.T @ (self._objective.weight @ jac)).tocsr()
            info: sp.csr_matrix = ((hessian + hessian.T) * 0.5).tocsr()
        else:
            info = sp.identity(self._n_state, format="csr")
        end_id = self._end_id if self._end_id != self._origin else None
        refined = LocalMap.trusted(
            self._dim, self._origin, end_id, np.asarray(self._ids, np.int64), np.asarray(self._kinds, np.int8),
            self._x.copy(), info, "refined map",
        )
        last = self._last
        return RefinedMap(
            refined, self.chi2, self.n_submaps, last.seq, last.stamp, last.arrived, self.iterations, self.settled,
            self.initial_chi2,
        )


def refine_offline(
    maps: Sequence[LocalMap], linear: LocalMap | None = None, config: RefinerConfig | None = None,
    max_iterations: int = 50,
) -> RefinedMap:
    """Refine a whole stream at once with :class:`OnlineRefiner` (``join --refine``, tests).

    Args:
        maps: the submaps in joining order.
        linear: the linear joiner's map of them (any frame holding their poses); ``None``: chain.
        config: the refiner's settings (``chi2_rtol`` decides convergence).
        max_iterations: Gauss-Newton steps at most.

    Raises:
        InvalidMapError: ``maps`` is empty.
    """
    if not maps:
        raise InvalidMapError("no submaps to refine")
    cfg = config or RefinerConfig()
    # the whole stream at once: no round ends at streaming_rtol
    refiner = OnlineRefiner(RefinerConfig(**{**cfg.__dict__, "max_round_iterations": max_iterations, "streaming_rtol": 0.0}))
    if linear is not None:
        refiner.linear(LinearEstimate.of_map(linear, len(maps)))
    for seq, m in enumerate(maps, start=1):
        refiner.submit(Submission(seq, m, 0.0))
    refiner.absorb()
    while not refiner.iterate():
        pass
    return refiner.result()
