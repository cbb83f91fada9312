"""χ² gating of a submap against the global map (issue 11, part 3): the normalised innovation squared.

Before a submap is joined, what it says about the variables the map already holds (its *common*
variables) is compared with the map's estimate. In one frame, with ``r = z_S,c - x_M,c`` (angles
wrapped) and the two marginal covariances of the common variables, the normalised innovation
squared is::

    NIS = r^T (P_S,cc + P_M,cc)^-1 r,      dof = number of common scalars,

which is exactly the increase of the linear least-squares objective that joining would cause
(local maps are independent): summed over a clean stream it is the joined map's χ² (VicPark200
3640 against the published 3645, Intel 552 against 546.5, DLR200 11136 against 12577 / 11164 at
the nonlinear optimum), and a Monte Carlo change of frame of the map's marginal (3000 samples,
DLR200 submap 57) gives its covariance to within sampling noise and NIS 166.7 against 164.9.

Two tests, both at ``probability``: the whole submap (``NIS`` against the χ² quantile of ``dof``)
and each common variable (its *conditional* NIS, below, against the quantile of its own scalars at
the Šidák probability ``probability ** (1 / n)`` for ``n`` common variables, so the submap's false
alarm rate stays about twice ``1 - probability``). The per-variable test is what finds one wrong
measurement among many right ones: a feature moved by 2.6 m with conditional NIS 46 (2 dof)
raises the total of 18 dof only to 49 < 62.

The variance of unit weight (:class:`VarianceFactor`): the information of real local maps is
not always true to scale. DLR200's clean joins have a median NIS/dof of 3.8 (its χ² at the
nonlinear optimum is 11164 for 2800 redundant scalars: 4.0), VicPark200's 0.4 (3643 / 7180), so
a gate at the nominal scale flags half of DLR200's clean submaps. With ``variance`` given, the
thresholds are ``s² k F(probability; k, ν)`` for ``k`` scalars, where ``s²`` is the stream's
a-posteriori variance factor (what the joins so far fused, with a prior of ``PRIOR_DOF`` scalars at
scale 1) and ``ν`` the scalars behind it: the F quantile accounts for the estimate's own
uncertainty, and tends to the χ² quantile as ``ν`` grows. ``s²`` may go below 1 (information
that is too loose: Manhattan's Σ NIS / Σ dof is 0.025), but never below the scale calibrated on
the stream's own upper tail, so heavy-tailed clean data (VicPark, Intel) keep their gate.

Frames: the map's marginal is requested for the common variables plus the submap's frame pose.
When the map holds that pose, the small marginal is moved into the submap's frame (closed form,
exact Jacobians: :func:`~linear_slam_ros.core.frames.change_frame`); when instead the submap holds
the map's frame pose, the submap is moved; with neither, nothing can be compared (the join itself
raises ``FrameError``).

A failing submap is not dropped whole when a few variables explain the failure: the variable whose
*conditional* NIS (its innovation given the others', ``(W r)_v^T W_vv^-1 (W r)_v`` with
``W = C^-1``: exactly how much the total NIS drops without it; χ² with the variable's scalars as
dof under the null hypothesis) is least likely is split off, and so on while the rest fails either
test, up to half of the common variables. Split-off variables are marginalised out of the
submap (:func:`marginalise_out`; exact, and for pose-only maps whose information is block diagonal
per edge it drops those edges), and the rest, including the pose chain, is joined. A submap that
still fails after that is gated whole: all its common variables are split off, so nothing it says
about the map is fused, and only its new variables join (the chain goes on; dropping the submap
would leave every later submap without the pose it is expressed in).
"""

from __future__ import annotations

import collections
import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.linalg
import scipy.sparse as sp
import scipy.special

from linear_slam_ros.core.errors import ConfigError, SolverError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import wrap_angle
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, angle_mask, pose_key, to_dense, var_keys, var_sizes
from linear_slam_ros.core.solvers import DENSE_MAX, solve_sparse_spd, spd_factor
from linear_slam_ros.joining.divide_conquer import Deferred, Entry, OnlineDCState, leaf_entries, leaf_maps
from linear_slam_ros.joining.pairwise import join_at_seam
from linear_slam_ros.joining.sequential import CovarianceMap, _symmetrize_lower

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

MAX_SPLIT_FRACTION = 0.5
"""At most this fraction of a submap's common variables (at least one) is split off; beyond, it is gated whole."""

PRIOR_DOF = 20.0
"""Scalars of prior belief, at scale 1, in the variance factor of :class:`VarianceFactor`."""

TAIL_QUANTILE = 0.95
"""Quantile at which :class:`VarianceFactor` calibrates the scale on the stream's own upper tail."""

TAIL_CONFIDENCE = 0.99
"""Confidence with which the tail calibration of :class:`VarianceFactor` bounds the
:data:`TAIL_QUANTILE` quantile from above (an order statistic: needs 90 fused submaps at 0.99)."""

EARLY_TAIL_MARGIN = 2.0
"""Before that bound exists, the tail calibration is this many times the largest ``u`` so far, at most 1."""


def tail_order_statistic(n: int, quantile: float, confidence: float) -> int | None:
    """Return the smallest ``k`` whose ``k``-th smallest of ``n`` samples bounds their ``quantile`` from above.

    Distribution-free: the ``k``-th order statistic exceeds the ``quantile`` quantile of any
    continuous distribution with probability ``P(Binomial(n, quantile) <= k - 1)``; ``k`` is the
    smallest with that probability at least ``confidence``. ``None`` when even the largest sample
    is not enough (``1 - quantile**n < confidence``).

    Raises:
        ConfigError: ``quantile`` or ``confidence`` is not in (0, 1).
    """
    for name, value in (("quantile", quantile), ("confidence", confidence)):
        if not 0.0 < value < 1.0:
            raise ConfigError(f"tail order statistic: {name}={value!r} must be in (0, 1)")
    if n <= 0 or 1.0 - quantile**n < confidence:
        return None
    lo, hi = 1, n  # bdtr grows with k: the smallest k with bdtr(k - 1, n, quantile) >= confidence
    while lo < hi:
        mid = (lo + hi) // 2
        if float(scipy.special.bdtr(mid - 1, n, quantile)) >= confidence:
            hi = mid
        else:
            lo = mid + 1
    return lo


