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

from linear_slam_ros.core.errors import FrameError
from linear_slam_ros.core.geometry import angles3, dangles3, drot3, pose_size, rot3, single_rotation, wrap_angle
from linear_slam_ros.core.local_map import POSE, InfoMatrix, LocalMap, pose_key, var_offsets, var_sizes

DENSE_MATMUL_MAX = 64
"""Up to this size ``G^T I G`` is two dense BLAS products; above, ``G`` is used as sparse."""

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
        x_new[ang_idx] = angles3(rot3(x[ang_idx]) @ rot.T)
        x_new[frame_cols[3:]] = angles3(rot.T)
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

    def csr(self, n: int, transpose: bool = False) -> sp.csr_matrix:
        """Return the ``(n, n)`` Jacobian (or its transpose) as CSR."""
        pos_idx, ang_idx, frame_cols = self.layout
        k, d = pos_idx.shape
        parts = [
            (pos_idx[:, :, None], pos_idx[:, None, :], np.broadcast_to(self.rot, (k, d, d))),
            (pos_idx[:, :, None], frame_cols[None, None, :], self.pos_frame),
            (ang_idx[:, :, None], ang_idx[:, None, :], self.ang_self),
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
    pos_frame[:, :, d:] = np.einsum("kij,nj->nik", drot, x[pos_idx] - t_frame)
    slot = np.zeros((p, p))
    slot[:d, :d] = -rot
    slot[:d, d:] = -np.einsum("kij,j->ik", drot, t_frame)
    ang_frame_blk = np.zeros((m, p - d, p))
    if dim == 2:
        ang_self = np.ones((m, 1, 1))
        ang_frame_blk[:, 0, 2] = -1.0
        slot[2, 2] = -1.0
    else:
        ang_v = x[ang_idx]
        rot_v = rot3(ang_v)
        rel = rot_v @ rot.T
        ang_self = dangles3(rel, drot3(ang_v) @ rot.T)
        ang_frame_blk[:, :, 3:] = dangles3(rel, rot_v[:, None, :, :] @ np.swapaxes(drot, -1, -2)[None])
        slot[3:, 3:] = dangles3(rot.T, np.swapaxes(drot, -1, -2))
    return FrameJacobian(layout, rot, pos_frame, ang_self, ang_frame_blk, slot)


def transform_information(info: InfoMatrix, back: FrameJacobian) -> InfoMatrix:
    """Return ``G^T I G`` for the reverse-change Jacobian ``G`` (eq. 20).

    Dense information stays dense (BLAS products, ``G`` dense for small maps, sparse above
    :data:`DENSE_MATMUL_MAX`); sparse information stays CSR.
    """
    n = info.shape[0]
    if not sp.issparse(info):
        if n <= DENSE_MATMUL_MAX:
            g = back.dense(n)
            out = g.T @ np.asarray(info) @ g
        else:
            g_t = back.csr(n, transpose=True)
            out = g_t @ (g_t @ np.asarray(info)).T  # G^T (I G), I symmetric
        return 0.5 * (out + out.T)
    g_t = back.csr(n, transpose=True)
    # G^T I G is symmetric up to round-off (1e-16 relative); the solvers read one triangle and
    # the message encoder the upper one, so it is not symmetrised here (a transpose and an add
    # on the largest matrices of divide and conquer).
    return (g_t @ info.tocsr() @ g_t.T).tocsr()


def change_frame(local_map: LocalMap, new_frame_id: int) -> LocalMap:
    """Re-express a map in the frame of its pose ``new_frame_id`` (eqs. 18-21).

    The old frame pose becomes a variable in the slot of ``new_frame_id``; information is
    carried through the reverse Jacobian, so the map stays exactly equivalent to first order.

    Raises:
        FrameError: ``new_frame_id`` is not a pose variable of the map.
    """
    if new_frame_id == local_map.frame_id:
        return local_map
    slot = local_map.index_of(pose_key(new_frame_id))
    if slot is None:
        raise FrameError(
            f"cannot change map {local_map.name!r} (frame pose {local_map.frame_id}) to the frame of "
            f"pose {new_frame_id}: that pose is not in the map"
        )
    dim, kinds = local_map.dim, local_map.kinds
    n = local_map.state_dim
    if not sp.issparse(local_map.info) and n <= DENSE_MATMUL_MAX:
        # Small dense map: include the slot in the vectorised blocks (its rows are overwritten
        # by the slot's own block), which saves building a layout without it.
        off = int(local_map.offsets[slot])
        layout = Layout(local_map.position_index, local_map.angle_index, off + np.arange(pose_size(dim)))
    else:
        layout = frame_layout(dim, kinds, slot, local_map.offsets)
    x_new = reframe(dim, local_map.x, layout)
    info = transform_information(local_map.info, reframe_jacobian(dim, x_new, layout))
    ids = local_map.ids.copy()
    ids[slot] = local_map.frame_id
    return local_map.replace(frame_id=int(new_frame_id), ids=ids, x=x_new, info=info)  # same kinds: same layout
