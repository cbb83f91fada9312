"""Divide and conquer one tree level at a time: every pairwise join of a level in one set of array operations.

Batch divide and conquer (:func:`~linear_slam_ros.joining.divide_conquer.join_divide_and_conquer`)
is thousands of small joins: each change of frame and each linear join costs tens of numpy calls,
about 0.5 ms of Python for a map of a few poses. The joins of one level are independent, so this
module keeps all the maps of a level side by side in one :class:`MapBatch` (one state vector, one
block-diagonal information) and does each level as a handful of vectorised operations:

1. every pair is brought into one frame exactly as :func:`~linear_slam_ros.joining.pairwise.join_at_seam`
   does (both maps to the seam, the earlier map's end pose; without one, :func:`align_frames`'s
   rule), all changes of frame of the level at once (eqs. 18-21; :func:`change_frames`);
2. every pair is joined by linear least squares (eqs. 12-17) as
   :func:`~linear_slam_ros.joining.pairwise.join_in_shared_frame` does (the union holds the
   earlier map's variables in their order, then the later map's new ones; common angles wrapped
   towards the earlier map's, Remark 3), with one sparse Cholesky solve for the whole level: the
   joined information is block diagonal by pair, so that solve is every pair's solve at once.

The tree is the same (``(1, 2), (3, 4), ...``, an odd last map moves up unchanged) and so is every
linearisation point: the result equals the pair-by-pair divide and conquer up to round-off
(tested to 1e-10 on small synthetic streams and 1e-8 on synthetic city and garage graphs; on the
benchmark datasets the estimates differ by at most 4e-7 m, the round-off the deep tree amplifies).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError, InvalidMapError
from linear_slam_ros.core.geometry import angles3, dangles3, drotation, pose_size, rot3, rot3_and_drot3, rotation, wrap_angle
from linear_slam_ros.core.local_map import POSE, InfoMatrix, LocalMap, var_keys, var_offsets, var_sizes
from linear_slam_ros.core.solvers import DENSE_MAX, solve_sparse_spd
from linear_slam_ros.joining.pairwise import GLOBAL_NAME

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

NO_END = np.iinfo(np.int64).min
"""Value of :attr:`MapBatch.end_ids` for a map without an end pose."""


@dataclass(frozen=True, eq=False)
class MapBatch:
    """Independent maps side by side: their variables concatenated, their information block diagonal.

    Attributes:
        dim: 2 or 3.
        frame_ids: ``(M,)`` frame pose of each map.
        end_ids: ``(M,)`` end pose of each map (:data:`NO_END`: none).
        var_ptr: ``(M + 1,)`` map ``j`` holds the variables ``var_ptr[j]:var_ptr[j + 1]``.
        ids: ``(V,)`` variable ids, map after map.
        kinds: ``(V,)`` variable kinds.
        x: ``(N,)`` the maps' estimates, each in its own frame (m, rad).
        info: ``(N, N)`` CSR, the maps' information matrices on the diagonal; with ``jacobian``,
            the information *before* the change of frame that ``jacobian`` describes.
        names: the maps' names (error messages).
        jacobian: ``None``, or ``(N, N)`` CSR ``G`` of a change of frame whose information
            product is not taken yet: the information of ``x`` is then ``G^T info G``
            (:meth:`information`). The next join folds ``G`` into its own products, which
            saves a relabelling and a sort of the whole information per level.
    """

    dim: int
    frame_ids: IntArray
    end_ids: IntArray
    var_ptr: IntArray
    ids: IntArray
    kinds: npt.NDArray[np.int8]
    x: FloatArray
    info: sp.csr_matrix
    names: tuple[str, ...]
    jacobian: sp.csr_matrix | None = None

    @classmethod
    def of_maps(cls, maps: Sequence[LocalMap]) -> MapBatch:
        """Put ``maps`` side by side.

        Raises:
            InvalidMapError: the maps differ in dimension.
        """
        dim = maps[0].dim
        for m in maps:
            if m.dim != dim:
                raise InvalidMapError(f"cannot join a {dim}D map {maps[0].name!r} with a {m.dim}D map {m.name!r}")
        starts = np.concatenate([[0], np.cumsum([m.state_dim for m in maps])])
        info = _block_diagonal([m.info for m in maps], starts)
        return cls(
            dim,
            np.array([m.frame_id for m in maps], dtype=np.int64),
            np.array([NO_END if m.end_id is None else m.end_id for m in maps], dtype=np.int64),
            np.concatenate([[0], np.cumsum([m.n_vars for m in maps])]).astype(np.int64),
            np.concatenate([m.ids for m in maps]),
            np.concatenate([m.kinds for m in maps]),
            np.concatenate([m.x for m in maps]),
            info,
            tuple(m.name for m in maps),
        )

    @property
    def n_maps(self) -> int:
        """Number of maps ``M``."""
        return int(self.frame_ids.size)

    @cached_property
    def sizes(self) -> IntArray:
        """``(V,)`` scalars of each variable."""
        return var_sizes(self.dim, self.kinds)

    @cached_property
    def offsets(self) -> IntArray:
        """``(V,)`` first state index of each variable."""
        return var_offsets(self.sizes)

    @cached_property
    def var_map(self) -> IntArray:
        """``(V,)`` the map each variable belongs to."""
        return np.repeat(np.arange(self.n_maps, dtype=np.int64), np.diff(self.var_ptr))

    @cached_property
    def keys(self) -> IntArray:
        """``(V,)`` variable keys (:func:`~linear_slam_ros.core.local_map.var_keys`)."""
        return var_keys(self.ids, self.kinds)

    @cached_property
    def _key_codes(self) -> tuple[IntArray, IntArray, IntArray]:
        """Unique keys, and the variables sorted by ``(map, key)`` with their codes ``map * U + rank``."""
        unique, rank = np.unique(self.keys, return_inverse=True)
        codes = self.var_map * unique.size + rank
        order = np.argsort(codes, kind="stable")
        return unique, order, codes[order]

    def find(self, maps: IntArray, keys: IntArray) -> IntArray:
        """Return the variable index of key ``keys[i]`` in map ``maps[i]`` (``-1``: not there)."""
        unique, order, sorted_codes = self._key_codes
        if unique.size == 0:  # maps without variables hold nothing
            return np.full(np.shape(keys), -1, dtype=np.int64)
        rank = np.minimum(np.searchsorted(unique, keys), unique.size - 1)
        codes = maps * unique.size + rank
        pos = np.minimum(np.searchsorted(sorted_codes, codes), sorted_codes.size - 1)
        found = (unique[rank] == keys) & (sorted_codes[pos] == codes)
        return np.where(found, order[pos], -1)

    def information(self) -> sp.csr_matrix:
        """Return the ``(N, N)`` information of :attr:`x` (``G^T info G`` when a Jacobian is pending)."""
        if self.jacobian is None:
            return self.info
        g = self.jacobian
        return sp.csr_matrix(g.T) @ (self.info @ g)

    def map_at(self, j: int, name: str = GLOBAL_NAME) -> LocalMap:
        """Return map ``j`` as a :class:`LocalMap` named ``name`` (dense information up to ``DENSE_MAX`` scalars, as the
        pairwise join makes it)."""
        v0, v1 = int(self.var_ptr[j]), int(self.var_ptr[j + 1])
        s0 = int(self.offsets[v0]) if v0 < self.ids.size else int(self.x.size)
        s1 = s0 + int(self.sizes[v0:v1].sum())
        block = sp.csr_matrix(self.information()[s0:s1, s0:s1])
        block.sort_indices()
        info: InfoMatrix = block.toarray() if s1 - s0 <= DENSE_MAX else block
        end = int(self.end_ids[j])
        return LocalMap.trusted(self.dim, int(self.frame_ids[j]), None if end == NO_END else end,
                                self.ids[v0:v1].copy(), self.kinds[v0:v1].copy(), self.x[s0:s1].copy(), info, name)


def _block_diagonal(blocks: Sequence[InfoMatrix], starts: IntArray) -> sp.csr_matrix:
    """Return the ``(N, N)`` CSR matrix with ``blocks[j]`` at rows and columns ``starts[j]:starts[j + 1]``.

    Dense blocks contribute every entry, laid out without a loop over their rows.
    """
    n = int(starts[-1])
    if all(not sp.issparse(b) for b in blocks):
        sizes = np.diff(starts)
        row_len = np.repeat(sizes, sizes)  # each row of block j has sizes[j] entries
        indptr = np.concatenate([[0], np.cumsum(row_len)])
        entry_block = np.repeat(np.arange(sizes.size), sizes * sizes)
        first = np.concatenate([[0], np.cumsum(sizes * sizes)])[:-1]
        within = np.arange(int(indptr[-1])) - first[entry_block]
        indices = starts[:-1][entry_block] + within % sizes[entry_block]
        data = np.concatenate([np.asarray(b, dtype=np.float64).ravel() for b in blocks])
        return sp.csr_matrix((data, indices, indptr), shape=(n, n))
    parts = [sp.coo_matrix(b) for b in blocks]
    rows = np.concatenate([p.row + start for p, start in zip(parts, starts[:-1].tolist(), strict=False)])
    cols = np.concatenate([p.col + start for p, start in zip(parts, starts[:-1].tolist(), strict=False)])
    return sp.csr_matrix((np.concatenate([p.data for p in parts]), (rows, cols)), shape=(n, n))


def change_frames(batch: MapBatch, maps: IntArray, slots: IntArray) -> MapBatch:
    """Re-express each map ``maps[i]`` in the frame of its pose variable ``slots[i]`` (eqs. 18-21), all at once.

    What :func:`~linear_slam_ros.core.frames.change_frame` does to one map, vectorised over
    maps: every other variable is seen from the new frame pose, whose slot receives the old
    origin; the information becomes ``G^T I G`` with ``G`` the Jacobian of the reverse change
    at the new estimate (block diagonal plus each moved map's dense slot column). That
    product is left to the next join (:attr:`MapBatch.jacobian`; :meth:`MapBatch.information`
    takes it).

    Args:
        batch: the maps.
        maps: ``(C,)`` distinct indices of the maps that move.
        slots: ``(C,)`` global variable index of each one's new frame pose (a pose of that map).
    """
    if maps.size == 0:
        return batch
    dim, d, p = batch.dim, batch.dim, pose_size(batch.dim)
    a = p - d
    offsets, kinds = batch.offsets, batch.kinds
    moved_of_map = np.full(batch.n_maps, -1, dtype=np.int64)
    moved_of_map[maps] = np.arange(maps.size)
    c_of_var = moved_of_map[batch.var_map]
    is_slot = np.zeros(kinds.size, dtype=bool)
    is_slot[slots] = True
    others = np.flatnonzero((c_of_var >= 0) & ~is_slot)  # variables that move, slots excluded
    c = c_of_var[others]
    pos_idx = offsets[others][:, None] + np.arange(d)  # (k, d)
    pose_others = kinds[others] == POSE
    ang_vars = others[pose_others]
    c_ang = c[pose_others]
    ang_idx = offsets[ang_vars][:, None] + np.arange(d, p)  # (m, a)
    slot_pos = offsets[slots][:, None] + np.arange(d)
    slot_ang = offsets[slots][:, None] + np.arange(d, p)

    # the estimate: reframe
    x = batch.x
    t_frame, ang_frame = x[slot_pos], x[slot_ang]
    rot = rotation(dim, ang_frame)  # (C, d, d)
    x_new = x.copy()
    x_new[pos_idx] = np.einsum("kij,kj->ki", rot[c], x[pos_idx] - t_frame[c])
    x_new[slot_pos] = -np.einsum("cij,cj->ci", rot, t_frame)
    if dim == 2:
        x_new[ang_idx[:, 0]] = wrap_angle(x[ang_idx[:, 0]] - ang_frame[c_ang, 0])
        x_new[slot_ang[:, 0]] = wrap_angle(-ang_frame[:, 0])
    else:
        x_new[ang_idx] = angles3(rot3(x[ang_idx]) @ np.swapaxes(rot[c_ang], -1, -2))
        x_new[slot_ang] = angles3(np.swapaxes(rot, -1, -2))

    # the Jacobian G of the reverse change, at the new estimate
    t_back, ang_back = x_new[slot_pos], x_new[slot_ang]
    rot_b = rotation(dim, ang_back)  # (C, d, d)
    drot_b = drotation(dim, ang_back)  # (C, a, d, d)
    diff = x_new[pos_idx] - t_back[c]  # (k, d)
    pos_frame = np.empty((others.size, d, p))
    pos_frame[:, :, :d] = -rot_b[c]
    pos_frame[:, :, d:] = np.einsum("kjab,kb->kaj", drot_b[c], diff)
    slot = np.zeros((maps.size, p, p))
    slot[:, :d, :d] = -rot_b
    slot[:, :d, d:] = -np.einsum("cjab,cb->caj", drot_b, t_back)
    ang_frame_blk = np.zeros((ang_vars.size, a, p))
    self_blocks = []  # 2D pose angles: the identity on themselves (kept with the scalars that do not move)
    if dim == 2:
        ang_frame_blk[:, 0, 2] = -1.0
        slot[:, 2, 2] = -1.0
    else:
        rot_bt = np.swapaxes(rot_b, -1, -2)
        rot_v, drot_v = rot3_and_drot3(x_new[ang_idx])
        rels = rot_v @ rot_bt[c_ang]
        directions = np.empty((ang_vars.size, 6, 3, 3))
        np.matmul(drot_v, rot_bt[c_ang][:, None], out=directions[:, :3])
        np.matmul(rot_v[:, None], np.swapaxes(drot_b[c_ang], -1, -2), out=directions[:, 3:])
        both = dangles3(rels, directions)  # (m, 3, 6)
        self_blocks.append((ang_idx[:, :, None], ang_idx[:, None, :], both[:, :, :3]))
        ang_frame_blk[:, :, 3:] = both[:, :, 3:]
        slot[:, 3:, 3:] = dangles3(rot_bt, np.swapaxes(drot_b, -1, -2))  # (C, 3, 3)

    # G as COO: the identity on the scalars that do not move, the blocks above on those that do
    n = x.size
    still = np.ones(n, dtype=bool)
    still[pos_idx.ravel()] = False
    still[slot_pos.ravel()] = False
    still[slot_ang.ravel()] = False
    if dim == 3:
        still[ang_idx.ravel()] = False
    frame_cols = np.concatenate([slot_pos, slot_ang], axis=1)  # (C, p)
    parts = [
        (pos_idx[:, :, None], pos_idx[:, None, :], rot_b[c]),
        (pos_idx[:, :, None], frame_cols[c][:, None, :], pos_frame),
        (ang_idx[:, :, None], frame_cols[c_ang][:, None, :], ang_frame_blk),
        (frame_cols[:, :, None], frame_cols[:, None, :], slot),
        *self_blocks,
    ]
    still_idx = np.flatnonzero(still)
    rows = np.concatenate([still_idx] + [np.broadcast_to(r, v.shape).ravel() for r, _, v in parts])
    cols = np.concatenate([still_idx] + [np.broadcast_to(cc, v.shape).ravel() for _, cc, v in parts])
    vals = np.concatenate([np.ones(still_idx.size)] + [v.ravel() for _, _, v in parts])
    g = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))
    if batch.jacobian is not None:  # two changes in a row: compose them
        g = batch.jacobian @ g
    ids = batch.ids.copy()
    ids[slots] = batch.frame_ids[maps]
    frame_ids = batch.frame_ids.copy()
    frame_ids[maps] = batch.ids[slots]
    return MapBatch(dim, frame_ids, batch.end_ids, batch.var_ptr, ids, kinds, x_new, batch.info, batch.names, g)


def join_pairs(batch: MapBatch) -> MapBatch:
    """Join maps ``(0, 1), (2, 3), ...`` of a batch whose pairs share a frame, by linear least squares.

    Pair ``(2g, 2g + 1)`` becomes map ``g``: the earlier map's variables in their order, then
    the later map's new ones (:func:`~linear_slam_ros.joining.pairwise.join_in_shared_frame`);
    an odd last map moves up as it is. One sparse solve for all pairs (the information is block
    diagonal by pair).

    Raises:
        InvalidMapError: a pair's maps are in different frames.
        SolverError: a joined information matrix is not positive definite.
    """
    n_maps = batch.n_maps
    n_pairs = n_maps // 2
    later = np.arange(1, 2 * n_pairs, 2)
    bad = np.flatnonzero(batch.frame_ids[later - 1] != batch.frame_ids[later])
    if bad.size:
        j = int(later[bad[0]])
        raise InvalidMapError(
            f"maps {batch.names[j - 1]!r} and {batch.names[j]!r} are in frames {int(batch.frame_ids[j - 1])} and "
            f"{int(batch.frame_ids[j])}; align them first"
        )
    var_map, sizes, offsets = batch.var_map, batch.sizes, batch.offsets
    group = var_map // 2
    is_later = (var_map % 2 == 1) & (var_map < 2 * n_pairs)
    # the later map's variables the earlier one holds
    match = np.full(var_map.size, -1, dtype=np.int64)
    later_vars = np.flatnonzero(is_later)
    match[later_vars] = batch.find(var_map[later_vars] - 1, batch.keys[later_vars])
    defining = match < 0  # the variables of the joined maps, in order within each group
    n_groups = (n_maps + 1) // 2
    per_group = np.bincount(group[defining], minlength=n_groups)
    group_start = np.concatenate([[0], np.cumsum(per_group)])
    target = np.empty(var_map.size, dtype=np.int64)
    def_idx = np.flatnonzero(defining)
    target[def_idx] = np.arange(def_idx.size)  # groups follow each other, so this is their order within each
    target[~defining] = target[match[~defining]]
    new_ids = batch.ids[def_idx]
    new_kinds = batch.kinds[def_idx]
    new_sizes = var_sizes(batch.dim, new_kinds)
    new_offsets = var_offsets(new_sizes)
    n = batch.x.size
    n_new = int(new_sizes.sum())
    sc_map = np.repeat(new_offsets[target] - offsets, sizes) + np.arange(n)

    z = batch.x
    common = ~defining
    if common.any():  # Remark 3: a common angle is observed within pi of the earlier map's
        is_pose = batch.kinds[common] == POSE
        later_poses = np.flatnonzero(common)[is_pose]
        d, p = batch.dim, pose_size(batch.dim)
        if later_poses.size:
            ang_b = (offsets[later_poses][:, None] + np.arange(d, p)).ravel()
            ang_a = (offsets[match[later_poses]][:, None] + np.arange(d, p)).ravel()
            z = z.copy()
            z[ang_b] = z[ang_a] + wrap_angle(z[ang_b] - z[ang_a])
    # The joined information is P^T I P, P the (N, N') 0/1 matrix of sc_map (overlaps summed), and
    # with a pending change of frame G it is (G P)^T I (G P). G P is G with its columns relabelled:
    # a row of G touches one map only, and P merges scalars of two different maps, so no two
    # entries of a row of G P fall together.
    g = batch.jacobian if batch.jacobian is not None else sp.identity(n, format="csr")
    moved = sp.csr_matrix((g.data, sc_map[g.indices], g.indptr), shape=(n, n_new))
    product = (moved.T.tocsr() @ (batch.info @ moved)).tocsc()  # (N', N'); the transposition sorts the indices
    joined = sp.csr_matrix((product.data, product.indices, product.indptr), shape=(n_new, n_new))  # its transpose
    joined.has_sorted_indices = True
    # Solved for the correction to a start point x0 (each variable's value in the map that defines it), not for
    # absolute coordinates: the same solution, but the right-hand side is the maps' disagreement, not their
    # coordinates, so round-off does not grow with the lever arms (an absolute solve drifted from the pairwise
    # tree by about 10x per level, off by decimetres on a noise-free chain of 12,800 steps: README, "Design").
    defining_scalars = np.repeat(defining, sizes)
    x0 = np.empty(n_new)
    x0[sc_map[defining_scalars]] = z[defining_scalars]
    rhs = np.asarray(moved.T @ (batch.info @ (g @ (z - x0[sc_map]))), dtype=np.float64)
    x = x0 + solve_sparse_spd(product, rhs)
    first = np.arange(0, n_maps, 2)
    nxt = first + 1
    ends = batch.end_ids[first].copy()
    has_later = nxt < n_maps
    later_end = batch.end_ids[nxt[has_later]]
    ends[has_later] = np.where(later_end != NO_END, later_end, ends[has_later])
    names = tuple(GLOBAL_NAME if 2 * g + 1 < n_maps else batch.names[2 * g] for g in range(n_groups))
    return MapBatch(batch.dim, batch.frame_ids[first], ends, group_start.astype(np.int64), new_ids, new_kinds, x,
                    joined, names)


def _share_frames(batch: MapBatch) -> MapBatch:
    """Bring each pair ``(2g, 2g + 1)`` into one frame, as :func:`~linear_slam_ros.joining.pairwise.join_at_seam` does.

    Raises:
        FrameError: a pair shares no frame (the message names both maps and poses).
    """
    moves: dict[int, int] = {}  # map -> the pose it moves to
    n_pairs = batch.n_maps // 2
    first = np.arange(0, 2 * n_pairs, 2)
    second = first + 1
    f_a, f_b, seam = batch.frame_ids[first], batch.frame_ids[second], batch.end_ids[first]
    # which of the poses involved each map holds
    seam_key = 2 * np.where(seam == NO_END, 0, seam) + POSE
    holds_seam_a = batch.find(first, seam_key) >= 0
    holds_seam_b = batch.find(second, seam_key) >= 0
    holds_fa_b = batch.find(second, 2 * f_a + POSE) >= 0
    holds_fb_a = batch.find(first, 2 * f_b + POSE) >= 0
    for g in np.flatnonzero(f_a != f_b).tolist():  # in pair order: the first failing pair is named, as the tree does
        a, b = 2 * g, 2 * g + 1
        fa, fb, s = int(f_a[g]), int(f_b[g]), int(seam[g])
        if s != NO_END:
            if fb != s and not holds_seam_b[g]:
                raise FrameError(
                    f"map {batch.names[b]!r} (frame pose {fb}) does not hold pose {s}, the end pose of map "
                    f"{batch.names[a]!r} (frame pose {fa}): the maps share no frame"
                )
            if fa != s and not holds_seam_a[g]:
                raise FrameError(
                    f"cannot change map {batch.names[a]!r} (frame pose {fa}) to the frame of pose {s}: that pose "
                    "is not in the map"
                )
            if fa != s:
                moves[a] = s
            if fb != s:
                moves[b] = s
        elif holds_fa_b[g]:
            moves[b] = fa
        elif holds_fb_a[g]:
            moves[a] = fb
        else:
            raise FrameError(
                f"map {batch.names[b]!r} is in the frame of pose {fb}, which is not in map {batch.names[a]!r} "
                f"(frame pose {fa}), and pose {fa} is not in {batch.names[b]!r} either: the maps share no frame"
            )
    if not moves:
        return batch
    maps = np.fromiter(moves, dtype=np.int64, count=len(moves))
    poses = np.fromiter(moves.values(), dtype=np.int64, count=len(moves))
    slots = batch.find(maps, 2 * poses + POSE)
    assert bool(np.all(slots >= 0)), "every move was checked above"
    return change_frames(batch, maps, slots)


def divide_and_conquer_levels(
    maps: Sequence[LocalMap], on_level: Callable[[float, int], None] | None = None
) -> LocalMap:
    """Join pose maps by divide and conquer, level by level, without a final transform.

    The same tree and the same result (up to round-off) as
    ``divide_and_conquer(maps, join_at_seam)``; the result is in the frame its last join left it in.

    Args:
        maps: local maps in order; map ``i + 1`` starts where map ``i`` ends.
        on_level: called after each level with its wall time (s) and its number of pairwise joins.

    Raises:
        InvalidMapError: ``maps`` is empty, or the maps differ in dimension.
        FrameError: neighbours share no frame.
    """
    if not maps:
        raise InvalidMapError("no local maps to join")
    if len(maps) == 1:
        return maps[0]
    batch = MapBatch.of_maps(maps)
    while batch.n_maps > 1:
        t0 = time.perf_counter()
        pairs = batch.n_maps // 2
        batch = join_pairs(_share_frames(batch))
        if on_level is not None:
            on_level(time.perf_counter() - t0, pairs)
    return batch.map_at(0)