@dataclass(frozen=True)
class VarianceFactor:
    """The a-posteriori variance of unit weight of a stream: ``s² = (PRIOR_DOF + Σ NIS) / (PRIOR_DOF + Σ dof)``.

    An immutable running sum over what the joins so far fused (``nis_after`` / ``dof_after`` of each
    :class:`GateResult`: what the gate split off does not count). ``VarianceFactor()`` is the
    nominal scale with ``PRIOR_DOF`` scalars of weight; :meth:`nominal` the exactly known scale 1
    (thresholds are plain χ² quantiles).

    ``s²`` may go below 1, so a stream whose information is too loose gets a tighter gate; but the
    mean alone would over-tighten a stream with heavy tails (VicPark6898: mean 0.06, and a gate at
    that scale splits off most of its clean submaps, the map then drifting from every later one).
    So the scale is also calibrated on the stream's own upper tail: each fused submap gives
    ``u = NIS / chi2.ppf(TAIL_QUANTILE, dof)``, and ``s²`` is at least an upper bound, with
    confidence ``tail_confidence``, of the ``TAIL_QUANTILE`` quantile of ``u``: the order
    statistic of :func:`tail_order_statistic` (distribution-free). For heavy tails the tail
    estimate is the larger; for χ²-consistent submaps it is conservative too (an upper bound lies
    above the quantile: a median ``s²`` of 1.2–1.5 from 90 fused submaps on, falling slowly; README,
    "χ² gate"). Until the stream has enough fused
    submaps for that bound (90 at 0.99), the tail calibration is ``EARLY_TAIL_MARGIN`` times the
    largest ``u`` so far, at most 1 (the nominal scale): a stream whose information is too loose
    tightens early (the mean's prior still holds ``s²`` near 1 for the first few tens of
    scalars), one with a large early ``u`` stays at 1. The F quantile of :meth:`threshold`
    widens the thresholds while ``nu`` is small; ``floor`` is a hard lower bound (1: the gate
    never tightens).

    Attributes:
        nis: sum of the fused NIS (dimensionless).
        dof: sum of their scalars.
        prior_dof: weight of the prior ``s² = 1``, in scalars (``inf``: ``s² = 1`` is known).
        floor: ``s²`` is never taken below this (0: no bound but the estimates').
        tail: ``u`` of each fused submap, in order (empty: only the prior).
        tail_confidence: confidence of the tail calibration's bound, in (0, 1).
    """

    nis: float = 0.0
    dof: float = 0.0
    prior_dof: float = PRIOR_DOF
    floor: float = 0.0
    tail: tuple[float, ...] = ()
    tail_confidence: float = TAIL_CONFIDENCE

    def __post_init__(self) -> None:
        for name in ("nis", "dof", "prior_dof", "floor"):
            value = getattr(self, name)
            if not value >= 0.0:
                raise ConfigError(f"VarianceFactor.{name}={value!r} must be a number >= 0")
        if not 0.0 < self.tail_confidence < 1.0:
            raise ConfigError(f"VarianceFactor.tail_confidence={self.tail_confidence!r} must be in (0, 1)")
        bad = [i for i, u in enumerate(self.tail) if not 0.0 <= u < float("inf")]  # NaN fails both
        if bad:
            raise ConfigError(f"VarianceFactor.tail[{bad[0]}]={self.tail[bad[0]]!r} must be a finite number >= 0")
        if self.prior_dof + self.dof <= 0.0:
            raise ConfigError(f"VarianceFactor: prior_dof={self.prior_dof!r} + dof={self.dof!r} must be > 0")

    @classmethod
    def nominal(cls) -> VarianceFactor:
        """The exactly known scale 1: the information of every submap is taken as true."""
        return cls(prior_dof=float("inf"))

    @property
    def nu(self) -> float:
        """Scalars behind the estimate (``inf``: known)."""
        return self.prior_dof + self.dof

    @property
    def mean(self) -> float:
        """The mean estimate ``(prior_dof + nis) / (prior_dof + dof)``."""
        return (self.prior_dof + self.nis) / self.nu

    @functools.cached_property
    def tail_scale(self) -> float:
        """The tail estimate: an upper bound of the ``TAIL_QUANTILE`` quantile of ``tail`` (1 with none)."""
        if not self.tail:
            return 1.0
        values = np.asarray(self.tail, dtype=np.float64)
        k = tail_order_statistic(values.size, TAIL_QUANTILE, self.tail_confidence)
        if k is None:
            return min(1.0, EARLY_TAIL_MARGIN * float(values.max()))
        return float(np.partition(values, k - 1)[k - 1])

    @property
    def value(self) -> float:
        """``s² = max(floor, mean, tail_scale)`` (1 for the known scale)."""
        if np.isinf(self.prior_dof):
            return 1.0
        return max(self.floor, self.mean, self.tail_scale)

    def threshold(self, probability: float, dof: int) -> float:
        """NIS threshold for ``dof`` scalars: ``s² dof F.ppf(probability, dof, nu)`` (χ² for known scale; ``inf`` for 0)."""
        if dof <= 0:
            return float("inf")
        if np.isinf(self.nu):
            return chi2_ppf(probability, dof)
        return self.value * dof * float(scipy.special.fdtri(dof, self.nu, probability))

    def logsf(self, nis: float, dof: int) -> float:
        """Log of the probability of a NIS at least ``nis`` for ``dof`` scalars under this scale."""
        if np.isinf(self.nu):
            return _logsf(nis, chi2_ppf(0.5, dof), lambda x: scipy.special.chdtrc(dof, x), lambda x: scipy.special.chdtr(dof, x))
        median = float(scipy.special.fdtri(dof, self.nu, 0.5))
        return _logsf(nis / (self.value * dof), median, lambda x: scipy.special.fdtrc(dof, self.nu, x),
                      lambda x: scipy.special.fdtr(dof, self.nu, x))

    def updated(self, result: GateResult) -> VarianceFactor:
        """Add what ``result`` lets through (``nis_after``, ``dof_after``; nothing when gated whole)."""
        if result.rejected or result.dof_after == 0:
            return self
        u = result.nis_after / chi2_ppf(TAIL_QUANTILE, result.dof_after)
        return replace(self, nis=self.nis + result.nis_after, dof=self.dof + result.dof_after, tail=(*self.tail, u))


