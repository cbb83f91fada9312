"""Closed-form change of a map's frame to one of its own poses (eqs. 18-21 of Linear SLAM).

A map in the frame of pose ``a`` that holds pose ``b`` can be re-expressed in the frame of ``b``:
every other variable ``v`` becomes ``v`` seen from ``b``, and the slot of ``b`` now holds pose
``a`` seen from ``b``. The information follows by ``I_b = G^T I_a G`` with ``G`` the Jacobian of
the reverse change (from ``b``'s frame back to ``a``'s), evaluated at the new estimate: eq. (20)
with ``nabla = G``. ``G`` is block diagonal plus one dense column block (the new origin's slot),
which is why every change of frame couples that slot with every variable.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError, GeometryError, InvalidMapError
from linear_slam_ros.core.geometry import angles3, dangles3, pose_size, rot3, rot3_and_drot3, single_rotation, wrap_angle
from linear_slam_ros.core.limits import DEFAULT_LIMITS, DEFINITE_ONLY
from linear_slam_ros.core.local_map import (
    POSE,
    InfoMatrix,
    LocalMap,
    VariableLayout,
    check_information,
    csr_from_arrays,
    pose_key,
    seed_key_lookup,
    var_offsets,
    var_sizes,
)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class Layout(NamedTuple):
    """Index arrays of a state layout around the slot of a new frame pose.

    Attributes:
        pos_idx: ``(k, d)`` indices of feature positions and pose translations (slot excluded,
            except in the dense path, where the slot's entries are written last and win).
        ang_idx: ``(m, a)`` indices of pose angles (slot excluded likewise).
        frame_cols: ``(p,)`` indices of the slot's scalars.
    """

    pos_idx: IntArray
    ang_idx: IntArray
    frame_cols: IntArray


def frame_layout(dim: int, kinds: npt.NDArray[np.int8], slot: int, offsets: IntArray | None = None) -> Layout:
    """Return the :class:`Layout` of a state whose pose variable ``slot`` becomes the frame.

    Args:
        dim: 2 or 3.
        kinds: ``(m,)`` variable kinds.
        slot: index of the pose variable that becomes the frame.
        offsets: ``(m,)`` state offsets of the variables, when already known.
    """
    d = dim
    p = pose_size(dim)
    if offsets is None:
        offsets = var_offsets(var_sizes(dim, kinds))
    keep = np.ones(kinds.shape, dtype=bool)
    keep[slot] = False
    pos_idx = offsets[keep][:, None] + np.arange(d)
    ang_idx = offsets[keep & (kinds == POSE)][:, None] + np.arange(d, p)
    return Layout(pos_idx, ang_idx, int(offsets[slot]) + np.arange(p))


def reframe(dim: int, x: FloatArray, layout: Layout) -> FloatArray:
    """Express a state in the frame of the pose in ``layout.frame_cols``.

    Feature positions and pose translations transform alike, ``R_T (p - t_T)``; pose
    orientations become ``angles(R R_T^T)``; the frame's slot receives the old origin seen from
    the new frame, ``(-R_T t_T, angles(R_T^T))``.

    Args:
        dim: 2 or 3.
        x: ``(n,)`` state in the current frame.
        layout: :func:`frame_layout` of the state.

    Returns:
        ``(n,)`` the state in the new frame, angles wrapped.
    """
    d = dim
    pos_idx, ang_idx, frame_cols = layout
    t_frame = x[frame_cols[:d]]
    ang_frame = x[frame_cols[d:]]
    rot, _ = single_rotation(dim, ang_frame)
    x_new = np.empty_like(x)
    x_new[pos_idx] = (x[pos_idx] - t_frame) @ rot.T
    x_new[frame_cols[:d]] = -rot @ t_frame
    if dim == 2:
        x_new[ang_idx[:, 0]] = wrap_angle(x[ang_idx[:, 0]] - ang_frame[0])
        x_new[frame_cols[2]] = wrap_angle(-ang_frame[0])
    else:
        m = ang_idx.shape[0]
        rels = np.empty((m + 1, 3, 3))  # the poses' orientations seen from the frame, and the old origin's
        np.matmul(rot3(x[ang_idx]), rot.T, out=rels[:m])
        rels[m] = rot.T
        ang = angles3(rels)
        x_new[ang_idx] = ang[:m]
        x_new[frame_cols[3:]] = ang[m]
    return x_new


class FrameJacobian(NamedTuple):
    """Jacobian ``d reframe(x) / d x``: block diagonal plus the dense column block of the slot.

    Attributes:
        layout: the state layout.
        rot: ``(d, d)`` block of every translation-like entry on itself.
        pos_frame: ``(k, d, p)`` blocks of translation-like entries on the slot.
        ang_self: ``(m, a, a)`` blocks of pose angles on themselves.
        ang_frame: ``(m, a, p)`` blocks of pose angles on the slot (translation columns zero).
        slot: ``(p, p)`` block of the slot on itself.
    """

    layout: Layout
    rot: FloatArray
    pos_frame: FloatArray
    ang_self: FloatArray
    ang_frame: FloatArray
    slot: FloatArray

    def dense(self, n: int) -> FloatArray:
        """Return the ``(n, n)`` Jacobian as a dense array."""
        pos_idx, ang_idx, frame_cols = self.layout
        jac = np.zeros((n, n))
        jac[pos_idx[:, :, None], pos_idx[:, None, :]] = self.rot
        jac[pos_idx[:, :, None], frame_cols[None, None, :]] = self.pos_frame
        jac[ang_idx[:, :, None], ang_idx[:, None, :]] = self.ang_self
        jac[ang_idx[:, :, None], frame_cols[None, None, :]] = self.ang_frame
        jac[frame_cols[:, None], frame_cols[None, :]] = self.slot
        return jac

    def column(self, n: int) -> FloatArray:
        """Return the ``(n, p)`` columns of the slot (the Jacobian's only dense block)."""
        pos_idx, ang_idx, frame_cols = self.layout
        out = np.zeros((n, frame_cols.size))
        out[pos_idx] = self.pos_frame
        out[ang_idx] = self.ang_frame
        out[frame_cols] = self.slot
        return out

    def csr(self, n: int, transpose: bool = False) -> sp.csr_matrix:
        """Return the ``(n, n)`` Jacobian (or its transpose) as CSR."""
        return self._csr(n, transpose, with_slot=True)

    def block_diagonal(self, n: int, transpose: bool = False) -> sp.csr_matrix:
        """Return the Jacobian without the slot's columns (its block-diagonal part ``D``), or ``D^T``, as CSR.

        ``D`` has no entry in the slot's rows or columns: the Jacobian is ``D`` plus
        :meth:`column` in the slot's columns.
        """
        return self._csr(n, transpose, with_slot=False)

    def _csr(self, n: int, transpose: bool, with_slot: bool) -> sp.csr_matrix:
        pos_idx, ang_idx, frame_cols = self.layout
        k, d = pos_idx.shape
        parts = [
            (pos_idx[:, :, None], pos_idx[:, None, :], np.broadcast_to(self.rot, (k, d, d))),
            (ang_idx[:, :, None], ang_idx[:, None, :], self.ang_self),
        ]
        if with_slot:
            parts += [
                (pos_idx[:, :, None], frame_cols[None, None, :], self.pos_frame),
                (ang_idx[:, :, None], frame_cols[None, None, :], self.ang_frame),
                (frame_cols[None, :, None], frame_cols[None, None, :], self.slot[None]),
            ]
        rows = np.concatenate([np.broadcast_to(r, v.shape).ravel() for r, _, v in parts])
        cols = np.concatenate([np.broadcast_to(c, v.shape).ravel() for _, c, v in parts])
        vals = np.concatenate([v.ravel() for _, _, v in parts])
        if transpose:
            rows, cols = cols, rows
        return sp.csr_matrix((vals, (rows, cols)), shape=(n, n))


def reframe_jacobian(dim: int, x: FloatArray, layout: Layout) -> FrameJacobian:
    """Return the exact Jacobian of :func:`reframe` at ``x``."""
    d = dim
    p = pose_size(dim)
    pos_idx, ang_idx, frame_cols = layout
    t_frame = x[frame_cols[:d]]
    ang_frame = x[frame_cols[d:]]
    rot, drot = single_rotation(dim, ang_frame)  # (d, d), (a, d, d)
    k = pos_idx.shape[0]
    m = ang_idx.shape[0]
    pos_frame = np.empty((k, d, p))
    pos_frame[:, :, :d] = -rot
    diff = x[pos_idx] - t_frame  # (k, d)
    slot = np.zeros((p, p))
    slot[:d, :d] = -rot
    ang_frame_blk = np.zeros((m, p - d, p))
    if dim == 2:
        pos_frame[:, :, 2] = diff @ drot[0].T
        slot[:2, 2] = -(drot[0] @ t_frame)
        ang_self = np.ones((m, 1, 1))
        ang_frame_blk[:, 0, 2] = -1.0
        slot[2, 2] = -1.0
    else:
        pos_frame[:, :, d:] = np.matmul(diff, np.swapaxes(drot, -1, -2)).transpose(1, 2, 0)
        slot[:d, d:] = -(drot @ t_frame).T
        ang_v = x[ang_idx]
        rot_v, drot_v = rot3_and_drot3(ang_v)
        # One dangles3 for all: each pose along its own angles then the slot's, and (last row)
        # the slot's own orientation along its angles.
        rels = np.empty((m + 1, 3, 3))
        np.matmul(rot_v, rot.T, out=rels[:m])
        rels[m] = rot.T
        directions = np.zeros((m + 1, 6, 3, 3))
        np.matmul(drot_v, rot.T, out=directions[:m, :3])
        np.matmul(rot_v[:, None, :, :], np.swapaxes(drot, -1, -2), out=directions[:m, 3:])
        directions[m, :3] = np.swapaxes(drot, -1, -2)
        both = dangles3(rels, directions)  # (m + 1, 3, 6)
        ang_self = both[:m, :, :3]
        ang_frame_blk[:, :, 3:] = both[:m, :, 3:]
        slot[3:, 3:] = both[m, :, :3]
    return FrameJacobian(layout, rot, pos_frame, ang_self, ang_frame_blk, slot)


def _times_jacobian(matrix: FloatArray, back: FrameJacobian, column: FloatArray) -> FloatArray:
    """Return ``matrix @ G`` for a dense ``(n, n)`` matrix, using the structure of ``G``.

    ``G`` is block diagonal (the rotation on every translation-like pair of scalars, the angle
    blocks on pose angles; the slot's own blocks included, then overwritten) plus the dense
    column block ``column`` (``(n, p)``, the slot's columns of ``G``).
    """
    pos_idx, ang_idx, frame_cols = back.layout
    out = matrix.copy()  # 2D pose angles: identity blocks
    out[:, pos_idx] = matrix[:, pos_idx] @ back.rot
    if back.rot.shape[0] == 3:
        out[:, ang_idx] = (matrix[:, ang_idx][:, :, None, :] @ back.ang_self)[:, :, 0, :]
    out[:, frame_cols] = matrix @ column
    return out


def transform_information(info: InfoMatrix, back: FrameJacobian) -> InfoMatrix:
    """Return ``G^T I G`` for the reverse-change Jacobian ``G`` (eq. 20).

    Dense information stays dense: ``I G`` and ``G^T (I G)`` are taken block by block (a product
    with the rotation on all translation-like scalars at once, one with the slot's column block),
    never with ``G`` as a matrix, and the result is symmetrised. Sparse information stays sparse:
    the result is CSR with sorted indices and no duplicates, the form the joins assemble from.
    """
    n = info.shape[0]
    if not sp.issparse(info):
        column = back.column(n)
        right = _times_jacobian(np.asarray(info), back, column)  # I G
        out = _times_jacobian(np.ascontiguousarray(right.T), back, column)  # (G^T I G)^T = (I G)^T G
        out += out.T
        out *= 0.5
        return out
    # G = D + C S, with D block diagonal (no entry in the slot's rows or columns), C the slot's
    # dense column block and S the selection of the slot's columns:
    #   G^T I G = D^T I D + (D^T I C) S + S^T (C^T I D) + S^T (C^T I C) S.
    # D^T I D stays within the blocks of I's pattern (two products with at most three entries a
    # row); the rest is the slot's rows and columns, from the dense (n, p) block I C. Half the
    # work of the products with G, whose dense column block every row of G holds.
    d_t = back.block_diagonal(n, transpose=True)
    moved = d_t @ info @ d_t.T.tocsr()
    moved.sort_indices()  # the products leave each row's indices unsorted
    # G^T I G is symmetric up to round-off (1e-16 relative); the solvers read one triangle and
    # the message encoder the upper one, so it is not symmetrised. The sum of two CSR matrices
    # with sorted indices is sorted, without duplicates: the form the joins assemble from.
    total: sp.csr_matrix = (moved + _slot_lines(info, back, d_t)).tocsr()
    return total


def _slot_lines(info: sp.csr_matrix, back: FrameJacobian, d_t: sp.csr_matrix) -> sp.csr_matrix:
    """Return the slot's rows and columns of ``G^T I G`` (every other entry absent) as CSR with sorted indices.

    Args:
        info: ``(n, n)`` sparse information in the old frame.
        back: the reverse-change Jacobian ``G``.
        d_t: ``back.block_diagonal(n, transpose=True)``.
    """
    n = info.shape[0]
    frame_cols = back.layout.frame_cols
    p = frame_cols.size
    column = back.column(n)  # C
    info_column = np.asarray(info @ column)  # I C, (n, p)
    lines = np.asarray(d_t @ info_column)  # D^T I C: the slot's columns, zero in its rows
    lines[frame_cols] = column.T @ info_column  # C^T I C
    counts = np.full(n, p, dtype=np.int64)
    counts[frame_cols] = n
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=indptr[1:])
    indices = np.empty(indptr[-1], dtype=np.int64)
    data = np.empty(indptr[-1])
    others = np.ones(n, dtype=bool)
    others[frame_cols] = False
    at = indptr[:-1][others][:, None] + np.arange(p)  # the slot's columns of every other row
    indices[at] = frame_cols
    data[at] = lines[others]
    everything = np.arange(n)
    for j, row in enumerate(frame_cols):  # the slot's rows: the transpose of its columns
        indices[indptr[row] : indptr[row + 1]] = everything
        data[indptr[row] : indptr[row + 1]] = lines[:, j]
    out = csr_from_arrays(data, indices, indptr, n)
    out.has_sorted_indices = True
    return out


def refuse_pitch_lock(moved: VariableLayout) -> None:
    """Raise :class:`GeometryError` when a changed frame put a 3D pose at pitch +-90 deg.

    Its Euler angles are singular there: the reverse Jacobian loses rank, so the information
    carried through it would be meaningless (:data:`~linear_slam_ros.core.geometry.PITCH_LOCK_COS`).
    """
    fault = moved.pitch_lock_fault()
    if fault is not None:
        raise GeometryError(fault)


def change_frame(local_map: LocalMap, new_frame_id: int) -> LocalMap:
    """Re-express a map in the frame of its pose ``new_frame_id`` (eqs. 18-21).

    The old frame pose becomes a variable in the slot of ``new_frame_id``; information is
    carried through the reverse Jacobian, so the map stays exactly equivalent to first order.
    The new map's key lookup is derived from the old one's (one key changes), not rebuilt.

    Raises:
        FrameError: ``new_frame_id`` is not a pose variable of the map.
        GeometryError: a 3D pose would have pitch +-90 deg in the new frame (:func:`refuse_pitch_lock`).
    """
    if new_frame_id == local_map.frame_id:
        return local_map
    new_key = pose_key(new_frame_id)
    slot = _frame_slot(local_map, new_frame_id)
    dim = local_map.dim
    if not sp.issparse(local_map.info):
        # Dense map: the slot stays in the vectorised blocks (its entries are overwritten by the
        # slot's own), which saves building a layout without it.
        off = int(local_map.offsets[slot])
        layout = Layout(local_map.position_index, local_map.angle_index, off + _POSE_RANGE[dim])
    else:
        layout = frame_layout(dim, local_map.kinds, slot, local_map.offsets)
    x_new = reframe(dim, local_map.x, layout)
    info = transform_information(local_map.info, reframe_jacobian(dim, x_new, layout))
    ids = local_map.ids.copy()
    ids[slot] = local_map.frame_id
    moved = local_map.replace(frame_id=int(new_frame_id), ids=ids, x=x_new, info=info)  # same kinds: same layout
    refuse_pitch_lock(moved)
    old_key = pose_key(local_map.frame_id)
    keys = local_map.keys.copy()
    keys[slot] = old_key
    key_set = dict(local_map.key_set)
    del key_set[new_key]
    key_set[old_key] = slot
    seed_key_lookup(moved, keys, key_set)
    return moved


_POSE_RANGE = {2: np.arange(3), 3: np.arange(6)}


def estimate_in_frame(local_map: LocalMap, new_frame_id: int) -> LocalMap:
    """Return the map's estimate in the frame of its pose ``new_frame_id``, without its information.

    What :func:`change_frame` does to the variables, at a fraction of the cost (no Jacobian):
    for views that need positions only. The returned map's information is the identity (a
    placeholder; do not join it).

    Raises:
        FrameError: ``new_frame_id`` is not a pose variable of the map.
    """
    if new_frame_id == local_map.frame_id:
        return local_map
    slot = _frame_slot(local_map, new_frame_id)
    x_new = reframe(local_map.dim, local_map.x, frame_layout(local_map.dim, local_map.kinds, slot, local_map.offsets))
    ids = local_map.ids.copy()
    ids[slot] = local_map.frame_id
    placeholder = sp.identity(local_map.state_dim, format="csr")
    return local_map.replace(frame_id=int(new_frame_id), ids=ids, x=x_new, info=placeholder)


def _frame_slot(local_map: LocalMap, new_frame_id: int) -> int:
    """Return the variable index of pose ``new_frame_id`` in the map.

    Raises:
        FrameError: the pose is not a variable of the map.
    """
    slot = local_map.index_of(pose_key(new_frame_id))
    if slot is None:
        raise FrameError(
            f"cannot change map {local_map.name!r} (frame pose {local_map.frame_id}) to the frame of "
            f"pose {new_frame_id}: that pose is not in the map"
        )
    return slot


def end_frame_fault(local_map: LocalMap, max_condition: float = DEFAULT_LIMITS.max_condition) -> str | None:
    """Return why ``local_map`` cannot be joined in the frame of its end pose, where joins express it, or None.

    A change of frame carries the angles' uncertainty to every variable by its lever arm: a pose
    100 m away with heading information 1e-3 and position information 1e10 (condition 1e13, within
    the input bound) is not positive definite in double precision in its end pose's frame, and once
    joined no global map could be factorised again. Only positive definiteness is asked there: a
    far pose's information is legitimately ill-conditioned in that frame (its position across the
    lever arm follows its heading: 1 km away, heading std 0.1 rad, position std 1 cm: condition
    1e14). Checked only when the bound ``condition * (1 + L)^4`` on the moved map's condition (``L``
    the largest coordinate, m, or angle) exceeds ``max_condition`` (below it the moved map is certainly
    positive definite): never for the benchmark datasets (at most 7.7e12, VicPark200).
    """
    end = local_map.end_id
    if end is None or end == local_map.frame_id or not local_map.has_pose(end) or local_map.state_dim == 0:
        return None
    lever = float(np.abs(local_map.x).max(initial=0.0))  # angles too (at most pi: the bound only grows)
    where = f"local map {local_map.name!r} in the frame of its end pose {end} (where it is joined)"
    try:
        if local_map.condition_estimate * (1.0 + lever) ** 4 <= max_condition:
            return None
        check_information(change_frame(local_map, end).info, where, DEFINITE_ONLY)
    except (InvalidMapError, GeometryError) as exc:
        return str(exc) if str(exc).startswith(where) else f"{where}: {exc}"
    return None