@dataclass(frozen=True)
class Marginal:
    """The marginal distribution of some variables of a map, in the map's frame.

    Attributes:
        dim: 2 or 3.
        frame_id: pose whose frame the estimate is in (not a variable).
        ids: ``(m,)`` variable ids; ``kinds``: ``(m,)`` :data:`POSE` / :data:`FEATURE`.
        x: ``(n,)`` estimate (metres, radians) in the frame of ``frame_id``.
        cov: ``(n, n)`` marginal covariance (m², rad²).
    """

    dim: int
    frame_id: int
    ids: IntArray
    kinds: npt.NDArray[np.int8]
    x: FloatArray
    cov: FloatArray

    @property
    def keys(self) -> IntArray:
        """Variable keys (``2 id + kind``)."""
        return var_keys(self.ids, self.kinds)

    def to_local_map(self) -> LocalMap:
        """Return the marginal as a map (information ``cov^-1``).

        Raises:
            SolverError: the covariance is not positive definite.
        """
        info = _spd_inverse(self.cov, "marginal covariance of the global map")
        return LocalMap.trusted(self.dim, self.frame_id, None, self.ids, self.kinds, self.x, info, "global marginal")

    @classmethod
    def of_map(cls, local_map: LocalMap, keys: Sequence[int] | IntArray) -> Marginal | None:
        """Return the marginal of the variables of ``local_map`` among ``keys`` (``None``: none of them).

        One sparse (or dense) Cholesky of the map's information and one solve per kept scalar.

        Raises:
            SolverError: the information is not positive definite.
        """
        lookup = local_map.key_set
        var_idx = np.array(sorted({lookup[k] for k in np.asarray(keys).tolist() if k in lookup}), dtype=np.int64)
        if var_idx.size == 0:
            return None
        sc = local_map.scalar_index(var_idx)
        n = local_map.state_dim
        if n <= DENSE_MAX or not sp.issparse(local_map.info):
            cov = _spd_inverse(to_dense(local_map.info), f"information of {local_map.name!r}")[np.ix_(sc, sc)]
        else:
            rhs = np.zeros((n, sc.size))
            rhs[sc, np.arange(sc.size)] = 1.0
            cov = solve_sparse_spd(local_map.info, rhs)[sc]
        return cls(local_map.dim, local_map.frame_id, local_map.ids[var_idx], local_map.kinds[var_idx],
                   local_map.x[sc], 0.5 * (cov + cov.T))

    @classmethod
    def of_covariance_map(cls, cov_map: CovarianceMap, keys: Sequence[int] | IntArray) -> Marginal | None:
        """Return the marginal of a covariance-form map (exact sequential joining): ``S_cc = Q_c S~_cc Q_c^T``, O(c²)."""
        lookup = cov_map.key_set
        var_idx = np.array(sorted({lookup[k] for k in np.asarray(keys).tolist() if k in lookup}), dtype=np.int64)
        if var_idx.size == 0:
            return None
        sc = cov_map.scalar_index(var_idx)  # ascending: the block of the stored lower triangle stays lower
        s_tilde = _symmetrize_lower(cov_map.cov_tilde[np.ix_(sc, sc)])
        q = cov_map.q_block(var_idx)
        cov = q @ s_tilde @ q.T
        return cls(cov_map.dim, cov_map.frame_id, cov_map.ids[var_idx], cov_map.kinds[var_idx], cov_map.x[sc],
                   0.5 * (cov + cov.T))


def _spd_inverse(matrix: FloatArray, what: str) -> FloatArray:
    try:
        factor = scipy.linalg.cho_factor(matrix, lower=True)
    except np.linalg.LinAlgError:
        raise SolverError(f"{what} (size {matrix.shape[0]}) is not positive definite") from None
    inv = scipy.linalg.cho_solve(factor, np.eye(matrix.shape[0]))
    return np.asarray(0.5 * (inv + inv.T), dtype=np.float64)


MarginalFn = Callable[[IntArray], "Marginal | None"]
"""Given variable keys, the global map's marginal of those it holds (``None``: none, or it cannot tell)."""


# --------------------------------------------------------------------------- online divide and conquer


def _entry_map(entry: Entry) -> LocalMap:
    """The map an entry stands for, never forcing a deferred join: its leaves are folded instead."""
    if isinstance(entry, Deferred):
        if entry.done:
            return entry.value()
        leaves = leaf_maps([entry])
        out = leaves[0]
        for leaf in leaves[1:]:
            out = join_at_seam(out, leaf)
        return out
    return entry


def _entry_token(entry: Entry) -> int:
    """Identity of what an entry stands for (a computed deferred join counts as its map)."""
    return id(entry.value()) if isinstance(entry, Deferred) and entry.done else id(entry)


@dataclass
class PrefixCache:
    """Cache of the online D&C stack's merged prefixes, for :func:`online_dc_marginal` (a cache only).

    A push changes only the top of the binary-counter stack, so the merge of every entry but the top
    was either merged at an earlier step or is one pairwise join away from one that was. Prefixes
    are keyed by the identity of their entries and kept while they are prefixes of the newest stack
    (at most as many maps as stack entries). Results never depend on what is cached.
    """

    _merged: collections.OrderedDict[tuple[int, ...], tuple[tuple[Entry, ...], LocalMap]] = field(
        default_factory=collections.OrderedDict
    )

    def merged(self, entries: tuple[Entry, ...]) -> LocalMap:
        """Return the entries joined oldest first at their seams (in the frame of the first's seam), caching prefixes."""
        tokens = tuple(_entry_token(e) for e in entries)
        j = len(entries)
        while j > 0 and tokens[:j] not in self._merged:
            j -= 1
        current = self._merged[tokens[:j]][1] if j else _entry_map(entries[0])
        if not j:
            j = 1
            self._merged[tokens[:1]] = (entries[:1], current)
        for i in range(j, len(entries)):
            current = join_at_seam(current, _entry_map(entries[i]))
            self._merged[tokens[: i + 1]] = (entries[: i + 1], current)
        for key in [k for k in self._merged if k != tokens[: len(k)]]:
            del self._merged[key]
        return current

    def clear(self) -> None:
        """Forget every cached prefix."""
        self._merged.clear()


def online_dc_marginal(state: OnlineDCState, keys: IntArray, cache: PrefixCache | None = None) -> Marginal | None:
    """Return the marginal of ``keys`` in the merged online D&C map, without merging the whole stack anew.

    The stack is split into its prefix (every entry but the top, merged oldest first and cached) and
    its top. The prefix is reduced to its marginal over the variables that matter (the requested
    ones, those it shares with the top, and its end pose, the seam) by one sparse Cholesky; that
    small map is joined with the top at the seam. Marginalising before the join is exact for the
    linear LS (the dropped variables are in the prefix only, and every change of frame of a variable
    depends on that variable and the frame pose alone), so the result is the marginal of the merged
    map, to the order of the merge (the same linear LS, folded oldest first).

    Cost per call: at most one pairwise join of the cached prefix with the previous top, one sparse
    factorisation of the prefix, and joins of small maps.

    Raises:
        SolverError: an information matrix is not positive definite.
    """
    if not state.stack:
        return None
    cache = cache if cache is not None else PrefixCache()
    top = _entry_map(state.stack[-1])
    if len(state.stack) == 1:
        return Marginal.of_map(top, keys)
    prefix = cache.merged(state.stack[:-1])
    wanted = set(np.asarray(keys).tolist()) | set(top.key_set) | {pose_key(top.frame_id)}
    if prefix.end_id is not None:
        wanted.add(pose_key(prefix.end_id))
    reduced = Marginal.of_map(prefix, np.fromiter(wanted, np.int64, len(wanted)))
    if reduced is None:
        return Marginal.of_map(top, keys)
    small = reduced.to_local_map().replace(end_id=prefix.end_id, name="global prefix marginal")
    return Marginal.of_map(join_at_seam(small, top), keys)


ENTRY_BLOCK_MAX = 6000
"""Scalars of covariance an :class:`EntryCovariance` keeps at most (then it starts afresh): 288 MB."""


class EntryCovariance:
    """One stack entry's map, its information factorised once, and the covariance of the variables asked so far.

    A stack entry stays unchanged while it is on the stack (a power of two of submaps), and the
    variables the gate asks of it (those it shares with the other entries, the arriving submaps'
    loop closures) mostly recur. So its information is factorised once (:func:`spd_factor`), a
    variable asked for the first time costs one solve per scalar, and the covariance block of every
    variable asked so far is kept. The same covariance as a factorisation per call to round-off,
    not bit for bit: an entry between two variables comes from the column of the one solved later
    (history-dependent at 1e-16 relative; a resumed joiner starts with an empty cache).
    """

    def __init__(self, local_map: LocalMap) -> None:
        self.map = local_map
        self._solve: Callable[[FloatArray], FloatArray] | None = None
        self._pos: dict[int, int] = {}  # variable index -> offset of its first scalar in the block
        self._block = np.zeros((0, 0))
        self._scalars = np.zeros(0, dtype=np.int64)  # the map's scalar of each row of the block

    def covariance(self, var_idx: IntArray) -> FloatArray:
        """Return the marginal covariance of the variables ``var_idx`` of the entry's map, in that order.

        Raises:
            SolverError: the information is not positive definite.
        """
        m = self.map
        new = np.array([v for v in var_idx.tolist() if v not in self._pos], dtype=np.int64)
        if new.size:
            sc_new = m.scalar_index(new)
            if self._block.shape[0] + sc_new.size > ENTRY_BLOCK_MAX:  # start afresh with what is asked now
                self._pos, self._block, self._scalars = {}, np.zeros((0, 0)), np.zeros(0, dtype=np.int64)
                new = np.asarray(var_idx, dtype=np.int64)
                sc_new = m.scalar_index(new)
            if self._solve is None:
                self._solve = spd_factor(m.info)
            rhs = np.zeros((m.state_dim, sc_new.size))
            rhs[sc_new, np.arange(sc_new.size)] = 1.0
            cols = self._solve(rhs)
            cross = cols[self._scalars]
            corner = cols[sc_new]
            n_old = self._block.shape[0]
            block = np.empty((n_old + sc_new.size, n_old + sc_new.size))
            block[:n_old, :n_old] = self._block
            block[:n_old, n_old:] = cross
            block[n_old:, :n_old] = cross.T
            block[n_old:, n_old:] = 0.5 * (corner + corner.T)
            offset = n_old
            for v in new.tolist():
                self._pos[v] = offset
                offset += int(m.sizes[v])
            self._block = block
            self._scalars = np.concatenate([self._scalars, sc_new])
        rows = np.concatenate([np.arange(self._pos[v], self._pos[v] + int(m.sizes[v])) for v in var_idx.tolist()])
        return np.asarray(self._block[np.ix_(rows, rows)], dtype=np.float64)

    def reduced(self, var_idx: IntArray) -> LocalMap:
        """Return the entry's map reduced to the variables ``var_idx`` (ascending), its end pose as it is.

        Raises:
            SolverError: a covariance is not positive definite.
        """
        m = self.map
        info = _spd_inverse(self.covariance(var_idx), f"marginal covariance of stack entry {m.name!r}")
        return LocalMap.trusted(m.dim, m.frame_id, m.end_id, m.ids[var_idx], m.kinds[var_idx],
                                m.x[m.scalar_index(var_idx)], info, "stack entry marginal")


BIG_ENTRY_FRACTION = 1 / 16
"""Stack entries of at least this fraction of the joined submaps are merged into one part by :func:`big_prefix`."""


def big_prefix(counts: Sequence[int]) -> int:
    """Return how many of the oldest stack entries :func:`online_dc_marginal_by_entries` merges into one part.

    The oldest entries of at least :data:`BIG_ENTRY_FRACTION` of the joined submaps each (never the
    top). That prefix changes only when an entry of that size forms (once every ``n / 16`` submaps
    or more) or one falls below the share as the stream grows, so its merge and factorisation are
    made rarely, and the variables those large entries share with one another leave the dense
    algebra of every call (a looped stream revisits its old places: Intel's two oldest entries
    share up to 192 poses, whose 576-scalar reductions each call inverted and joined densely; with
    the prefix merged, the gate's marginals cost 4.6 instead of 44 s over the stream, docs/gating.md).
    1/16 was chosen over 1/4, 1/8 and 1/32 (Intel: 13.4, 7.5 and 4.9 s; p99 of a call 74, 35 and
    34 ms against 20) and 1/64 (sphere2500's first 1500 submaps: the median call a third lower, its
    99th percentile twice as high). 0 or 1: nothing is merged.
    """
    total = sum(counts)
    j = 0
    while j < len(counts) - 1 and counts[j] >= BIG_ENTRY_FRACTION * total:
        j += 1
    return j


Token = int | tuple[int, ...]


@dataclass
class EntryCache:
    """The :class:`EntryCovariance` of each part of an online D&C stack, for :func:`online_dc_marginal_by_entries` (a cache only).

    The parts are the merge of the stack's :func:`big_prefix` (when it has two entries or more,
    merged by :attr:`prefixes`) and each entry after it. Parts are keyed by the identity of their
    entries and kept while they are on the newest stack asked about or the one before (a
    benchmark's trials alternate between two states). Results depend on it at round-off only
    (:class:`EntryCovariance`).
    """

    _held: dict[Token, tuple[tuple[Entry, ...], EntryCovariance]] = field(default_factory=dict)
    _previous: frozenset[Token] = frozenset()
    prefixes: PrefixCache = field(default_factory=PrefixCache)

    def entries(self, stack: tuple[Entry, ...], merged: int = 0) -> list[EntryCovariance]:
        """Return the covariance holder of each part of ``stack``, creating those not held yet.

        Args:
            stack: the online D&C stack, oldest first.
            merged: its oldest entries making up the first part, merged (0 or 1: one part per entry).
        """
        tokens = [_entry_token(e) for e in stack]
        parts: list[tuple[Token, tuple[Entry, ...]]] = [(t, (e,)) for t, e in zip(tokens, stack, strict=True)]
        if merged >= 2:
            parts = [(tuple(tokens[:merged]), tuple(stack[:merged])), *parts[merged:]]
        out = []
        for token, entries in parts:
            held = self._held.get(token)
            if held is None:
                part = self.prefixes.merged(entries) if len(entries) > 1 else _entry_map(entries[0])
                held = (entries, EntryCovariance(part))
                self._held[token] = held
            out.append(held[1])
        current = frozenset(t for t, _ in parts)
        keep = self._previous | current
        for token in [t for t in self._held if t not in keep]:
            del self._held[token]
        self._previous = current
        return out

    def clear(self) -> None:
        """Forget every cached entry and prefix."""
        self._held.clear()
        self._previous = frozenset()
        self.prefixes.clear()


def online_dc_marginal_by_entries(
    state: OnlineDCState, keys: IntArray, cache: EntryCache | None = None
) -> Marginal | None:
    """Return the marginal of ``keys`` in the merged online D&C map, reducing each stack entry (the stack not merged).

    A deferred join not computed yet counts as its inputs (:func:`~linear_slam_ros.joining.divide_conquer.leaf_entries`):
    no join is made here that a background worker is making, and those inputs, the stack's entries
    one step before, mostly still have their factorisations in the cache. The marginal is then that
    of the parts joined one after the other; the pending join's own result, a tree of joins, differs
    from it by linearisation (6e-5 relative on a noisy synthetic stream, ``test_gate.py``;
    centimetres on VicPark200), so the result depends on which merges have landed. The gate
    therefore makes every pending merge first (:meth:`OnlineDC.marginal
    <linear_slam_ros.joiner.strategies.divide_conquer.OnlineDC.marginal>`): its decisions are then
    those of a joiner that merges at once. The stack's :func:`big_prefix` (its oldest
    entries of at least a sixteenth of the stream each) counts as one entry, merged (cached while
    those entries stay). Each entry is reduced to the variables that matter: the requested ones,
    those it shares with another entry, and its end pose (the seam of the next join); the small
    maps are joined oldest first at their seams, as the stack is merged; after each join, what no
    later entry holds (as a variable or as its frame) and nobody asked for is marginalised out, so
    the running map stays small (sphere2500 at 500 submaps: a call 2.4-3.5 times faster,
    docs/gating.md). Exact for the same reason as :func:`online_dc_marginal`. Each entry's
    information is factorised once while it is on the stack (:class:`EntryCovariance`): a call
    costs solves for variables not asked before and dense algebra on the kept ones. ``None`` when
    the map holds none of ``keys``. An entry left with no variable (in its own end pose's frame,
    sharing nothing) falls back to :func:`online_dc_marginal`.

    Raises:
        SolverError: an information matrix is not positive definite.
    """
    if not state.stack:
        return None
    cache = cache if cache is not None else EntryCache()
    parts, part_counts = leaf_entries(state.stack, state.counts)
    held = cache.entries(parts, big_prefix(part_counts))
    maps = [h.map for h in held]
    requested = set(np.asarray(keys).tolist())
    if len(maps) == 1:
        wanted = requested
    else:  # an entry's frame pose counts: a change of frame makes it a variable of that entry
        frames = np.array([pose_key(m.frame_id) for m in maps], dtype=np.int64)
        all_keys, counts = np.unique(np.concatenate([*(m.keys for m in maps), frames]), return_counts=True)
        wanted = requested | set(all_keys[counts > 1].tolist())
    later: list[set[int]] = [set() for _ in maps]  # keys and frame poses of the entries after each one
    for i in range(len(maps) - 2, -1, -1):
        later[i] = later[i + 1] | set(maps[i + 1].key_set) | {pose_key(maps[i + 1].frame_id)}
    current: LocalMap | None = None
    for h, m, after in zip(held, maps, later, strict=True):
        lookup = m.key_set
        chosen = {lookup[k] for k in wanted if k in lookup}
        if m.end_id is not None and pose_key(m.end_id) in lookup:
            chosen.add(lookup[pose_key(m.end_id)])
        if not chosen:
            return online_dc_marginal(state, keys, cache.prefixes)
        small = h.reduced(np.array(sorted(chosen), dtype=np.int64))
        current = small if current is None else join_at_seam(current, small)
        if after:  # what no later entry holds and nobody asked for is done with: marginalised out now
            end = pose_key(current.end_id) if current.end_id is not None else None
            done = [i for i, k in enumerate(current.keys.tolist()) if k not in requested and k not in after and k != end]
            if done:
                current = marginalise_out(current, done)
    assert current is not None
    return Marginal.of_map(current, keys)


def online_dc_holds(state: OnlineDCState, keys: IntArray) -> bool:
    """Whether the online D&C map holds any of ``keys`` (key sets and frame poses of the stack's parts: no join, no solve).

    A part's frame pose counts: the merged map holds it (a part in the frame of pose 2, after
    parts that end there, is how a held loop closure to pose 2 finds it in the map).
    """
    wanted = np.asarray(keys).tolist()
    chosen = set(wanted)
    # membership tests in C (map over the keys): hundreds of parts while merges are pending, each asked every key
    return any(pose_key(leaf.frame_id) in chosen or any(map(leaf.key_set.__contains__, wanted))
               for leaf in leaf_maps(state.stack))


# --------------------------------------------------------------------------- the test


@dataclass(frozen=True)
class VariableNis:
    """One common variable's part of a gate decision.

    Attributes:
        var_id: the variable's id; ``kind``: :data:`POSE` or :data:`FEATURE`.
        nis: its conditional NIS (given the other common variables'): how much the total drops without it.
        dof: its scalars (3/6 for a pose, 2/3 for a feature).
    """

    var_id: int
    kind: int
    nis: float
    dof: int

    def describe(self) -> str:
        """``pose 12 (NIS 1722.1, 3 dof)``."""
        return f"{'pose' if self.kind == POSE else 'feature'} {self.var_id} (NIS {self.nis:.1f}, {self.dof} dof)"


@dataclass(frozen=True)
class GateResult:
    """A gate decision for one submap.

    Attributes:
        probability: the gate's χ² probability.
        nis: NIS of all common variables (0 without any).
        dof: their scalars; ``threshold``: ``chi2.ppf(probability, dof)`` (``inf`` with dof 0).
        worst: the common variables by decreasing conditional NIS (at most 5).
        split: variables split off (marginalised out of the submap), in order of removal.
        nis_after, dof_after: NIS and dof of the common variables that remain.
        rejected: the submap is gated whole: more than half of its common variables fail, so all of
            them are split off (what it says about the map is dropped; its new variables, the pose
            chain, are still joined, anchored at its frame pose).
        submap: what is joined: the submap, or the submap without ``split`` (``None``: nothing is left).
        variance_factor: ``s²`` the thresholds were scaled by (:class:`VarianceFactor`; 1: nominal).
        variable_threshold: the per-variable test's threshold for the worst variable's dof.
        n_common: number of common variables (the Šidák exponent of the per-variable test).
        variables: every common variable's conditional NIS, as first tested (``worst`` is their top 5).
        variable_thresholds: ``(dof, threshold)`` of the per-variable test, for each variable size present.
        reinitialised: ``(front-end id, new landmark id)`` of each feature whose sighting failed
            again after an earlier one was split off: joined as a new landmark instead of split
            off (:mod:`~linear_slam_ros.joining.reinit`; not in ``split``).
    """

    probability: float
    nis: float
    dof: int
    threshold: float
    worst: tuple[VariableNis, ...] = ()
    split: tuple[VariableNis, ...] = ()
    nis_after: float = 0.0
    dof_after: int = 0
    rejected: bool = False
    submap: LocalMap | None = None
    variance_factor: float = 1.0
    variable_threshold: float = float("inf")
    n_common: int = 0
    variables: tuple[VariableNis, ...] = ()
    reinitialised: tuple[tuple[int, int], ...] = ()
    variable_thresholds: tuple[tuple[int, float], ...] = ()

    def threshold_of(self, variable: VariableNis) -> float:
        """The per-variable test's threshold for ``variable``'s size (``inf`` when none was tested)."""
        return dict(self.variable_thresholds).get(variable.dof, float("inf"))

    @property
    def passed(self) -> bool:
        """Whether nothing of the submap was kept out (nothing split off, not rejected; re-initialised features are joined)."""
        return not self.rejected and not self.split

    def message(self, label: str) -> str:
        """One line naming the NIS, the threshold, the dof, the worst variables and what was done."""
        worst = ", ".join(v.describe() for v in self.worst[:3])
        scale = f", variance factor {self.variance_factor:.2f}" if self.variance_factor != 1.0 else ""
        head = (
            f"{label}: NIS {self.nis:.2f} {'>' if self.nis > self.threshold else '<='} χ² threshold "
            f"{self.threshold:.2f} for {self.dof} dof (probability {self.probability:.12g}{scale}; per-variable "
            f"threshold {self.variable_threshold:.2f}); worst: {worst}"
        )
        if self.rejected:
            return head + (f"; gated whole (more than {MAX_SPLIT_FRACTION:.0%} of its common variables fail): "
                           "every common variable split off, only its new variables joined")
        split = ", ".join(f"{'pose' if v.kind == POSE else 'feature'} {v.var_id}" for v in self.split)
        renewed = "".join(f"; feature {front} re-initialised as landmark {new}" for front, new in self.reinitialised)
        return head + f"; split off {split} (NIS {self.nis_after:.2f} for {self.dof_after} dof after), rest joined{renewed}"


def chi2_threshold(probability: float, dof: int) -> float:
    """``chi2.ppf(probability, dof)`` (``inf`` for ``dof`` 0)."""
    return chi2_ppf(probability, dof) if dof > 0 else float("inf")


# scipy.stats's χ² and F functions, through the scipy.special functions they call (the same
# numbers): importing scipy.stats cost the node about 30 MB of memory (importing the node module: 137 -> 106 MB).


def chi2_ppf(probability: float, dof: float) -> float:
    """``scipy.stats.chi2.ppf(probability, dof)`` for ``dof`` > 0 and ``probability`` in [0, 1]."""
    return float(2.0 * scipy.special.gammaincinv(dof / 2.0, probability))


def _logsf(x: float, median: float, sf: Callable[[float], Any], cdf: Callable[[float], Any]) -> float:
    """``log(sf(x))`` as scipy.stats computes it: ``log1p(-cdf(x))`` up to the median, 0 for ``x <= 0``."""
    if x <= 0.0:
        return 0.0
    with np.errstate(divide="ignore"):
        return float(np.log(sf(x))) if x > median else float(np.log1p(-cdf(x)))


def _nis(r: FloatArray, cov: FloatArray) -> tuple[float, FloatArray]:
    """Return ``r^T C^-1 r`` and ``W = C^-1``."""
    w = _spd_inverse(cov, "innovation covariance")
    return float(r @ w @ r), w


def gate_submap(
    marginal: MarginalFn, submap: LocalMap, probability: float, variance: VarianceFactor | None = None,
    holds: Callable[[IntArray], bool] | None = None,
) -> GateResult:
    """Test a submap against the global map's marginal (module docstring): pass, split, or gate it whole.

    Args:
        marginal: the global map's marginal of given keys (:class:`Marginal`, in the map's frame).
        submap: the arriving submap (its own frame).
        probability: χ² probability of the gate, in (0, 1).
        variance: the stream's variance of unit weight (``None``: :meth:`VarianceFactor.nominal`,
            plain χ² quantiles).
        holds: whether the global map holds any of given keys, cheaply (``None``: not known). A
            submap sharing no variable with the map has nothing to test: its marginal is then not
            computed (half the submaps of a pose graph: only the frame pose, not a variable of the
            submap, is in the map).

    Raises:
        ConfigError: ``probability`` is not in (0, 1).
        SolverError: a covariance is not positive definite.
    """
    if not 0.0 < probability < 1.0:
        raise ConfigError(f"gate probability={probability!r} must be in (0, 1)")
    scale = variance if variance is not None else VarianceFactor.nominal()
    request = np.concatenate([submap.keys, [pose_key(submap.frame_id)]])
    nothing = GateResult(probability, 0.0, 0, float("inf"), submap=submap, variance_factor=scale.value)
    if holds is not None and not holds(submap.keys):
        return nothing
    m = marginal(request)
    if m is None:
        return nothing
    s = submap
    if m.frame_id != s.frame_id:
        held = {int(k) for k in m.keys}
        if pose_key(s.frame_id) in held:
            m = _reframe(m, s.frame_id)
        elif s.has_pose(m.frame_id):
            s = change_frame(s, m.frame_id)
        else:
            return nothing
    m_lookup = {int(k): i for i, k in enumerate(m.keys.tolist())}
    s_keys = s.keys.tolist()
    common = [(i, m_lookup[k]) for i, k in enumerate(s_keys) if k in m_lookup]
    if not common:
        return nothing
    s_idx = np.array([c[0] for c in common], dtype=np.int64)
    m_idx = np.array([c[1] for c in common], dtype=np.int64)
    sizes = s.sizes[s_idx]
    sc_s = s.scalar_index(s_idx)
    m_offsets = np.concatenate([[0], np.cumsum(var_sizes(m.dim, m.kinds))])
    sc_m = np.concatenate([np.arange(m_offsets[j], m_offsets[j + 1]) for j in m_idx])
    r = s.x[sc_s] - m.x[sc_m]
    ang = angle_mask(s.dim, s.kinds[s_idx])
    r[ang] = wrap_angle(r[ang])
    p_s = _submap_covariance(s, sc_s)
    c_full = p_s + m.cov[np.ix_(sc_m, sc_m)]
    block_start = np.concatenate([[0], np.cumsum(sizes)])
    ids = s.ids[s_idx]
    kinds = s.kinds[s_idx]
    original = set(submap.keys.tolist())
    removable = np.array([int(k) in original for k in s.keys[s_idx].tolist()])
    if s.end_id is not None:
        removable &= ~((kinds == POSE) & (ids == s.end_id))

    def blocks_scalars(active: list[int]) -> IntArray:
        return np.concatenate([np.arange(block_start[b], block_start[b + 1]) for b in active])

    def conditional(active: list[int]) -> tuple[float, list[VariableNis]]:
        sc = blocks_scalars(active)
        total, w = _nis(r[sc], c_full[np.ix_(sc, sc)])
        wr = w @ r[sc]
        out: list[VariableNis] = []
        pos = 0
        for b in active:
            k = int(sizes[b])
            part = slice(pos, pos + k)
            value = float(wr[part] @ np.linalg.solve(w[part, part], wr[part]))
            out.append(VariableNis(int(ids[b]), int(kinds[b]), value, k))
            pos += k
        return total, out

    # the per-variable test: Šidák probability over the common variables, one threshold per size
    p_var = probability ** (1.0 / len(common))
    var_thresholds = {int(k): scale.threshold(p_var, int(k)) for k in set(sizes.tolist())}

    def fails(total: float, dof: int, per_var: list[VariableNis]) -> bool:
        return total > scale.threshold(probability, dof) or any(v.nis > var_thresholds[v.dof] for v in per_var)

    active = list(range(len(common)))
    total, per_var = conditional(active)
    dof = int(sizes.sum())
    threshold = scale.threshold(probability, dof)
    worst = tuple(sorted(per_var, key=lambda v: -v.nis)[:5])
    worst_threshold = var_thresholds[worst[0].dof]
    n_common = len(common)
    passed = GateResult(probability, total, dof, threshold, worst, nis_after=total, dof_after=dof, submap=submap,
                        variance_factor=scale.value, variable_threshold=worst_threshold, n_common=n_common,
                        variables=tuple(per_var), variable_thresholds=tuple(sorted(var_thresholds.items())))
    if not fails(total, dof, per_var):
        return passed
    limit = max(1, int(MAX_SPLIT_FRACTION * len(common)))
    split: list[VariableNis] = []
    current, current_vars = total, per_var
    while fails(current, int(sizes[active].sum()), current_vars) and len(split) < limit:
        candidates = [(scale.logsf(v.nis, v.dof), b, v) for b, v in zip(active, current_vars, strict=True) if removable[b]]
        if not candidates:
            break
        _, b_out, v_out = min(candidates, key=lambda t: t[0])
        split.append(v_out)
        active.remove(b_out)
        if not active:
            current, current_vars = 0.0, []
            break
        current, current_vars = conditional(active)
    dof_after = int(sizes[active].sum()) if active else 0
    rejected = fails(current, dof_after, current_vars)
    if rejected and not removable.any():
        # what fails is only what cannot be split off (its end pose, already in the map through a closure): it
        # is joined as it is, and said so, never reported as kept out
        logger.warning(
            "submap %r fails the gate (NIS %.1f > %.1f for %d dof) on its end pose only, which cannot be split off: "
            "joined as it is", submap.name, total, threshold, dof,
        )
        return passed
    if rejected:  # everything it says about the map is dropped; its new variables still extend the chain
        split = [v for b, v in enumerate(per_var) if removable[b]]
        current, dof_after = 0.0, int(sizes[~removable].sum())
    drop = [submap.key_set[int(2 * v.var_id + v.kind)] for v in split]
    trimmed = marginalise_out(submap, drop) if len(drop) < submap.n_vars else None
    return GateResult(probability, total, dof, threshold, worst, tuple(split), current, dof_after, rejected, trimmed,
                      variance_factor=scale.value, variable_threshold=worst_threshold, n_common=n_common,
                      variables=tuple(per_var), variable_thresholds=tuple(sorted(var_thresholds.items())))


def _reframe(m: Marginal, frame_id: int) -> Marginal:
    """Move a marginal (which holds pose ``frame_id``) into the frame of that pose."""
    moved = change_frame(m.to_local_map(), frame_id)
    cov = _spd_inverse(to_dense(moved.info), "moved marginal information")
    return Marginal(m.dim, frame_id, moved.ids, moved.kinds, moved.x, cov)


def _submap_covariance(submap: LocalMap, scalars: IntArray) -> FloatArray:
    """Marginal covariance of some scalars of a submap (dense: submaps are small)."""
    n = submap.state_dim
    if n <= DENSE_MAX or not sp.issparse(submap.info):
        return _spd_inverse(to_dense(submap.info), f"information of submap {submap.name!r}")[np.ix_(scalars, scalars)]
    rhs = np.zeros((n, scalars.size))
    rhs[scalars, np.arange(scalars.size)] = 1.0
    cov = solve_sparse_spd(submap.info, rhs)[scalars]
    return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)


def marginalise_out(submap: LocalMap, var_indices: Sequence[int]) -> LocalMap:
    """Return ``submap`` without the variables ``var_indices``, marginalised out (Schur complement).

    The remaining estimate is unchanged; the information becomes ``I_kk - I_kr I_rr^-1 I_rk``. With
    block-diagonal information (pose-only maps made of edges from the frame pose), this drops
    exactly the removed variables' edges.

    Raises:
        SolverError: the removed variables' information is not positive definite.
    """
    drop = np.zeros(submap.n_vars, dtype=bool)
    drop[list(var_indices)] = True
    keep_vars = np.flatnonzero(~drop)
    sc_r = submap.scalar_index(np.flatnonzero(drop))
    sc_k = submap.scalar_index(keep_vars)
    info = to_dense(submap.info)
    i_kk = info[np.ix_(sc_k, sc_k)]
    i_kr = info[np.ix_(sc_k, sc_r)]
    if np.any(i_kr):
        try:
            factor = scipy.linalg.cho_factor(info[np.ix_(sc_r, sc_r)], lower=True)
        except np.linalg.LinAlgError:
            raise SolverError(
                f"submap {submap.name!r}: information of the variables marginalised out is not positive definite"
            ) from None
        i_kk = i_kk - i_kr @ scipy.linalg.cho_solve(factor, i_kr.T)
    i_kk = 0.5 * (i_kk + i_kk.T)
    return submap.restricted(keep_vars, sp.csr_matrix(i_kk) if sp.issparse(submap.info) else i_kk)


__all__ = [
    "BIG_ENTRY_FRACTION", "EARLY_TAIL_MARGIN", "ENTRY_BLOCK_MAX", "FEATURE", "MAX_SPLIT_FRACTION", "POSE", "PRIOR_DOF",
    "TAIL_CONFIDENCE", "TAIL_QUANTILE", "EntryCache", "EntryCovariance", "GateResult", "Marginal", "MarginalFn",
    "PrefixCache", "VarianceFactor", "VariableNis", "big_prefix", "chi2_threshold", "gate_submap",
    "marginalise_out", "online_dc_holds", "online_dc_marginal", "online_dc_marginal_by_entries", "tail_order_statistic",
]
